"""Normal/tangential split and friction-cone projection shared by every contact model.

Convention (all contact models): for an object surface point, ``normal`` is the unit vector along which a
positive normal force pushes the object, i.e. the object's *inward* surface normal (a point pressed into a
compliant body is pushed back out of it, towards the object's interior). Forces are in newtons, world frame.
"""

from __future__ import annotations

import torch
from torch import Tensor

from hydrosoft.geometry.se3 import safe_norm


def split_normal(v: Tensor, normal: Tensor) -> tuple[Tensor, Tensor]:
    """Split ``v (..., 3)`` into its component along ``normal (..., 3)`` (unit) and the tangential rest.

    Returns ``(v_n (...), v_t (..., 3))`` with ``v = v_n * normal + v_t``.
    """
    v_n = (v * normal).sum(-1)
    return v_n, v - v_n.unsqueeze(-1) * normal


def project_to_cone(f_n: Tensor, f_t: Tensor, mu: Tensor) -> tuple[Tensor, Tensor]:
    """Project a contact force onto the Coulomb cone (paper eq. 9 and 18-19).

    Args:
        f_n: ``(...)`` normal force in N (any sign).
        f_t: ``(..., 3)`` tangential force in N.
        mu: friction coefficient, broadcastable to ``f_n``.
    Returns:
        ``(relu(f_n), min(1, mu relu(f_n) / |f_t|) f_t)``. The ratio is only formed where it is below 1 (the force
        slips), so it is finite with finite gradients for ``f_t = 0``, ``f_n = 0`` and a tiny ``f_t`` under a large
        limit: a clamped ratio ``limit / |f_t|`` had the gradient ``0 * limit / |f_t|^2``, which is NaN once
        ``limit / |f_t|^2`` overflows (float32: a 1e-18 N shear under a 250 N limit).
    """
    f_n = torch.relu(f_n)
    limit = mu * f_n
    norm = safe_norm(f_t)
    slips = norm > limit
    scale = torch.where(slips, limit / torch.where(slips, norm, torch.ones_like(norm)), torch.ones_like(norm))
    return f_n, scale.unsqueeze(-1) * f_t
