"""Differentiable, batched cost terms for the MPC (paper Sec. IV-E, eq. 21).

Poses are ``(..., 7)`` = ``[px, py, pz, qw, qx, qy, qz]`` (metres, unit quaternion, scalar first).
Every function keeps the dtype and device of its inputs and has finite values and gradients everywhere,
zero error included (no ``sqrt(0)`` in the backward pass).
"""
from __future__ import annotations

import torch.nn.functional as F
from torch import Tensor

from hydrosoft.geometry.se3 import angle_between, safe_norm


def position_error(q: Tensor, goal: Tensor) -> Tensor:
    """Euclidean distance (m) between the positions of poses ``q`` and ``goal`` (``(..., 7)``, broadcast).

    Returns ``(...)``; the gradient is zero where the positions coincide.
    """
    return safe_norm(q[..., :3] - goal[..., :3])


def orientation_error(q: Tensor, goal: Tensor) -> Tensor:
    """Geodesic angle (rad, in [0, pi]) between the rotations of poses ``q`` and ``goal`` (``(..., 7)``).

    Returns ``(...)``; ``q`` and ``-q`` are the same rotation, and the gradient is zero where they coincide.
    """
    return angle_between(q[..., 3:], goal[..., 3:])


def pose_cost(q: Tensor, goal: Tensor, w_pos: float = 1.0, w_rot: float = 1.0) -> Tensor:
    """Weighted squared pose error ``w_pos |p - p_goal|^2 + w_rot angle^2``, shape ``(...)``.

    ``q, goal``: poses ``(..., 7)`` (broadcast); ``w_pos`` in cost/m^2, ``w_rot`` in cost/rad^2.
    """
    pos_sq = (q[..., :3] - goal[..., :3]).square().sum(-1)
    return w_pos * pos_sq + w_rot * orientation_error(q, goal).square()


def effort_cost(u: Tensor, weight: float | Tensor = 1.0) -> Tensor:
    """Quadratic action effort ``sum(weight * u^2)`` over all but the batch axis; ``u (B, ...)`` -> ``(B,)``.

    ``weight``: a scalar or a tensor broadcast against ``u``'s trailing axes, e.g. ``(6,)`` to weigh the
    translation (cost/m^2) and rotation (cost/rad^2) parts of a ``(B, M, 6)`` action differently.
    """
    return (weight * u.square()).reshape(u.shape[0], -1).sum(-1)


def hinge_cost(value: Tensor, limit: float | Tensor, weight: float, *, width: float) -> Tensor:
    """Smooth one-sided penalty ``weight * sum(softplus_w(value - limit)^2)``; ``value (B, ...)`` -> ``(B,)``.

    ``softplus_w(x) = width * log(1 + exp(x / width))`` is a smoothed ``max(x, 0)``: the penalty grows like
    ``weight * (value - limit)^2`` beyond the limit and decays exponentially below it, over a transition
    of ``width`` (same unit as ``value``: N for a force limit, m for a penetration limit). At the limit
    itself it is ``weight * (width * ln 2)^2``. ``limit`` is a scalar or broadcasts against ``value``;
    ``weight`` is in cost per squared unit of ``value``.
    """
    excess = F.softplus(value - limit, beta=1.0 / width)
    return weight * excess.square().reshape(value.shape[0], -1).sum(-1)
