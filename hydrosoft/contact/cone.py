"""Normal/tangential split and friction-cone projection shared by every contact model.

Convention (all contact models): for an object surface point, ``normal`` is the unit vector along which a
positive normal force pushes the object, i.e. the object's *inward* surface normal (a point pressed into a
compliant body is pushed back out of it, towards the object's interior). Forces are in newtons, world frame.
"""

from __future__ import annotations

import torch
from torch import Tensor

from hydrosoft.geometry.se3 import safe_norm


def split_normal(v: Tensor, normal: Tensor, axis: int = -1) -> tuple[Tensor, Tensor]:
    """Split ``v (..., 3)`` into its component along ``normal (..., 3)`` (unit) and the tangential rest.

    Returns ``(v_n (...), v_t (..., 3))`` with ``v = v_n * normal + v_t``. ``axis`` is the coordinate axis (a
    negative index): -1 as written, -2 for vectors laid out ``(..., 3, n)`` (then ``v_n`` is ``(..., n)``).
    """
    v_n = (v * normal).sum(axis)
    return v_n, v - v_n.unsqueeze(axis) * normal


def project_to_cone(f_n: Tensor, f_t: Tensor, mu: Tensor, axis: int = -1) -> tuple[Tensor, Tensor]:
    """Project a contact force onto the Coulomb cone (paper eq. 9 and 18-19).

    Args:
        f_n: ``(...)`` normal force in N (any sign).
        f_t: ``(..., 3)`` tangential force in N.
        mu: friction coefficient, broadcastable to ``f_n``.
        axis: ``f_t``'s coordinate axis (a negative index): -1 as written, -2 for ``f_t (..., 3, n)`` beside
            ``f_n (..., n)``.
    Returns:
        ``(relu(f_n), min(1, mu relu(f_n) / |f_t|) f_t)``, the scale formed as ``limit / max(|f_t|, limit)``: finite
        with finite gradients for ``f_t = 0``, ``f_n = 0`` and any shear under any limit, because every quotient in
        it and in its gradient has a denominator of at least ``|f_t|``, and ``safe_norm`` keeps that above
        ``sqrt(tiny)``. A ratio ``limit / |f_t|`` clamped at 1 instead had, where it was clamped, the gradient
        ``0 * limit / |f_t|^2``: NaN once ``limit / |f_t|^2`` overflows (float32: a 1e-18 N shear under a 250 N
        limit). Where ``|f_t|`` equals the limit exactly, ``max`` splits the gradient between the two.
    """
    f_n = torch.relu(f_n)
    limit = mu * f_n
    scale = limit / torch.maximum(safe_norm(f_t, axis), limit)
    return f_n, scale.unsqueeze(axis) * f_t
