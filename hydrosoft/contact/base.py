"""The interface shared by the four contact models, and the per-step inputs they consume."""

from __future__ import annotations

import math
from typing import NamedTuple, Protocol

from torch import Tensor


class Material(NamedTuple):
    """Per compliant body material, each ``(M,)``.

    E: normal pressure gradient in Pa/m (= N/m^3); K: tangential stiffness per area in Pa/m; mu: friction.
    """

    E: Tensor
    K: Tensor
    mu: Tensor


def check_positive_parameter(name: str, value: float, unit: str) -> None:
    """ValueError naming the contact model parameter ``name`` unless ``value`` is a positive finite number of
    ``unit``."""
    if not (isinstance(value, (int, float)) and 0 < value < math.inf):
        raise ValueError(f"{name}: must be a positive finite number of {unit}, got {value!r}")


class ContactStep(NamedTuple):
    """Geometry of one step ``k -> k+1`` for ``N`` object surface points against ``M`` compliant bodies.

    phi_prev, phi_next: ``(B, M, N)`` signed distance of each point to each body at k and k+1, metres,
        negative inside the body.
    displacement: ``(B, M, N, 3)`` ``r = p_k - p_{k+1}``: minus the motion of each point *relative to the body*
        during the step, expressed in the world frame at k+1 (paper eq. 15), metres.
    normal: ``(B, 1 or M, N, 3)`` unit inward normal of the object surface in the world frame (the direction a
        positive normal force pushes the object).
    area: ``(N,)`` area of each surface point in m^2.
    """

    phi_prev: Tensor
    phi_next: Tensor
    displacement: Tensor
    normal: Tensor
    area: Tensor


class ContactModel(Protocol):
    """A contact model maps the previous per-point forces and one step of geometry to the next forces.

    ``step(geometry, forces, material) -> forces_next``, forces ``(B, M, N, 3)`` in newtons, world frame, the
    force each body applies to each object point. Path-independent models ignore ``forces``.

    ``step(..., axis=-2)`` takes and returns every vector coordinate-major instead: forces and
    ``geometry.displacement`` ``(B, M, 3, N)``, ``geometry.normal`` ``(B, 1 or M, 3, N)`` (the distances and areas
    are unchanged). The arithmetic is the same; compiled, the buffers the backward keeps are then laid out over the
    points (``dynamics.advance_forces`` steps this way).
    """

    name: str

    def step(self, geometry: ContactStep, forces: Tensor, material: Material, axis: int = -1) -> Tensor: ...
