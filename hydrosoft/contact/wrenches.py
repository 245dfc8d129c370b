"""Net wrench of per-point contact forces (paper eq. 11-12)."""

from __future__ import annotations

import torch
from torch import Tensor


def wrench(forces: Tensor, points: Tensor, about: Tensor) -> Tensor:
    """Net wrench ``[force (3) N, torque (3) N m]`` of point forces about a reference point.

    Args:
        forces: ``(..., N, 3)`` forces in N, world frame.
        points: ``(..., N, 3)`` application points in metres, world frame (broadcastable to ``forces``).
        about: ``(..., 3)`` reference point in metres (e.g. the object's centre of mass).
    Returns:
        ``(..., 6)``. The wrench on a compliant body is minus the wrench its forces apply to the object,
        taken about that body's origin.
    """
    lever = points - about.unsqueeze(-2)
    total_force = forces.sum(-2)
    total_torque = torch.linalg.cross(lever.expand_as(forces), forces, dim=-1).sum(-2)
    return torch.cat([total_force, total_torque], dim=-1)
