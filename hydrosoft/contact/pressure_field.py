"""Path-independent hydroelastic baselines: Pressure Field (PF) and PF Frictionless (PFF), paper eq. 3-5."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import Tensor

from hydrosoft.contact.base import ContactStep, Material, check_positive_parameter
from hydrosoft.contact.cone import split_normal
from hydrosoft.geometry.se3 import safe_norm


def _normal_force(geometry: ContactStep, material: Material) -> Tensor:
    """``f_n = max(-E A phi_{k+1}, 0)``, ``(B, M, N)`` in newtons (eq. 3)."""
    E = material.E.view(1, -1, 1)
    return E * geometry.area * torch.relu(-geometry.phi_next)


@dataclass(frozen=True)
class PressureFieldFrictionless:
    """PFF: the pressure-field normal force only; never any tangential force."""

    name: ClassVar[str] = "pff"

    def step(self, geometry: ContactStep, forces: Tensor, material: Material, axis: int = -1) -> Tensor:
        """Forces ``(B, M, N, 3)``; ``forces`` (the previous state) is ignored (``ContactModel`` on ``axis``)."""
        return _normal_force(geometry, material).unsqueeze(axis) * geometry.normal


@dataclass(frozen=True)
class PressureField:
    """PF: pressure-field normal force plus kinetic Coulomb friction opposing the relative sliding (eq. 4).

    The sliding direction comes from the step's relative displacement: the object point moves by ``-r``
    relative to the body, so friction on the object points along ``+r_t``. Eq. 4 is discontinuous at zero
    slip; ``slip_tolerance`` (metres per sub-step) regularises it as ``r_t / sqrt(|r_t|^2 + slip_tolerance^2)``,
    so zero slip gives exactly zero friction and the force never leaves the cone.

    ``step`` evaluates the law at a prescribed displacement (kinematic replays: the force benchmark, the tactile
    model). In the quasi-dynamic step the friction must not come from the previous sub-step's slip: applied
    explicitly, its gain ``(h^2/epsilon) mu f_n / (m tol)`` is far above 1 and the object chatters back and forth
    across the bubble. ``implicit_friction`` tells ``dynamics`` to solve it together with the object's motion
    instead (backward Euler, ``dynamics._implicit_friction_motion``), which is stable for any step size.
    """

    slip_tolerance: float = 1e-7
    name: ClassVar[str] = "pf"
    implicit_friction: ClassVar[bool] = True

    def __post_init__(self) -> None:
        check_positive_parameter("slip_tolerance", self.slip_tolerance, "m")

    def step(self, geometry: ContactStep, forces: Tensor, material: Material, axis: int = -1) -> Tensor:
        """Forces ``(B, M, N, 3)``; ``forces`` (the previous state) is ignored (``ContactModel`` on ``axis``)."""
        f_n = _normal_force(geometry, material)
        _, r_t = split_normal(geometry.displacement, geometry.normal, axis)
        slip = torch.sqrt(safe_norm(r_t, axis) ** 2 + self.slip_tolerance**2)
        mu = material.mu.view(1, -1, 1)
        f_t = (mu * f_n / slip).unsqueeze(axis) * r_t
        return f_n.unsqueeze(axis) * geometry.normal + f_t
