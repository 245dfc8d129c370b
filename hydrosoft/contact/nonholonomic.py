"""Non-holonomic incremental hydroelastic model (NH, paper eq. 14-20), its smoothed relaxation (IV-C), and NH with
the pressure field's normal force (``NonHolonomicPressureNormal``).

Each object surface point carries a force state. Per step the displacement of the body material relative to
the point, ``r = p_k - p_{k+1}``, is split along the contact normal: the normal part loads the point with
stiffness ``E A`` and the tangential part with ``K A`` (a virtual stick spring); the sum is projected onto the
friction cone (slip), and the force is reset when the point leaves the body.

The force state lives in the world frame and is re-split against the current normal every step, so an object
rotating in contact carries its membrane forces along the world directions in which they were built up.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import Tensor

from hydrosoft.contact.base import ContactStep, Material, check_positive_parameter
from hydrosoft.contact.cone import project_to_cone, split_normal


def inside_fraction(phi_prev: Tensor, phi_next: Tensor) -> Tensor:
    """Fraction ``alpha_d`` of a straight step from ``phi_prev`` to ``phi_next`` spent inside the body (eq. 14).

    ``(relu(-phi_next) - relu(-phi_prev)) / (phi_prev - phi_next)``: 1 when both ends are inside (phi <= 0),
    0 when both are outside, the linear crossing fraction otherwise. When the step does not change phi (a
    grazing or tangential step) the ratio is 0/0; its limit is used instead: 1 if the point is inside, 0 if not.
    Shapes ``(...)``; result in ``[0, 1]`` with finite gradients everywhere.
    """
    denom = phi_prev - phi_next
    flat = denom.abs() <= torch.finfo(denom.dtype).tiny
    safe_denom = torch.where(flat, torch.ones_like(denom), denom)
    crossing = (torch.relu(-phi_next) - torch.relu(-phi_prev)) / safe_denom
    inside = (phi_prev + phi_next <= 0).to(phi_prev.dtype)
    return torch.where(flat, inside, crossing).clamp(0.0, 1.0)


def _accumulate(forces: Tensor, d: Tensor, geometry: ContactStep, material: Material, axis: int
                ) -> tuple[Tensor, Tensor]:
    """Eq. 16-19: add ``E A d_n`` and ``K A d_t`` to the split previous force and project onto the cone.

    Written with one tangential split: ``g = F + K A d`` has normal part ``g_n = f_n + K A d_n``, so the new
    normal force is ``g_n + (E - K) A d_n`` and the new tangential force ``g - g_n n``.
    """
    normal = geometry.normal
    area = geometry.area
    EA = material.E.view(1, -1, 1) * area
    KA = material.K.view(1, -1, 1) * area
    g = forces + KA.unsqueeze(axis) * d
    g_n = (g * normal).sum(axis)
    f_n = g_n + (EA - KA) * (d * normal).sum(axis)
    return project_to_cone(f_n, g - g_n.unsqueeze(axis) * normal, material.mu.view(1, -1, 1), axis)


@dataclass(frozen=True)
class NonHolonomic:
    """Exact NH model: fractional in/out steps (eq. 14-15), increments (16-17), cone (18-19), reset (20)."""

    name: ClassVar[str] = "nh"

    def stiffness_share(self, phi: Tensor) -> Tensor:
        """The share ``(...)`` of ``E A`` and ``K A`` with which a point at signed distance ``phi (...)`` (m) loads per
        unit of motion: 1 inside the body (``phi <= 0``), 0 outside."""
        return (phi <= 0).to(phi.dtype)

    def step(self, geometry: ContactStep, forces: Tensor, material: Material, axis: int = -1) -> Tensor:
        """Next forces ``(B, M, N, 3)`` from the previous ``forces (B, M, N, 3)`` (``ContactModel`` on ``axis``)."""
        alpha = inside_fraction(geometry.phi_prev, geometry.phi_next)
        f_n, f_t = _accumulate(forces, alpha.unsqueeze(axis) * geometry.displacement, geometry, material, axis)
        inside = (geometry.phi_next <= 0).to(f_n.dtype)
        return inside.unsqueeze(axis) * (f_n.unsqueeze(axis) * geometry.normal + f_t)


@dataclass(frozen=True)
class SmoothedNonHolonomic:
    """Smoothed NH (IV-C): ``alpha_d = 1`` and the reset's Heaviside replaced by ``sigmoid(-beta phi_{k+1})``.

    ``beta`` (1/m) sets the width of the transition band (about ``4/beta`` metres from 12% to 88%). Points just
    outside the body keep a small force, which gives the planner gradients before contact. The price, which the
    model benchmark measures: a point held at depth ``delta`` keeps the fraction ``sigmoid(beta delta)`` of
    its force per step, so choose ``beta >> 1/delta`` for the depths of the task (e.g. beta = 1e4/m for
    millimetre indentations).
    """

    beta: float = 1e4
    name: ClassVar[str] = "snh"

    def __post_init__(self) -> None:
        check_positive_parameter("beta", self.beta, "1/m")

    def stiffness_share(self, phi: Tensor) -> Tensor:
        """The share ``sigmoid(-beta phi) (...)`` of ``E A`` and ``K A`` with which a point at signed distance
        ``phi (...)`` (m) loads per unit of motion: every point loads, scaled by the smoothed reset."""
        return torch.sigmoid(-self.beta * phi)

    def step(self, geometry: ContactStep, forces: Tensor, material: Material, axis: int = -1) -> Tensor:
        """Next forces ``(B, M, N, 3)`` from the previous ``forces (B, M, N, 3)`` (``ContactModel`` on ``axis``)."""
        f_n, f_t = _accumulate(forces, geometry.displacement, geometry, material, axis)
        weight = torch.sigmoid(-self.beta * geometry.phi_next)
        return weight.unsqueeze(axis) * (f_n.unsqueeze(axis) * geometry.normal + f_t)


@dataclass(frozen=True)
class NonHolonomicPressureNormal:
    """NH's path-dependent shear and stick-slip (eq. 14, 15, 17, 19, reset 20) with the pressure field's normal force.

    The normal force is not integrated (eq. 16) but taken from the current penetration, ``f_n = E A max(-phi_{k+1},
    0)`` as in PF (eq. 3). NH's integrated normal force drifts wherever a contact slides without changing its depth:
    the increments ``E A d_n`` are split against the object's own normal, so a tilted face sliding along a table
    gains ``E A tan(tilt)`` per metre slid, and points crossing a body's edge leave with their force while the
    points that replace them start from zero. Here the normal force depends on the pose alone, and only the
    tangential force keeps its history: the previous force's tangential part plus ``K A d_t`` (the stick spring,
    eq. 17) projected onto the cone ``mu f_n`` (slip, eq. 19).
    """

    name: ClassVar[str] = "nh_pressure_normal"
    stiffness_share = NonHolonomic.stiffness_share

    def step(self, geometry: ContactStep, forces: Tensor, material: Material, axis: int = -1) -> Tensor:
        """Next forces ``(B, M, N, 3)`` from the previous ``forces (B, M, N, 3)`` (``ContactModel`` on ``axis``)."""
        alpha = inside_fraction(geometry.phi_prev, geometry.phi_next)
        KA = material.K.view(1, -1, 1) * geometry.area
        g = forces + (KA * alpha).unsqueeze(axis) * geometry.displacement
        _, g_t = split_normal(g, geometry.normal, axis)
        depth = torch.relu(-geometry.phi_next)
        f_n, f_t = project_to_cone(material.E.view(1, -1, 1) * geometry.area * depth, g_t,
                                   material.mu.view(1, -1, 1), axis)
        inside = (geometry.phi_next <= 0).to(f_n.dtype)
        return inside.unsqueeze(axis) * (f_n.unsqueeze(axis) * geometry.normal + f_t)
