"""Contact forces from membrane deformation (paper V-A, eq. 22-24), and the simulated sensor that feeds it.

The Soft Bubble measures how far its membrane is displaced where it touches the object. With the sensed
object and body poses, that deformation is known per object surface point: ``d_i (B, M, N, 3)`` in metres,
world frame, pointing the way the membrane pushes back (along the inward object normal when pressed). The
linear compliance model turns it into forces:

    d_n = <d, n> n,   d_t = d - d_n,   f = E A d_n + K A d_t                     (eq. 22-24)

In simulation the membrane deformation is that of the plant (the "world" model): ``deformation_from_forces``
inverts eq. 24 on the plant's force state, ``resample`` moves it onto the planner's (usually coarser) surface
points by nearest neighbour in the object frame, and ``forces_from_deformation`` applies eq. 22-24 with the
planner's own areas and materials. So the planner sees the plant's contact through the sensor model, never by
copying the plant's state.
"""

from __future__ import annotations

import torch
from torch import Tensor

from hydrosoft.contact import Material
from hydrosoft.contact.cone import split_normal


def forces_from_deformation(deformation: Tensor, normal: Tensor, area: Tensor, material: Material) -> Tensor:
    """Eq. 22-24: forces ``(B, M, N, 3)`` (N) from deformations ``(B, M, N, 3)`` (m).

    normal: ``(B, 1 or M, N, 3)`` unit inward object normals, world frame; area ``(N,)`` m^2; material per body.
    The normal part is clipped at zero: a membrane cannot pull.
    """
    d_n, d_t = split_normal(deformation, normal)
    E = material.E.view(1, -1, 1)
    K = material.K.view(1, -1, 1)
    f_n = E * area * torch.relu(d_n)
    return f_n.unsqueeze(-1) * normal + (K * area).unsqueeze(-1) * d_t


def deformation_from_forces(forces: Tensor, normal: Tensor, area: Tensor, material: Material) -> Tensor:
    """Inverse of eq. 24: the membrane deformation ``(B, M, N, 3)`` (m) that carries ``forces (B, M, N, 3)``."""
    f_n, f_t = split_normal(forces, normal)
    E = material.E.view(1, -1, 1)
    K = material.K.view(1, -1, 1)
    return (f_n / (E * area)).unsqueeze(-1) * normal + f_t / (K * area).unsqueeze(-1)


def nearest_indices(source_points: Tensor, target_points: Tensor) -> Tensor:
    """For each target point ``(N2, 3)`` the index ``(N2,)`` of the nearest source point ``(N1, 3)`` (object frame)."""
    return torch.cdist(target_points, source_points).argmin(dim=-1)


def resample(values: Tensor, index: Tensor) -> Tensor:
    """Per-point values ``(B, M, N1, 3)`` moved onto target points by ``index (N2,)`` -> ``(B, M, N2, 3)``."""
    return values.index_select(2, index)
