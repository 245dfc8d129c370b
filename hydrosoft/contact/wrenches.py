"""Net wrench of per-point contact forces (paper eq. 11-12)."""

from __future__ import annotations

import torch
from torch import Tensor

from hydrosoft.geometry.se3 import small_matmul


def wrench(forces: Tensor, points: Tensor, about: Tensor) -> Tensor:
    """Net wrench ``[force (3) N, torque (3) N m]`` of point forces about a reference point.

    Args:
        forces: ``(..., N, 3)`` forces in N, world frame.
        points: ``(..., N, 3)`` application points in metres, world frame (broadcastable to ``forces``).
        about: ``(..., 3)`` reference point in metres (e.g. the object's centre of mass).
    Returns:
        ``(..., 6)``. The wrench on a compliant body is minus the wrench its forces apply to the object,
        taken about that body's origin.

    The torque ``sum_i l_i x f_i`` (lever ``l_i = p_i - about``) is read off the antisymmetric part of the
    ``3 x 3`` moment matrix ``S = sum_i l_i f_i^T`` (one batched product over the points, much cheaper than a
    per-point cross product): ``torque = (S_yz - S_zy, S_zx - S_xz, S_xy - S_yx)``.
    """
    lever = points - about.unsqueeze(-2)
    S = small_matmul(lever.mT, forces)
    torque = torch.stack(
        [S[..., 1, 2] - S[..., 2, 1], S[..., 2, 0] - S[..., 0, 2], S[..., 0, 1] - S[..., 1, 0]], dim=-1
    )
    return torch.cat([forces.sum(-2), torque], dim=-1)
