"""The quasi-dynamic step ``x_{k+1} = f(x_k, u_k)`` of paper section IV-D, batched and differentiable.

State ``x = (object_pose (B, 7), body_poses (B, M, 7), forces (B, M, N, 3))``; control ``u (B, M, 6)``: per
compliant body a world-frame translation increment (m) and rotation-vector increment (rad) about the body's
origin. One step:

1. apply the controls to the actuated bodies;
2. sum the current contact forces into the object wrench about its centre of mass, plus gravity;
3. move the object by ``(h^2 / epsilon) M^{-1} w`` (``epsilon`` in s^2/s = s: a damping time; larger is
   slower and more stable), restricted to (x, y, yaw) for planar models;
4. update the per-point forces with the contact model from the geometry before and after the step.

Stability. Step 3 is explicit gradient flow on the contact energy. Linearised, the object update is
``dq <- (1 - (h^2/epsilon) M^{-1} K_c) dq`` with ``K_c`` the contact stiffness, so the step is stable only when
``(h^2/epsilon) lambda_max(M^{-1} K_c) < 2``. ``stiffness_bound`` gives an upper bound of that eigenvalue for a
compiled model (all its active points in contact at once); the compiler sub-steps when the bound is exceeded:
``n`` sub-steps of ``h/n`` each (controls split evenly, mobility ``h/epsilon`` held fixed) satisfy
``(h/epsilon)(h/n) lambda < 2``. It raises an error naming the bound when that would need more sub-steps than
allowed. A model with ``object_update = "linearly_implicit"`` moves the object by backward Euler on the linearised
contact forces instead (``_linearly_implicit_motion``): stable at any stiffness where the forces are linear in the
motion, one sub-step per step.

Speed. Most of a step is the bodies' signed distances and the per-point transforms. Each step caches the signed
distances of its end state in ``State.phi``, so the next step evaluates the SDFs once instead of twice. All
per-point quantities are affine in the object-frame points and come from one ``(3, 3) @ (3, N)`` product per
pose pair, laid out coordinate-major (see ``contact_geometry``). ``CompiledStep`` wraps the step in
``torch.compile`` for a further several-fold speed-up once compiled (``hydrosoft-stack bench model`` measures
all of this).
"""

from __future__ import annotations

import functools
import math
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import torch
from torch import Tensor

from hydrosoft.compilation import (CompiledCopies, CompiledFunction, FallsBack, compiled_copy, precompiling,
                                  private_copy, uses_cuda_graphs, with_default_options)
from hydrosoft.contact import ContactModel, ContactStep, Material, PressureFieldFrictionless, wrench
from hydrosoft.geometry import se3


class State(NamedTuple):
    """Quasi-dynamic state (paper IV-D). SI units, world frame.

    object_pose: ``(B, 7)`` pose of the rigid object (origin at its centre of mass).
    body_poses: ``(B, M, 7)`` poses of the compliant bodies.
    forces: ``(B, M, N, 3)`` force each body applies to each object surface point, N. ``step`` and
        ``advance_forces`` return it laid out coordinate-major (strides of a ``(B, M, 3, N)`` tensor), the layout its
        next step's compiled kernels read fastest; any layout is accepted.
    phi: optional cache ``(B, P)`` of the signed distances (m) at these poses of the points each body can touch,
        body after body (``touchable_points``; ``P = M N`` when the model was not pruned per body). ``step`` and ``advance_forces`` fill it, and the next step uses it as ``phi_prev`` instead of
        evaluating the SDFs again; ``None`` means "compute it". It must describe this state's poses: build a new
        ``State`` without it (or ``_replace(phi=None)``) after editing the poses.
    """

    object_pose: Tensor
    body_poses: Tensor
    forces: Tensor
    phi: Tensor | None = None


OBJECT_UPDATES = ("explicit", "linearly_implicit")
"""The object updates a ``Model`` can take (``Model.object_update``)."""
LINEARLY_IMPLICIT_CONTACTS = ("nh", "snh", "nh_pressure_normal")
"""Contact models whose force response the linearly implicit update predicts: the incremental ones, which load a
point by ``E A`` along the normal and ``K A`` across it until it slides, scaled by their ``stiffness_share`` of the
point's signed distance."""
STICKING_SHARE = 0.5
"""In the linearly implicit update, a point whose tangential force is at most this share of its friction limit
``mu f_n`` sticks (its full tangential stiffness ``K A``), one on the limit slides (none: the cone projection puts
sliding points exactly on it), and one in between gets the linear blend, so that the update is continuous."""


@dataclass(frozen=True)
class Model:
    """A compiled scene: the minimal tensors and callables one step needs, in one dtype and device.

    points, normals: ``(N, 3)`` object-frame surface points (m) and outward unit normals, stored coordinate-major
    (``_coordinate_major``); areas ``(N,)`` m^2.
    bodies: ``M`` signed distance functions, each mapping body-frame points ``(..., 3)`` to ``(...)`` metres.
    material: per-body ``E, K, mu``, each ``(M,)``. actuated: ``(M,)`` bool, bodies the controls move.
    mass (kg), inertia ``(3, 3)`` (kg m^2, object frame, about the centre of mass), gravity ``(3,)`` m/s^2.
    dt: step h (s); epsilon: the quasi-dynamic damping time (s); substeps: sub-steps per step.
    planar: the object moves in (x, y, yaw) only, its height and tilt held.
    touchable: per body, the indices ``(N_m,)`` of the points it can touch (per-body pruning by the scene
    compiler: a point out of a body's reach is never evaluated against it); ``()`` means every point for every body.
    point_sets (derived from ``touchable``): per body, the slice its touchable points span where they are
    consecutive (a view when compiled, where indices are a gather read point by point), else the indices.
    actuated_bodies (derived from ``actuated``): the actuated bodies' indices, as the slice they span where they are
    consecutive (``largest_turn``), else the indices.
    support: in a planar model, the index of the body that carries the object's weight (the table: an unactuated
    horizontal half-space), or None. Its normal forces are set each step to balance the vertical load: the
    weight plus the other bodies' downward contact forces (``support_load``), so its friction limit is
    ``mu (m g + downward load)``.
    stability_margin: points within this distance (m) of a body count as in contact for the run-time stability
    check (``substeps_needed``). max_substeps: the most sub-steps a step may take before it raises
    ``UnstableStepError``.
    object_update: how step 3 moves the object. ``"explicit"`` (the paper's update, sub-stepped for stability as
    above) or ``"linearly_implicit"`` (``_linearly_implicit_motion``: backward Euler on the linearised contact
    forces, stable at any step length, so one sub-step per step; the contact models of
    ``LINEARLY_IMPLICIT_CONTACTS``). The two agree where the contacts are soft and the motion slow, and have the
    same rest states; in between, the implicit update relaxes stiff contacts less per step (``hydrosoft-stack bench
    model --sections object-update`` measures the gap).
    """

    points: Tensor
    normals: Tensor
    areas: Tensor
    bodies: tuple
    body_names: tuple[str, ...]
    material: Material
    actuated: Tensor
    contact: ContactModel
    mass: float
    inertia: Tensor
    gravity: Tensor
    dt: float
    epsilon: float
    planar: bool
    substeps: int = 1
    touchable: tuple[Tensor, ...] = ()
    support: int | None = None
    stability_margin: float = 0.0
    max_substeps: int = 64
    object_update: str = "explicit"
    point_sets: tuple[slice | Tensor, ...] = field(init=False, repr=False, compare=False)
    actuated_bodies: slice | Tensor = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "point_sets", tuple(_slice_if_consecutive(index) for index in self.touchable))
        object.__setattr__(self, "actuated_bodies", _slice_if_consecutive(self.actuated.nonzero().squeeze(-1)))
        for name in ("points", "normals"):
            object.__setattr__(self, name, _coordinate_major(getattr(self, name)))
        if self.object_update not in OBJECT_UPDATES:
            raise ValueError(f"object_update: one of {', '.join(OBJECT_UPDATES)}, got {self.object_update!r}")
        if self.object_update == "linearly_implicit" and self.contact.name not in LINEARLY_IMPLICIT_CONTACTS:
            raise ValueError(
                f"object_update 'linearly_implicit' needs an incremental contact model "
                f"({', '.join(LINEARLY_IMPLICIT_CONTACTS)}), whose force response it predicts; got "
                f"{self.contact.name!r}")

    @property
    def n_points(self) -> int:
        return self.points.shape[0]

    @property
    def n_bodies(self) -> int:
        return len(self.bodies)

    @property
    def dtype(self) -> torch.dtype:
        return self.points.dtype

    @property
    def device(self) -> torch.device:
        return self.points.device

    def to(self, dtype: torch.dtype | None = None, device: torch.device | str | None = None) -> Model:
        """The same model with its float tensors cast to ``dtype`` and moved to ``device``."""

        def cast(t: Tensor) -> Tensor:
            return t.to(device=device, dtype=dtype if t.is_floating_point() else None)

        return replace(
            self,
            points=cast(self.points),
            normals=cast(self.normals),
            areas=cast(self.areas),
            material=Material(*(cast(t) for t in self.material)),
            actuated=cast(self.actuated),
            inertia=cast(self.inertia),
            gravity=cast(self.gravity),
            touchable=tuple(cast(t) for t in self.touchable),
        )


def _coordinate_major(vectors: Tensor) -> Tensor:
    """``vectors (..., N, 3)`` as a transposed view of a contiguous ``(..., 3, N)`` tensor: each coordinate contiguous
    over the points, the layout in which compiled kernels run over the points (``contact_geometry``)."""
    return vectors.mT.contiguous().mT


def with_object_update(model: Model, object_update: str) -> Model:
    """The model, as ``scene.compile_scene`` built it, with the given object update (``Model.object_update``): the
    linearly implicit update takes one sub-step per step, which its stability never needs to raise; the explicit one
    keeps the scene's count."""
    if object_update == model.object_update:
        return model
    return replace(model, object_update=object_update,
                   substeps=1 if object_update == "linearly_implicit" else model.substeps)


STABLE_RATIO = 1.8
"""Largest ``(h/epsilon)(h/n) lambda_max(M^-1 K_c)`` a sub-step may take: 0.9 of the explicit update's limit 2."""


def _slice_if_consecutive(index: Tensor) -> slice | Tensor:
    """Indices ``(N,)`` as the slice they span when they are consecutive, else as they are: a body's touchable points
    (``Model.point_sets``; ``compile_scene`` orders the points so that the first two bodies' sets are consecutive) or
    the actuated bodies (``Model.actuated_bodies``)."""
    values = index.tolist()
    if values and values == list(range(values[0], values[-1] + 1)):
        return slice(values[0], values[-1] + 1)
    return index


def with_gathered_points(model: Model) -> Model:
    """The same model reading each body's touchable points by index (a gather) even where they are consecutive, as
    a model whose point sets are not consecutive does (``hydrosoft-stack bench model --sections point-sets`` times
    the two)."""
    gathered = replace(model)
    object.__setattr__(gathered, "point_sets", tuple(model.touchable))
    return gathered


class UnstableStepError(ValueError):
    """A step that needs more than ``max_substeps`` sub-steps: its contacts are too stiff for the explicit object
    update, or its bodies turn too far (``MAX_SUBSTEP_TURN``)."""


MAX_SUBSTEP_TURN = 0.1
"""rad: the most a body may turn in one sub-step. The contact update sees only a sub-step's end points, so the
material of a turning body moves along the chord of its arc: ``2 sin(theta/2)`` instead of ``theta`` per unit
lever, which vanishes at a full turn (a 2 pi twist per step turned a held cube by 0). At 0.1 rad the chord is
within 0.05 % of the arc. The task scenes' step limits (at most 4 degrees) stay within one sub-step."""


def largest_turn(model: Model, u: Tensor) -> float:
    """The largest rotation (rad) of an actuated body under the controls ``u (B, M, 6)`` of one step (the norm of
    their rotation vectors); 0 for no samples or no actuated body. NaN when one is NaN.

    A compiled step asks it once per step, outside its graph: two operations on the actuated bodies' columns
    (``Model.actuated_bodies``, a slice where they are consecutive), where selecting them with ``where`` over every
    body took four and 0.08 of the planner's solve (py-spy, docs/benchmarks.md)."""
    turns = torch.linalg.vector_norm(u.detach()[:, model.actuated_bodies, 3:], dim=-1)
    return float(turns.max()) if turns.numel() else 0.0


def substeps_for_turn(turn: float) -> int:
    """Sub-steps that keep a body's rotation per sub-step at most ``MAX_SUBSTEP_TURN`` when it turns ``turn`` (rad)
    in one step; at least 1 (a non-finite turn is left to the contact update, which makes the state non-finite)."""
    return max(1, math.ceil(turn / MAX_SUBSTEP_TURN)) if math.isfinite(turn) else 1


def _mass_matrix(model: Model) -> Tensor:
    """The object's generalised mass ``(d, d)`` float64 in its own frame: ``d = 6`` (m I, inertia), or
    ``d = 3`` (m, m, I_zz) for planar models."""
    eye = torch.eye(3, dtype=torch.float64)
    mass = torch.block_diag(model.mass * eye, model.inertia.double().cpu())
    return mass[[0, 1, 5]][:, [0, 1, 5]] if model.planar else mass


def point_stiffness(model: Model) -> Tensor:
    """Per body and point, its contribution ``(M, N, d, d)`` (float64, object frame) to the contact stiffness.

    ``A_i J_i^T S_{m,i} J_i`` with ``S = E_m n n^T + K_m (I - n n^T)`` (N/m per m^2 of area) and the point Jacobian
    ``J_i = [I, -[p_i]x]``; in the object frame, so it does not depend on the object's pose; restricted to
    (x, y, yaw) (``d = 3``) for planar models, else ``d = 6``.
    """
    p, n, a = model.points.double().cpu(), model.normals.double().cpu(), model.areas.double().cpu()
    eye = torch.eye(3, dtype=torch.float64)
    nnT = n.unsqueeze(-1) * n.unsqueeze(-2)
    skew = torch.zeros(p.shape[0], 3, 3, dtype=torch.float64)
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -p[:, 2], p[:, 1], -p[:, 0]
    skew = skew - skew.transpose(1, 2)
    J = torch.cat([eye.expand_as(skew), -skew], dim=-1)
    if model.planar:
        J = J[..., [0, 1, 5]]
    E = model.material.E.double().cpu().view(-1, 1, 1, 1)
    K = model.material.K.double().cpu().view(-1, 1, 1, 1)
    S = (E * nnT + K * (eye - nnT)) * a.view(1, -1, 1, 1)
    return torch.einsum("nji,mnjk,nkl->mnil", J, S, J)


def stiffness_bound(model: Model, active: Tensor | None = None) -> float:
    """``lambda_max(M^-1 K_c)`` (1/s^2) with every point marked ``active (M, N)`` (bool) in contact with its body.

    ``K_c = sum_{m,i} active_{m,i} A_i J_i^T S_{m,i} J_i`` (``point_stiffness``). It is exact when exactly the
    marked points touch, and an upper bound over every state in which only marked points touch (contact only
    removes terms, and ``lambda_max(M^-1 K)`` grows with ``K`` in the PSD order). It is not a bound over states
    in which other points touch: the run-time check ``substeps_needed`` covers those.
    """
    if active is None:
        active = torch.ones(model.n_bodies, model.n_points, dtype=torch.bool)
    K_c = torch.einsum("mn,mnij->ij", active.to(torch.float64).cpu(), point_stiffness(model))
    return float(torch.linalg.eigvals(torch.linalg.solve(_mass_matrix(model), K_c)).real.max())


def substeps_for(model: Model, max_substeps: int, active: Tensor | None = None) -> int:
    """Sub-steps per step that keep the explicit update stable with the points ``active (M, N)`` in contact,
    ``ceil((h^2/epsilon) lambda / 1.8)`` (``stiffness_bound``).

    Raises ValueError naming the bound when more than ``max_substeps`` would be needed.
    """
    lam = stiffness_bound(model, active)
    ratio = model.dt * model.dt * lam / model.epsilon
    if not math.isfinite(ratio):
        raise ValueError(f"quasi-dynamic step: h^2/epsilon * lambda_max(M^-1 K_c) = {ratio} is not finite (h = "
                         f"{model.dt} s, epsilon = {model.epsilon} s, lambda <= {lam:.3g} 1/s^2)")
    n = max(1, math.ceil(ratio / STABLE_RATIO))
    if n > max_substeps:
        raise ValueError(
            f"quasi-dynamic step unstable: h^2/epsilon * lambda_max(M^-1 K_c) = {ratio:.3g} must stay below 2 "
            f"(h = {model.dt} s, epsilon = {model.epsilon} s, lambda <= {lam:.3g} 1/s^2 from the contact "
            f"stiffness E, K times the active area over mass {model.mass} kg); it needs {n} sub-steps but "
            f"max_substeps = {max_substeps}. Raise epsilon to >= {model.dt**2 * lam / 1.8:.3g} s, lower dt, "
            f"soften E/K, or allow more sub-steps."
        )
    return n


@functools.lru_cache(maxsize=32)
def _packed_stiffness(model: Model) -> tuple[Tensor, Tensor, Tensor]:
    """``(Q (P, d*d), margin (P,), L^-1 (d, d))``: the per-pair stiffness terms in ``State.phi``'s layout (body after body,
    each on its touchable points), the contact margin (m) of each pair, and the inverse Cholesky factor of the
    mass matrix, float64 on the CPU. The support body of a planar model keeps exactly its contact patch (its
    points' distances cannot change), so its margin is 0."""
    terms = point_stiffness(model)
    packed = torch.cat([terms[m] if index is None else terms[m, index.cpu()]
                        for m, index in enumerate(touchable_points(model))])
    margins = torch.cat([torch.full((count,), 0.0 if model.planar and m == model.support else model.stability_margin,
                                    dtype=torch.float64) for m, count in enumerate(pair_counts(model))])
    inverse_factor = torch.linalg.inv(torch.linalg.cholesky(_mass_matrix(model)))
    return packed.flatten(1), margins, inverse_factor


def stability_ratio(model: Model, state: State) -> Tensor:
    """``(h^2/epsilon) lambda_max(M^-1 K_c)`` ``(B,)`` over the contacts of each sample of ``state``.

    A point counts as in contact with a body when it lies within ``model.stability_margin`` of it (its cached
    signed distance ``state.phi``, computed when missing; the support body of a planar model counts exactly its
    contact patch). One step of ``n`` sub-steps is stable while this ratio
    stays below ``2 n``. Float64 on the CPU, no gradient; non-finite samples give NaN.
    """
    phi = state.phi if state.phi is not None else packed_distances(model, state.object_pose, state.body_poses)
    Q, margins, inverse_factor = _packed_stiffness(model)
    active = (phi.detach().double().cpu() <= margins).to(torch.float64)
    d = inverse_factor.shape[0]
    K_c = (active @ Q).view(-1, d, d)
    lam = torch.linalg.eigvalsh(inverse_factor @ K_c @ inverse_factor.mT)[:, -1]
    finite = torch.isfinite(phi.detach()).all(-1).cpu()
    return torch.where(finite, model.dt**2 / model.epsilon * lam, torch.nan)


def substeps_needed(model: Model, state: State) -> int:
    """Sub-steps the next step from ``state`` needs: ``model.substeps``, or more when the contacts of some sample
    are stiffer than that count allows (``stability_ratio`` above ``1.8 n``).

    Raises ``UnstableStepError`` naming the bound when that exceeds ``model.max_substeps``. Non-finite samples
    are ignored (they are already lost, and the planner discards them). A linearly implicit model is stable at any
    step length: always ``model.substeps``.
    """
    if model.object_update == "linearly_implicit":
        return model.substeps
    ratio = stability_ratio(model, state)
    worst = float(torch.nan_to_num(ratio, nan=0.0).max()) if ratio.numel() else 0.0
    needed = max(model.substeps, math.ceil(worst / STABLE_RATIO))
    if needed > model.max_substeps:
        raise UnstableStepError(
            f"quasi-dynamic step unstable: the current contacts give h^2/epsilon * lambda_max(M^-1 K_c) = "
            f"{worst:.3g}, which needs {needed} sub-steps to stay below 1.8 per sub-step, but max_substeps = "
            f"{model.max_substeps} (h = {model.dt} s, epsilon = {model.epsilon} s, contact within "
            f"{model.stability_margin} m). The bodies press deeper than the scene allows for: raise epsilon or "
            f"max_substeps, or bound the actions."
        )
    return needed


def _frame(pose: Tensor) -> tuple[Tensor, Tensor]:
    """Rotation matrices ``(..., 3, 3)`` and translations ``(..., 3, 1)`` of poses ``(..., 7)``."""
    return se3.quat_to_matrix(pose[..., 3:]), pose[..., :3].unsqueeze(-1)


def _world_points(model: Model, object_pose: Tensor) -> Tensor:
    """World-frame surface points ``(B, N, 3)`` (m) of the object at ``object_pose (B, 7)``.

    Computed as one ``(B, 3, 3) @ (3, N)`` product, so the result is a transposed view of a ``(B, 3, N)``
    tensor: each coordinate is contiguous over the points (see ``contact_geometry``).
    """
    R, t = _frame(object_pose)
    return (se3.small_matmul(R, model.points.mT) + t).mT


def object_wrench(model: Model, state: State) -> Tensor:
    """Net wrench ``(B, 6)`` (N, N m) of the contact forces and gravity on the object, about its centre of mass."""
    w = wrench(state.forces.sum(1), _world_points(model, state.object_pose), state.object_pose[:, :3])
    gravity = torch.cat([model.mass * model.gravity, torch.zeros_like(model.gravity)])
    return w + gravity


def body_wrenches(model: Model, state: State) -> Tensor:
    """Wrench ``(B, M, 6)`` the object applies to each compliant body, about each body's origin (eq. 11)."""
    return wrench(-state.forces, _world_points(model, state.object_pose).unsqueeze(1), state.body_poses[..., :3])


def _object_motion(model: Model, state: State, w: Tensor, dt_sub: Tensor) -> Tensor:
    """Object displacement ``(B, 6)`` ``(h/epsilon) dt_sub M^{-1} w`` (world translation, rotation vector)."""
    gain = model.dt / model.epsilon * dt_sub
    R = se3.quat_to_matrix(state.object_pose[:, 3:])
    if model.planar:
        izz = torch.einsum("bi,ij,bj->b", R[:, 2], model.inertia, R[:, 2])
        zero = torch.zeros_like(izz)
        return gain * torch.stack(
            [w[:, 0] / model.mass, w[:, 1] / model.mass, zero, zero, zero, w[:, 5] / izz], dim=-1
        )
    torque_body = torch.einsum("bji,bj->bi", R, w[:, 3:])
    omega_body = torch.linalg.solve(model.inertia, torque_body.unsqueeze(-1)).squeeze(-1)
    omega = torch.einsum("bij,bj->bi", R, omega_body)
    return gain * torch.cat([w[:, :3] / model.mass, omega], dim=-1)


def signed_distances(model: Model, body_points: Tensor) -> Tensor:
    """Signed distance ``(B, M, N)`` (m) of body-frame points ``(B, M, N, 3)`` to each body."""
    return torch.stack([sdf(body_points[:, m]) for m, sdf in enumerate(model.bodies)], dim=1)


def _relative_frame(object_pose: Tensor, body_poses: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The object frame seen from each body: ``x_body = A p_object + c``.

    ``object_pose (B, 7)``, ``body_poses (B, M, 7)`` -> ``A = R_b^T R_o (B, M, 3, 3)``,
    ``c = R_b^T (t_o - t_b) (B, M, 3, 1)`` (m), the body rotations ``R_b (B, M, 3, 3)`` and the object rotation
    ``R_o (B, 3, 3)``.
    """
    R_o, t_o = _frame(object_pose)
    R_b, t_b = _frame(body_poses)
    R_bT = R_b.mT
    return se3.small_matmul(R_bT, R_o.unsqueeze(1)), se3.small_matmul(R_bT, t_o.unsqueeze(1) - t_b), R_b, R_o


def touchable_points(model: Model) -> tuple[Tensor | None, ...]:
    """Per body, the indices ``(N_m,)`` of the surface points it can touch, or None for all ``N`` points."""
    return model.touchable if model.touchable else (None,) * model.n_bodies


def pair_counts(model: Model) -> list[int]:
    """Per body, the number ``N_m`` of points it is evaluated on; their sum is the width ``P`` of ``State.phi``."""
    return [model.n_points if index is None else index.numel() for index in touchable_points(model)]


def _point_sets(model: Model) -> tuple[slice | Tensor | None, ...]:
    """Per body, its touchable points as ``Model.point_sets`` holds them (a slice where they are consecutive, else
    indices ``(N_m,)``), or None for all ``N`` points: what the step indexes with."""
    return model.point_sets if model.touchable else (None,) * model.n_bodies


def _body_groups(model: Model) -> list[tuple[slice, slice | Tensor | None]]:
    """Bodies evaluated together, each group on one point set: all ``M`` bodies on every point (one batched
    evaluation) when the model is not pruned per body and has no support body, else each body alone on its
    touchable points (``_point_sets``; all points when the model is not pruned)."""
    if not model.touchable and (model.support is None or not model.planar):
        return [(slice(0, model.n_bodies), None)]
    return [(slice(m, m + 1), points) for m, points in enumerate(_point_sets(model))]


def _distances(model: Model, A: Tensor, c: Tensor, P: Tensor, bodies: slice) -> Tensor:
    """Signed distances ``(B, g, n)`` (m) of the object-frame points ``P (3, n)`` to the bodies ``bodies`` (``g`` of
    them), seen through the relative frames ``A (B, M, 3, 3)``, ``c (B, M, 3, 1)`` (``_relative_frame``)."""
    local = (se3.small_matmul(A[:, bodies], P) + c[:, bodies]).mT
    return torch.stack([model.bodies[m](local[:, j]) for j, m in enumerate(range(bodies.start, bodies.stop))], 1)


def _group_points(model: Model, index: slice | Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
    """The points, normals ``(n, 3)`` and areas ``(n,)`` of a body group's point set (all when ``index`` is None)."""
    if index is None:
        return model.points, model.normals, model.areas
    return model.points[index], model.normals[index], model.areas[index]


def packed_distances(model: Model, object_pose: Tensor, body_poses: Tensor) -> Tensor:
    """Signed distances ``(B, P)`` (m) at the given poses in ``State.phi``'s layout (body after body, each on the
    points it can touch)."""
    A, c, _, _ = _relative_frame(object_pose, body_poses)
    return torch.cat([_distances(model, A, c, _group_points(model, index)[0].mT, bodies).flatten(1)
                      for bodies, index in _body_groups(model)], dim=-1)


def stepped_form(model: Model, state: State, grad: bool = False, distances: Callable | None = None) -> State:
    """``state`` in the form a step returns, with the same values: its signed distances cached (``State.phi``, from
    ``distances(object_pose, body_poses)``, ``packed_distances`` by default), its forces coordinate-major, and with
    ``grad`` every tensor in autograd's graph (one that is not becomes a leaf that requires grad, whose gradient
    nobody reads). ``state`` itself when it is in that form already.

    A rollout's start state (measured, estimated or made, and expanded to a batch) has no cache, another force
    layout and no gradient: a compiled step met it as an input signature of its own, compiled as a graph of its own
    per grad mode; in this form it runs the graphs of the steps after it (``CompiledStep``)."""
    if state.phi is None:
        distances = distances or functools.partial(packed_distances, model)
        with torch.set_grad_enabled(state.object_pose.requires_grad or state.body_poses.requires_grad):
            state = state._replace(phi=distances(state.object_pose, state.body_poses))
    bodies, points = state.forces.shape[1:3]
    if state.forces.stride() != (bodies * 3 * points, 3 * points, 1, points):
        state = state._replace(forces=state.forces.mT.clone(memory_format=torch.contiguous_format).mT)
    if grad and not all(t.requires_grad for t in state):
        state = State(*(t if t.requires_grad else t.detach().requires_grad_(True) for t in state))
    return state


def _bound_distances(model: Model) -> Callable[[Tensor, Tensor], Tensor]:
    """``packed_distances`` of ``model`` as a plain function ``(object_pose, body_poses) -> phi`` to compile."""
    def start_distances(object_pose: Tensor, body_poses: Tensor) -> Tensor:
        return packed_distances(model, object_pose, body_poses)

    return start_distances


def contact_geometry(model: Model, prev: State, object_pose: Tensor, body_poses: Tensor) -> list[ContactStep]:
    """Geometry of the step from ``prev`` to the poses ``object_pose (B, 7)``, ``body_poses (B, M, 7)``.

    One ``ContactStep`` per group of bodies that share a point set (``_body_groups``): the whole model, over all
    ``N`` points, when it was not pruned per body; else one per body ``m`` over the ``N_m`` points it can touch
    (``touchable_points``). Shapes, for ``g`` bodies on ``n`` points: ``phi_prev, phi_next (B, g, n)``,
    ``displacement (B, g, n, 3)``, ``normal (B, 1, n, 3)``, ``area (n,)``. Every per-point quantity is an affine
    map of the object-frame points ``P (3, n)``, so each is one batched ``(3, 3) @ (3, n)`` product of per-pose
    matrices: body-frame points ``A P + c``, the displacement ``r = R_b1 (x_0 - x_1) = R_b1 (A_0 - A_1) P +
    R_b1 (c_0 - c_1)`` and the normals ``-R_o1 n``. The results are transposed views ``(..., n, 3)`` of
    ``(..., 3, n)`` tensors, a layout in which the reductions over the coordinate axis and the SDFs' element-wise
    work run over contiguous memory (several times faster on CPU, and vectorised over points when compiled).
    ``phi_prev`` is taken from ``prev.phi`` when it is cached.
    """
    A1, c1, R_b1, R_o1 = _relative_frame(object_pose, body_poses)
    A0, c0, _, _ = _relative_frame(prev.object_pose, prev.body_poses)
    cached = None if prev.phi is None else prev.phi.split(pair_counts(model), dim=-1)  # per body

    mm = se3.small_matmul
    geometries = []
    for bodies, index in _body_groups(model):
        points, normals, areas = _group_points(model, index)
        P = points.mT
        R = R_b1[:, bodies]
        geometries.append(ContactStep(
            phi_prev=_distances(model, A0, c0, P, bodies) if cached is None else torch.stack(cached[bodies], dim=1),
            phi_next=_distances(model, A1, c1, P, bodies),
            displacement=(mm(mm(R, A0[:, bodies] - A1[:, bodies]), P) + mm(R, c0[:, bodies] - c1[:, bodies])).mT,
            normal=mm(R_o1, -normals.mT).mT.unsqueeze(1),
            area=areas,
        ))
    return geometries


def pressure_wrenches(model: Model, object_pose: Tensor, body_poses: Tensor) -> Tensor:
    """The wrench ``(B, M, 6)`` (N, N m) the object's pressure field applies to each body at the given poses, about
    each body's origin: the pose-to-wrench query of a hydroelastic contact (what Drake's hydroelastic query
    answers), with PF's and PFF's normal force law (eq. 3) and no friction.

    ``object_pose (B, 7)``, ``body_poses (B, M, 7)``. It depends on the poses alone (no force state, no motion), so
    it is what PFF's step gives and PF's gives without slip, at one signed-distance evaluation per point and body
    instead of two (``advance_forces``); only the points each body can touch are evaluated (``touchable_points``).
    A planar model's support body gets its pressure-field force too, not the vertical load balance the step gives
    it (``support_load``).
    """
    A, c, _, R_o = _relative_frame(object_pose, body_poses)
    points = _world_points(model, object_pose)
    law = PressureFieldFrictionless()
    wrenches = []
    for bodies, index in _body_groups(model):
        group_points, normals, areas = _group_points(model, index)
        phi = _distances(model, A, c, group_points.mT, bodies)
        normal = se3.small_matmul(R_o, -normals.mT).mT.unsqueeze(1)
        geometry = ContactStep(phi_prev=phi, phi_next=phi, displacement=normal.new_zeros(()).expand_as(normal),
                               normal=normal, area=areas)
        forces = law.step(geometry, normal, Material(*(t[bodies] for t in model.material)))
        at = points if index is None else points[:, index]
        wrenches.append(wrench(-forces, at.unsqueeze(1), body_poses[:, bodies, :3]))
    return torch.cat(wrenches, dim=1)


def support_load(model: Model, forces: Tensor) -> Tensor:
    """The vertical load ``(B,)`` (N) the support body carries: the object's weight plus the downward contact
    forces of the other bodies (``forces (B, M', N, 3)`` of those bodies, on the object), clamped at zero when
    they lift the object off."""
    weight = -model.mass * model.gravity[2]
    return torch.relu(weight - forces[..., 2].sum((1, 2)))


def _with_support_normal(forces: Tensor, geometry: ContactStep, load: Tensor, scale_friction: bool = False) -> Tensor:
    """The support body's forces ``(B, 1, 3, n)`` with their normal parts replaced by ``load (B,)`` (N) spread over
    its contact patch in proportion to ``A_i max(-phi_i, 0)`` (the pressure-field distribution; uniform on a flat
    face). Tangential parts are kept, or with ``scale_friction`` (a model whose friction is a multiple of the
    normal force it computed: PF) scaled with their normal force. A patch that does not touch carries nothing.
    Coordinate-major, as ``advance_forces`` steps: the forces and ``geometry``'s vectors ``(B, 1, 3, n)``
    (``ContactModel.step`` with ``axis=-2``)."""
    normal = geometry.normal
    weights = geometry.area * torch.relu(-geometry.phi_next)
    total = weights.sum(-1, keepdim=True)
    share = weights / torch.where(total > 0, total, torch.ones_like(total))
    f_n = (forces * normal).sum(-2, keepdim=True)
    supported = load.view(-1, 1, 1, 1) * share.unsqueeze(-2)
    tangential = forces - f_n * normal
    if scale_friction:
        tangential = tangential * torch.where(f_n > 0, supported / torch.where(f_n > 0, f_n, torch.ones_like(f_n)),
                                              torch.zeros_like(f_n))
    return supported * normal + tangential


def _body_turns(model: Model, body_poses: Tensor, next_poses: Tensor) -> Tensor:
    """Rotation increments ``R_1 R_0^T (B, M, 3, 3)`` of the bodies over a step; identity for unactuated bodies."""
    turn = se3.small_matmul(se3.quat_to_matrix(next_poses[..., 3:]), se3.quat_to_matrix(body_poses[..., 3:]).mT)
    eye = torch.eye(3, dtype=turn.dtype, device=turn.device)
    return torch.where(model.actuated.view(1, -1, 1, 1) > 0, turn, eye)


def advance_forces(model: Model, state: State, object_pose: Tensor, body_poses: Tensor) -> State:
    """Move object and bodies kinematically to the given poses and update the forces (step 4 of IV-D).

    ``object_pose (B, 7)`` and ``body_poses (B, M, 7)``; used by the step and to replay prescribed motions
    (force benchmarks, tactile estimation). Each body's forces are updated on the points it can touch
    (``touchable_points``) and stay zero elsewhere. The returned state caches its signed distances (``State.phi``).

    The force state co-rotates with its body (paper eq. 8 keeps it in the contact frame): before the contact
    update, each body's stored forces are rotated by the body's rotation increment over the step, so a body and an
    object that turn together without relative motion carry their forces along. In a planar model with a
    ``support`` body, that body is updated last, with its normal forces set to ``support_load`` of the others'
    new forces before (so the friction cone uses it) and after the contact update.
    """
    n = model.n_points
    geometries = contact_geometry(model, state, object_pose, body_poses)
    groups = _body_groups(model)
    turns = _body_turns(model, state.body_poses, body_poses)
    support = model.support if model.planar else None
    order = sorted(range(len(groups)), key=lambda g: groups[g][0].start == support)
    forces, phis = [None] * len(groups), [None] * len(groups)
    for g in order:
        geometry, (bodies, index) = geometries[g], groups[g]
        # the contact update runs coordinate-major, on (B, g, 3, n) vectors (axis -2), as the forces leave it (see
        # the return): compiled, the buffers its backward keeps are then laid out over the points
        geometry = geometry._replace(displacement=geometry.displacement.mT, normal=geometry.normal.mT)
        material = Material(*(t[bodies] for t in model.material))
        previous = state.forces[:, bodies]
        if index is not None:
            previous = previous[:, :, index]
        previous = se3.small_matmul(turns[:, bodies], previous.mT)
        is_support = bodies.start == support
        if is_support:
            load = support_load(model, torch.cat([f.mT for f in forces if f is not None], dim=1))
            previous = _with_support_normal(previous, geometry, load)
        f = model.contact.step(geometry, previous, material, axis=-2)
        if is_support:
            f = _with_support_normal(f, geometry, load, getattr(model.contact, "implicit_friction", False))
        if isinstance(index, slice):
            f = torch.nn.functional.pad(f, (index.start, n - index.stop))
        elif index is not None:
            f = f.new_zeros(f.shape[0], f.shape[1], 3, n).index_copy(3, index, f)
        forces[g] = f
        phis[g] = geometry.phi_next.flatten(1)
    # The forces leave laid out as a (B, M, 3, N) tensor: each coordinate contiguous over the points, so that the next
    # step's kernels read them over the points (a (B, M, N, 3) buffer is read three floats apart). A copy, not the
    # transposed view: a view would bring its base into a compiled step's guards and inputs.
    return State(object_pose, body_poses, torch.cat(forces, dim=1).mT.clone(), torch.cat(phis, dim=-1))


def _planar_jacobian(lever: Tensor) -> Tensor:
    """Point Jacobians ``(B, N, 3, 3)`` of the planar twist ``(vx, vy, wz)`` at levers ``(B, N, 3)`` (m)."""
    zero, one = torch.zeros_like(lever[..., 0]), torch.ones_like(lever[..., 0])
    rows = [torch.stack([one, zero, -lever[..., 1]], -1), torch.stack([zero, one, lever[..., 0]], -1),
            torch.stack([zero, zero, zero], -1)]
    return torch.stack(rows, dim=-2)


def _spatial_jacobian(lever: Tensor) -> Tensor:
    """Point Jacobians ``(B, N, 3, 6)`` of the twist ``(v, w)`` at levers ``(B, N, 3)`` (m): ``v + w x lever``."""
    x, y, z = lever.unbind(-1)
    zero, one = torch.zeros_like(x), torch.ones_like(x)
    rows = [torch.stack([one, zero, zero, zero, z, -y], -1), torch.stack([zero, one, zero, -z, zero, x], -1),
            torch.stack([zero, zero, one, y, -x, zero], -1)]
    return torch.stack(rows, dim=-2)


FRICTION_NEWTON_STEPS = 20
NEWTON_TOLERANCE = 1e-10  # m or rad: an eager solve stops once a Newton step moves the object less than this
LINE_SEARCH_STEPS = 8
"""Safeguarded Newton steps of the exact line search along each Newton direction. With 8, every sub-step of the
four task scenes' full planners converged in at most 14 Newton steps (at most 23 with the earlier search over 26
fixed halvings, which ended short of the minimiser under the 20-step cap)."""
LONGEST_STEP = 1e3
"""Longest step the line search takes, in Newton steps. At rest the object sticks to the table, where the
regularised slip energy curves sharply (``slip_tolerance`` 1e-7 m): Newton's step there is 1e-7 m long while
the minimiser is a millimetre away, and a search capped at one Newton step needed three more Newton steps to
leave the kink."""


def _line_minimum(kinetic: Tensor, limit: Tensor, s: Tensor, ds: Tensor, slip_tolerance: float) -> Tensor:
    """The step length ``(B, 1)`` in ``[0, LONGEST_STEP]`` that minimises the friction energy along a direction.

    Along ``v + alpha d`` the energy is ``phi(alpha) = (k0 + 2 alpha k1 + alpha^2 k2) / 2 + sum_{m,i} limit_mi
    (sqrt(|s_mi + alpha ds_mi|^2 + tol^2) - tol)`` with ``kinetic = (k0, k1, k2)`` ``(B, 3)``, the slips ``s`` and
    their change ``ds`` per unit step ``(B, M, N, 3)`` (m) and the friction limits ``limit`` ``(B, M, N)`` (N). It is
    convex, so ``phi'`` rises through one zero: ``LINE_SEARCH_STEPS`` safeguarded Newton steps on ``phi'`` from
    ``alpha = 1`` keep a bracket ``[lo, hi]`` around it (``phi'(lo) < 0``) and bisect where a Newton step would
    leave it (in ratios of 16 while ``lo`` is 0, so a minimiser far below one Newton step is found too). The result
    is the lowest-energy of ``lo``, the last iterate and ``hi``: never above ``phi(0)``, since ``phi`` falls up to
    ``lo``."""
    k0, k1, k2 = kinetic.unbind(-1)
    a = s.square().sum(-1) + slip_tolerance**2
    b, c = (s * ds).sum(-1), ds.square().sum(-1)
    curving = c * a - b * b  # |s|^2 |ds|^2 - (s . ds)^2 + tol^2 |ds|^2 >= 0; a point's phi'' is limit curving / q^3
    limit_curving, two_b = limit * curving, 2 * b  # the loop's terms that do not change with alpha, made once
    lo, hi = torch.zeros_like(k1), torch.full_like(k1, LONGEST_STEP)
    alpha = torch.ones_like(k1)
    for _ in range(LINE_SEARCH_STEPS):
        at = alpha.view(-1, 1, 1)
        atc = at * c
        q2 = a + at * (two_b + atc)
        q = torch.sqrt(q2)
        slope = k1 + alpha * k2 + (limit * (b + atc) / q).sum((1, 2))
        bend = k2 + (limit_curving / (q2 * q)).sum((1, 2))
        below = slope < 0
        lo, hi = torch.where(below, alpha, lo), torch.where(below, hi, alpha)
        newton = alpha - slope / bend
        bisection = torch.where(lo > 0, 0.5 * (lo + hi), hi / 16)
        alpha = torch.where((newton > lo) & (newton < hi), newton, bisection)
    candidates = torch.stack([lo, alpha, hi], -1)
    at = candidates.view(-1, 1, 1, 3)
    slide = (limit.unsqueeze(-1) * (torch.sqrt(a.unsqueeze(-1) + at * (2 * b.unsqueeze(-1) + at * c.unsqueeze(-1)))
                                    - slip_tolerance)).sum((1, 2))
    energy = 0.5 * (k0.unsqueeze(-1) + candidates * (2 * k1.unsqueeze(-1) + candidates * k2.unsqueeze(-1))) + slide
    return candidates.gather(-1, energy.argmin(-1, keepdim=True))


class FrictionSystem(NamedTuple):
    """The terms of one sub-step's friction energy (``_implicit_friction_motion``), for ``B`` samples, ``M``
    bodies, ``N`` points and ``d`` object velocity coordinates (3 planar, 6 spatial).

    ``PJ (B, N, 3, d)`` maps the object twist to each point's tangential motion (m); ``carried (B, M, N, 3)`` is
    each body's tangential motion at each point (m); ``limit (B, M, N)`` the friction limits ``mu f_n`` (N);
    ``mass (B, d, d)`` the mass matrix (kg, kg m^2); ``v0 (B, d)`` the frictionless motion; ``gain`` (0-d,
    s^2/kg-like: ``(h/epsilon) dt_sub``) scales the kinetic term; ``slip_tolerance`` (m) regularises the slip."""

    PJ: Tensor
    carried: Tensor
    limit: Tensor
    mass: Tensor
    v0: Tensor
    gain: Tensor
    slip_tolerance: float


def _newton_direction(system: FrictionSystem, v: Tensor) -> tuple[Tensor, Tensor]:
    """The Newton direction ``(B, d)`` of the friction energy at ``v (B, d)`` and the per-point slips there
    ``(B, M, N, 3)`` (m).

    The projector is symmetric and idempotent and each slip's unit vector ``u`` is tangent, so the friction
    Hessian ``sum J^T (f/|s|)(P - u u^T) J`` is ``sum W (PJ)^T PJ - G^T diag(f/|s|) G`` with ``W`` the weights
    summed over bodies and ``G`` the rows ``(PJ)^T u`` (and the friction gradient ``G^T limit``): two batched
    products over all points instead of a 3 x 3 product per point and body."""
    PJ, carried, limit, mass, v0, gain, slip_tolerance = system
    batch, n_points, _, dof = PJ.shape
    PJ_rows = PJ.reshape(batch, 3 * n_points, dof)
    s = (PJ * v.view(batch, 1, 1, dof)).sum(-1).unsqueeze(1) - carried
    sigma = torch.sqrt(s.square().sum(-1) + slip_tolerance**2)
    weight = limit / sigma
    G = (PJ.unsqueeze(1) * (s / sigma.unsqueeze(-1)).unsqueeze(-1)).sum(-2).reshape(batch, -1, dof)
    grad = (mass @ (v - v0).unsqueeze(-1)).squeeze(-1) / gain + (limit.reshape(batch, 1, -1) @ G).squeeze(1)
    W = weight.sum(1).repeat_interleave(3, dim=-1).unsqueeze(-1)
    hessian = mass / gain + PJ_rows.mT @ (W * PJ_rows) - G.mT @ (weight.reshape(batch, -1, 1) * G)
    return -torch.linalg.solve(hessian, grad.unsqueeze(-1)).squeeze(-1), s


def _newton_move(system: FrictionSystem, v: Tensor) -> Tensor:
    """One Newton step of the friction energy from ``v (B, d)`` with its exact line search: the move ``(B, d)``."""
    direction, s = _newton_direction(system, v)
    PJ, mass, v0, gain = system.PJ, system.mass, system.v0, system.gain
    ds = (PJ * direction.view(*direction.shape[:1], 1, 1, -1)).sum(-1).unsqueeze(1)
    dv = v - v0
    Mdv, Md = (mass @ dv.unsqueeze(-1)).squeeze(-1), (mass @ direction.unsqueeze(-1)).squeeze(-1)
    kinetic = torch.stack([(dv * Mdv).sum(-1), (direction * Mdv).sum(-1), (direction * Md).sum(-1)], -1) / gain
    return _line_minimum(kinetic, system.limit, s, ds, system.slip_tolerance) * direction


@torch.compiler.disable
def _minimise_friction_energy(move, system: FrictionSystem) -> Tensor:
    """The minimiser ``(B, d)`` of the friction energy, without autograd: Newton steps ``move(system, v)`` from
    ``system.v0`` until one moves the object less than ``NEWTON_TOLERANCE`` (m or rad), at most
    ``FRICTION_NEWTON_STEPS``.

    Kept out of ``torch.compile``'s graphs: a compiled step calls it between its two graphs and passes a compiled
    ``_newton_move`` (``CompiledStep``), so the loop stops as soon as it converges and only one Newton step is
    compiled instead of every step of the loop unrolled."""
    # detached inputs and a fresh start: a compiled move is guarded on requires_grad and on aliasing, so every
    # call, with or without gradients and from v0 or not, reuses one graph
    system = system._replace(**{name: value.detach() for name, value in system._asdict().items()
                                if isinstance(value, Tensor)})
    with torch.no_grad():
        v = system.v0.clone()
        for _ in range(FRICTION_NEWTON_STEPS):
            step_taken = move(system, v)
            v = v + step_taken
            if float(step_taken.abs().max()) < NEWTON_TOLERANCE:
                break
    return v


def _implicit_friction_motion(model: Model, state: State, body_poses: Tensor, w: Tensor, dt_sub: Tensor,
                              slip_tolerance: float) -> Tensor:
    """Object displacement ``(B, 6)`` of a sub-step with Coulomb friction solved implicitly (PF's friction).

    The object twist ``v`` (``d = 3`` planar or 6) minimises the convex energy
    ``(1 / 2 gain) (v - v0)^T M (v - v0) + sum_{m,i} mu_m f_n,mi (sqrt(|s_mi|^2 + tol^2) - tol)``,
    with ``v0 = gain M^-1 w`` the frictionless motion under the normal and gravity wrench ``w (B, 6)``, ``gain =
    (h/epsilon) dt_sub`` and ``s_mi`` the tangential slip of object point ``i`` relative to body ``m``'s material
    over the sub-step (its motion ``J_i v`` minus the body's motion at the point). Its stationarity condition is
    ``v = v0 + gain M^-1 sum J^T f`` with ``f = -mu f_n s / sqrt(|s|^2 + tol^2)``: PF's regularised kinetic
    friction (eq. 4) evaluated at the slip the motion itself produces (backward Euler, maximum dissipation).
    Friction therefore never exceeds the force that stops the slip in this sub-step, so it cannot overshoot and
    reverse the motion, whatever the step size. The energy is minimised by at most ``FRICTION_NEWTON_STEPS``
    Newton steps (``_minimise_friction_energy``), each with an exact line search (``_line_minimum``), stopping
    once converged (``NEWTON_TOLERANCE``). The loop runs without autograd: the gradient is the
    implicit one, ``dv/dx = -H^-1 dg/dx`` at the minimiser (energy gradient ``g``, Hessian ``H``), from one Newton
    direction evaluated there with autograd on, so the backward costs one Newton step instead of the whole loop.
    The normal forces ``f_n`` are those of ``state.forces``; a point without normal force carries no friction.
    """
    system = _friction_system(model, state, body_poses, w, dt_sub, slip_tolerance)
    return _friction_motion(model, system, _minimise_friction_energy(_newton_move, _frictional_pairs(system)))


def _frictional_pairs(system: FrictionSystem) -> FrictionSystem:
    """``system`` over its frictional (body, point) pairs alone, as one body of ``P`` pairs: ``PJ (B, P, 3, d)``,
    ``carried (B, 1, P, 3)``, ``limit (B, 1, P)``, the pairs whose friction limit is not 0 in some sample (a NaN
    limit is kept, so a non-finite state stays non-finite).

    The same energy: a pair with no friction limit adds exactly 0 to it, to its gradient and to its Hessian, but in
    a contact scene it is most of them (the rolling planner's sub-steps: 28 of 2 x 132). Its shape changes with the
    contacts, so only the eager Newton loop runs on it; a compiled step keeps the full system, whose shape is
    fixed."""
    body, point = (system.limit != 0).any(0).nonzero(as_tuple=True)
    return system._replace(PJ=system.PJ[:, point], carried=system.carried[:, body, point].unsqueeze(1),
                           limit=system.limit[:, body, point].unsqueeze(1))


def _friction_system(model: Model, state: State, body_poses: Tensor, w: Tensor, dt_sub: Tensor,
                     slip_tolerance: float) -> FrictionSystem:
    """The friction energy of the sub-step from ``state`` to the bodies' ``body_poses`` ``(B, M, 7)`` under the
    normal and gravity wrench ``w (B, 6)`` (``_implicit_friction_motion``)."""
    gain = model.dt / model.epsilon * dt_sub
    R_o, t_o = _frame(state.object_pose)
    points = (R_o @ model.points.mT + t_o).mT
    normal = (R_o @ -model.normals.mT).mT
    R_b0, t_b0 = _frame(state.body_poses)
    R_b1, t_b1 = _frame(body_poses)
    carried = (points.unsqueeze(1) - t_b0.mT) @ (R_b1 @ R_b0.mT).mT + t_b1.mT - points.unsqueeze(1)
    f_n = torch.relu((state.forces * normal.unsqueeze(1)).sum(-1))
    limit = model.material.mu.view(1, -1, 1) * f_n
    lever = points - state.object_pose[:, None, :3]
    J = (_planar_jacobian if model.planar else _spatial_jacobian)(lever)
    mass, w_v = _generalised_mass(model, R_o, w)
    v0 = gain * torch.linalg.solve(mass, w_v.unsqueeze(-1)).squeeze(-1)
    projector = torch.eye(3, dtype=w.dtype, device=w.device) - normal.unsqueeze(-1) * normal.unsqueeze(-2)
    PJ = projector @ J
    carried_t = (carried.unsqueeze(-2) @ projector.unsqueeze(1)).squeeze(-2)
    return FrictionSystem(PJ, carried_t, limit, mass, v0, gain, slip_tolerance)


def _friction_motion(model: Model, system: FrictionSystem, v: Tensor) -> Tensor:
    """The object displacement ``(B, 6)`` from the minimiser ``v (B, d)`` of ``system``, with its implicit gradient."""
    if torch.is_grad_enabled():
        # implicit gradient: at the minimiser, d(Newton direction)/d(inputs) = dv*/d(inputs), so adding the
        # direction minus its own value keeps v* and gives exactly that derivative (one step to differentiate
        # instead of the whole loop)
        direction, _ = _newton_direction(system, v)
        v = v + (direction - direction.detach())
    return _displacement(model, v)


def _displacement(model: Model, v: Tensor) -> Tensor:
    """The object displacement ``(B, 6)`` of a motion ``v (B, d)`` in the model's coordinates: (x, y, yaw) placed
    in the 6-vector for planar models (``d = 3``), else ``v`` itself."""
    if model.planar:
        zero = torch.zeros_like(v[:, 0])
        return torch.stack([v[:, 0], v[:, 1], zero, zero, zero, v[:, 2]], dim=-1)
    return v


def _generalised_mass(model: Model, R_o: Tensor, w: Tensor) -> tuple[Tensor, Tensor]:
    """The object's mass matrix ``(B, d, d)`` in the world frame at rotations ``R_o (B, 3, 3)`` and the matching
    coordinates ``(B, d)`` of the wrench ``w (B, 6)``: ``d = 3`` (x, y, yaw) for planar models, else 6."""
    if model.planar:
        izz = torch.einsum("bi,ij,bj->b", R_o[:, 2], model.inertia, R_o[:, 2])
        mass = torch.diag_embed(torch.stack([torch.full_like(izz, model.mass), torch.full_like(izz, model.mass), izz], -1))
        return mass, w[:, [0, 1, 5]]
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand(w.shape[0], 3, 3)
    inertia = R_o @ model.inertia @ R_o.mT
    zero = torch.zeros_like(eye)
    return torch.cat([torch.cat([model.mass * eye, zero], -1), torch.cat([zero, inertia], -1)], -2), w


def _generalised(lever: Sequence[Tensor], v: Sequence[Tensor], planar: bool) -> list[Tensor]:
    """``J^T v`` of point vectors ``v`` at levers ``lever`` about the centre of mass, one coordinate at a time: each
    of ``lever`` and ``v`` is its three coordinates ``(B, n)`` (m; any unit), the result ``d`` coordinates ``(B, n)``:
    ``(v, lever x v)`` (``d = 6``), or ``(v_x, v_y, (lever x v)_z)`` for planar models (``d = 3``: x, y, yaw).

    Kept per coordinate so that compiled kernels run over the points (contiguous where the points are a transposed
    view, ``_world_points``), not over a trailing axis of 3."""
    (lx, ly, lz), (vx, vy, vz) = lever, v
    yaw = lx * vy - ly * vx
    if planar:
        return [vx, vy, yaw]
    return [vx, vy, vz, ly * vz - lz * vy, lz * vx - lx * vz, yaw]


def _contact_stiffness(lever: Sequence[Tensor], normal: Sequence[Tensor], k_t: Tensor, k_n: Tensor,
                       planar: bool) -> Tensor:
    """The contact stiffness ``sum_i J_i^T (k_t,i I + k_n,i n_i n_i^T) J_i`` ``(B, d, d)`` of points with levers
    ``lever`` (m) and unit normals ``normal`` (each three coordinates ``(B, n)``) and stiffnesses ``k_t, k_n (B, n)``
    (N/m), in ``_generalised``'s coordinates.

    Written out from ``J = [I, -[l]x]``: ``sum k_t J^T J = [[K I, -[a]x], [[a]x, sum k_t (|l|^2 I - l l^T)]]`` with
    ``K = sum k_t`` and ``a = sum k_t l``; planar models keep rows and columns (x, y, yaw). Each entry is one sum over
    the points, so no ``(B, n, d, d)`` tensor is formed."""
    lx, ly, lz = lever
    total = k_t.sum(-1)
    ax, ay, az = ((k_t * l).sum(-1) for l in lever)
    roll = (k_t * (ly * ly + lz * lz)).sum(-1)
    pitch = (k_t * (lx * lx + lz * lz)).sum(-1)
    yaw = (k_t * (lx * lx + ly * ly)).sum(-1)
    zero = torch.zeros_like(total)
    if planar:
        rows = [[total, zero, -ay], [zero, total, ax], [-ay, ax, yaw]]
    else:
        xy, xz, yz = ((k_t * a * b).sum(-1) for a, b in ((lx, ly), (lx, lz), (ly, lz)))
        rows = [[total, zero, zero, zero, az, -ay],
                [zero, total, zero, -az, zero, ax],
                [zero, zero, total, ay, -ax, zero],
                [zero, -az, ay, roll, -xy, -xz],
                [az, zero, -ax, -xy, pitch, -yz],
                [-ay, ax, zero, -xz, -yz, yaw]]
    g = _generalised(lever, normal, planar)
    d = len(g)
    weighted = [k_n * gi for gi in g]
    normal_part = {(i, j): (weighted[i] * g[j]).sum(-1) for i in range(d) for j in range(i, d)}
    return torch.stack([torch.stack([rows[i][j] + normal_part[min(i, j), max(i, j)] for j in range(d)], -1)
                        for i in range(d)], -2)


def _linearly_implicit_motion(model: Model, state: State, body_poses: Tensor, w: Tensor, dt_sub: Tensor) -> Tensor:
    """Object displacement ``(B, 6)`` of a sub-step by backward Euler on the linearised contact forces.

    The explicit update moves the object by ``dq = gain M^-1 w`` with the wrench ``w (B, 6)`` of the forces at the
    start (``gain = (h/epsilon) dt_sub``). This one uses the forces at the end instead, predicted linearly: each
    point ``i`` inside body ``m`` at the start loads by ``A_i S_mi (c_mi - J_i dq)``, with ``c_mi`` the motion of
    the body's material at the point over the sub-step (m), ``J_i`` the point's Jacobian at its lever about the
    centre of mass and ``S = E n n^T + K_eff (I - n n^T)`` (``K_eff = K`` for a sticking point, 0 for one that
    slides: ``STICKING_SHARE``; both scaled by the contact model's ``stiffness_share`` of the point's distance: 1
    inside the body and 0 outside for NH, the smoothed reset's weight for SNH), and its stored force ``f_mi`` turns
    with the body (by its rotation ``T_m`` over the sub-step, as step 4 turns it). So ``(M / gain + K_c) dq = w +
    sum_mi J_i^T (A_i S_mi c_mi + (T_m - I) f_mi)`` with the contact stiffness ``K_c = sum_mi A_i J_i^T S_mi J_i``:
    ``d = 3`` (x, y, yaw) planar, else 6, mass matrix in the world frame. Where the forces are linear in the motion
    (sticking points fully inside) the force error then decays by ``1 / (1 + gain lambda)`` per sub-step instead of
    ``1 - gain lambda``: stable for any stiffness, where the explicit update needs ``gain lambda < 2``. Steady
    motion and rest states are the explicit update's: at a constant body velocity the predicted and the start forces
    agree. Points that enter a body during the sub-step are not predicted; the exact contact update (step 4) loads
    them, and the next sub-step predicts them. Every point inside counts fully, however shallow: a stiffness ramped
    in over the first 0.5 mm of depth instead left most of a stiff, shallow contact's stiffness to the explicit
    update, and a plate at rest on a table of E = 1e7 Pa/m (0.08 mm deep) rang and left the table after 16 steps.
    ``state.phi`` must be cached (``_substep`` fills it).
    """
    gain = model.dt / model.epsilon * dt_sub
    R_o, t_o = _frame(state.object_pose)
    points = _world_points(model, state.object_pose)
    normals = se3.small_matmul(R_o, -model.normals.mT)  # (B, 3, N)
    t_b0, t_b1 = state.body_poses[..., :3, None], body_poses[..., :3, None]
    turns = _body_turns(model, state.body_poses, body_poses)
    stiffness, push = 0.0, 0.0
    # every point vector below is coordinate-major, (B, 3, n): compiled, the per-point loads the kernels keep are then
    # laid out over the points, as the forces and points they are read with
    for m, (index, phi) in enumerate(zip(_point_sets(model), state.phi.split(pair_counts(model), dim=-1))):
        x, n, area, f = points.mT, normals, model.areas, state.forces[:, m].mT
        if index is not None:
            x, n, area, f = x[..., index], n[..., index], area[index], f[..., index]
        f_n = (f * n).sum(-2)
        capacity = model.material.mu[m] * f_n  # friction limit (N)
        spare = capacity - se3.safe_norm(f - f_n.unsqueeze(-2) * n, dim=-2)
        ramp = (1 - STICKING_SHARE) * capacity
        sticking = torch.where(ramp > 0, spare / torch.where(ramp > 0, ramp, torch.ones_like(ramp)), 0.0).clamp(0, 1)
        contact = area * model.contact.stiffness_share(phi)  # (B, n) m^2
        k_t = model.material.K[m] * sticking * contact  # (B, n) N/m
        k_n = model.material.E[m] * contact - k_t
        lever_b = x - t_b0[:, m]
        carried = se3.small_matmul(turns[:, m], lever_b) + t_b1[:, m] - t_b0[:, m] - lever_b
        load = k_t.unsqueeze(-2) * carried + (k_n * (carried * n).sum(-2)).unsqueeze(-2) * n
        load = load + se3.small_matmul(turns[:, m], f) - f  # the stored forces turn with the body
        lever = (x - t_o).unbind(-2)
        push = push + torch.stack([term.sum(-1) for term in _generalised(lever, load.unbind(-2), model.planar)], -1)
        stiffness = stiffness + _contact_stiffness(lever, n.unbind(-2), k_t, k_n, model.planar)
    mass, w_v = _generalised_mass(model, R_o, w)
    return _displacement(model, se3.small_spd_solve(mass / gain + stiffness, w_v + push))


def _normal_wrench(model: Model, state: State) -> Tensor:
    """Net wrench ``(B, 6)`` of the normal parts of the contact forces and gravity, about the centre of mass.

    The normals turn by the rotation matrix of the object's quaternion, normalised on the fly as in the rest of the
    step, so a quaternion of any scale gives the same wrench."""
    normal = (se3.quat_to_matrix(state.object_pose[:, 3:]) @ -model.normals.mT).mT.unsqueeze(1)
    forces = (state.forces * normal).sum(-1, keepdim=True) * normal
    return object_wrench(model, state._replace(forces=forces))


def _substep(model: Model, state: State, u: Tensor, dt_sub: Tensor) -> State:
    """One sub-step of length ``dt_sub`` (s; a 0-d or ``(1,)`` tensor, ``_substep_length``)."""
    dt_sub = dt_sub.reshape(())
    body_poses = _moved_bodies(model, state, u)
    if getattr(model.contact, "implicit_friction", False):
        motion = _implicit_friction_motion(model, state, body_poses, _normal_wrench(model, state), dt_sub,
                                           model.contact.slip_tolerance)
    elif model.object_update == "linearly_implicit":
        if state.phi is None:
            state = state._replace(phi=packed_distances(model, state.object_pose, state.body_poses))
        motion = _linearly_implicit_motion(model, state, body_poses, object_wrench(model, state), dt_sub)
    else:
        motion = _object_motion(model, state, object_wrench(model, state), dt_sub)
    return advance_forces(model, state, se3.retract(state.object_pose, motion), body_poses)


def _moved_bodies(model: Model, state: State, u: Tensor) -> Tensor:
    """The bodies' poses ``(B, M, 7)`` after the sub-step's actions ``u (B, M, 6)`` (unactuated bodies stay).

    An unactuated body's actions are selected away, not multiplied by zero, so their gradient is exactly zero even
    where the gradient at its pose is not finite."""
    return se3.retract(state.body_poses, torch.where(model.actuated.view(1, -1, 1) > 0, u, 0.0))


@functools.lru_cache(maxsize=256)
def _substep_length(dt_sub: float, dtype: torch.dtype, device: torch.device) -> Tensor:
    """The sub-step length ``dt_sub`` (s) as a tensor of shape ``(1,)``, made once per value, dtype and device (a new
    tensor per call took 3-15 us of a 0.6 ms compiled step). Callers only read it. Made outside inference mode, so that
    it is an ordinary tensor whatever mode the first step ran in (a compiled graph with gradients may save its inputs).

    Not 0-d: dynamo takes a 0-d float64 CPU input for a Python float as well, specialises it, and restarts its analysis
    of the whole sub-step, which a cold compile of the plant's float64 step paid once (the sub-step makes it 0-d in
    its graph)."""
    with torch.inference_mode(False):
        return torch.full((1,), dt_sub, dtype=dtype, device=device)


def _integrate(model: Model, state: State, u: Tensor, substep, n: int) -> State:
    """``n`` applications of ``substep(state, u / n, h / n)``: one step of length ``model.dt``."""
    u_sub = u if n == 1 else u / n
    dt_sub = _substep_length(model.dt / n, u.dtype, u.device)
    for _ in range(n):
        state = substep(state, u_sub, dt_sub)
    return state


def _checked_step(model: Model, state: State, u: Tensor, substep, start_substeps: int | None = None
                  ) -> tuple[State, int | None]:
    """One step with as many sub-steps as its contacts and its bodies' turns need, checked at its start and its end.

    The sub-step count is ``substeps_needed`` at the start (or ``start_substeps`` when the caller already knows
    it for this very state), raised to ``substeps_for_turn`` of the controls' largest turn; if the end state's
    contacts need more (the step pressed deeper), the step is run again from the same start with that many. A state
    past the bound never passes silently: beyond ``model.max_substeps`` it raises ``UnstableStepError``. Returns the
    state and ``substeps_needed`` of that state, which the next step from it would compute again (None after a
    re-run, whose end was not checked).
    """
    n = substeps_needed(model, state) if start_substeps is None else start_substeps
    turn = largest_turn(model, u)
    turning = substeps_for_turn(turn)
    if turning > model.max_substeps:
        raise UnstableStepError(
            f"a body turns {turn:.3g} rad in one step: that needs {turning} sub-steps "
            f"of at most {MAX_SUBSTEP_TURN} rad (a larger turn per sub-step aliases: the contacts see only its chord), "
            f"but max_substeps = {model.max_substeps}. Split the motion over more steps or raise max_substeps."
        )
    n = max(n, turning)
    out = _integrate(model, state, u, substep, n)
    n_end = substeps_needed(model, out)
    if n_end > n:
        return _integrate(model, state, u, substep, n_end), None
    return out, n_end


def step(model: Model, state: State, u: Tensor) -> State:
    """One quasi-dynamic step of length ``model.dt``: ``State (B, ...)``, ``u (B, M, 6)`` -> ``State``.

    Sub-steps ``model.substeps`` times, or more when the current contacts need it (``_checked_step``).
    """
    return _checked_step(model, state, u, functools.partial(_substep, model))[0]


def _bound_substep(model: Model, friction_move=None):
    """The sub-step of ``model`` as a plain function ``(state, u_sub, dt_sub) -> state`` to compile.

    With implicit friction (PF) the Newton loop runs between two graphs, calling ``friction_move`` (a compiled
    ``_newton_move``). The loop is called from this function itself, so the graph break falls in the compiled
    (private) code and not in the shared ``_substep``, whose resume frames would count every model's graphs against
    one recompile limit."""
    if friction_move is None:
        def compiled_substep(state: State, u: Tensor, dt_sub: Tensor) -> State:
            return _substep(model, state, u, dt_sub)

        return compiled_substep

    def compiled_friction_substep(state: State, u: Tensor, dt_sub: Tensor) -> State:
        dt_sub = dt_sub.reshape(())
        body_poses = _moved_bodies(model, state, u)
        system = _friction_system(model, state, body_poses, _normal_wrench(model, state), dt_sub,
                                  model.contact.slip_tolerance)
        motion = _friction_motion(model, system, _minimise_friction_energy(friction_move, system))
        return advance_forces(model, state, se3.retract(state.object_pose, motion), body_poses)

    return compiled_friction_substep


class CompiledStep(FallsBack):
    """``step(model, state, u)`` with its sub-step compiled by ``torch.compile`` (inductor), and an eager fallback.

    Only one sub-step is compiled and the sub-step loop (with its stability check) stays in Python, so the graphs
    stay small whatever the sub-step count is (compiling the whole step put every sub-step into each graph:
    minutes to compile); the sub-step length is a tensor input, so a step that needs more sub-steps reuses the
    compiled graph.
    With implicit friction (PF) the sub-step is two graphs with the Newton loop between them in Python, calling a
    compiled Newton step (``_bound_substep``): the loop stops when it converges, as the eager one does.

    ``CompiledStep(model, **options)(state, u)`` returns what ``step(model, state, u)`` returns, within float
    rounding (the compiled kernels reassociate sums: about 1e-7 relative in float32, 1e-15 in float64). The
    first call for each new input signature (dtype, device, shape, whether gradients are needed) compiles: tens of
    seconds on a CPU, which pays off over long rollouts or many planner iterations. A start state (no ``state.phi``
    cached) is first put in the form a step returns (``stepped_form``), so that the first step of a rollout runs the
    graphs of the steps after it. ``options`` go to ``torch.compile`` (e.g. ``dynamic=True`` to compile once for all
    batch sizes).
    With the default inductor backend and no ``mode``/``options`` given, the options are
    ``compilation.DEFAULT_OPTIONS`` on the CPU (a model on a GPU: ``compilation.GPU_DEFAULT_OPTIONS``):
    inductor's C++ wrapper, which launches the kernels from C++ instead of Python and halves a batch-1 step
    (0.27 -> 0.14 ms measured on the pushing scene) for a few more seconds of compilation; and no bounds check on
    each indirect index. The step's indices are the model's own point subsets (``touchable_points``), arg-minima
    and a mesh SDF's grid cells, clamped into the grid (a NaN point reads cell 0 and gives NaN), so none can be out
    of range; the checks were a branch per element of the fused kernels (the pushing planner's step at B = 64: 0.82
    of the time without them, forward and backward); and no masked vector code for a loop's tail. Many of the
    step's loops run over a trailing axis of 3 (a force's coordinates), which inductor otherwise vectorises as a
    16-lane vector with 13 lanes masked off, reading it through a buffer; as plain scalar loops the pushing planner's
    step took 0.88 of the time forward and backward at B = 64 (float32), the same forward alone (the explicit step
    over 600 points of ``bench model``'s rows: 0.85 forward and backward, but 1.06 forward).
    If compilation fails (no C++ compiler, an unsupported platform, more than dynamo's ``recompile_limit`` of 8
    input signatures on one instance), it warns once and runs the eager ``step`` from then on;
    ``fallback_reason`` then says why: dynamo's own fallback past its limit would be silent. Each instance
    compiles a private copy of the sub-step's code (``compilation.private_copy``), so any number of instances (one
    per model) stay compiled. With a precompiled directory set (``compilation.use_precompiled``), the sub-step of a
    model without implicit friction loads each signature's graphs whole from there, without dynamo's tracing
    (``compilation.Precompiled``).
    A step from the very state this instance returned last (a rollout) takes its start stability check from
    that step's end check instead of repeating it: one ``substeps_needed`` per step instead of two, the same
    sub-step counts. Nothing in the library requires it.
    ``activation_memory_budget`` (AOT autograd's, read when a graph with gradients compiles): 0 (the default) has
    the backward graphs recompute the forward's intermediates instead of saving them, 1 saves what torch saves by
    default. Each saved intermediate is handed from the forward to the backward as a tensor object on every call,
    and this step's are many and small: with 0 the full pushing planner's solve took 0.89 of the time with 1, for
    the same compile time (float32, one thread; ``hydrosoft-stack bench control --compile
    --rate-activation-budgets 1,0`` measures it).
    An instance may be called from several threads at once (``CemGdConfig.workers``; give that count as
    ``workers``, so that as many copies compile up front): each running call steps
    through a compiled copy of the sub-step of its own, the first step from each new input signature runs alone, its
    backward graph compiled with it, and a copy compiles the signatures that other copies ran before it steps
    (``compilation.CompiledCopies`` says why).
    """

    def __init__(self, model: Model, activation_memory_budget: float = 0.0, workers: int = 1, **options) -> None:
        self.model = model
        options = with_default_options(options, model.device)
        implicit_friction = getattr(model.contact, "implicit_friction", False)

        setting = precompiling()

        def build() -> Callable:
            if not implicit_friction:  # one graph: precompiled when a directory is set (compilation.Precompiled)
                return compiled_copy(_bound_substep(model), options, setting)
            friction_move = torch.compile(private_copy(_newton_move), **options)
            return torch.compile(private_copy(_bound_substep(model, friction_move)), **options)

        def warm(substep: Callable, state: State, u: Tensor) -> State:
            return _checked_step(model, state, u, substep)[0]

        self._copies = CompiledCopies(build, warm, activation_memory_budget, passthrough=(UnstableStepError,),
                                      copy_outputs=uses_cuda_graphs(options),
                                      workers=workers)
        # a start state's signed distances (``stepped_form``): a small forward graph, where eager took 2.5-5 ms
        self._distances = CompiledFunction(_bound_distances(model), workers=workers, **options)
        self._eager_substep = functools.partial(_substep, model)
        # per thread, (signed distances of the last state returned, the sub-steps a step from it needs): a rollout's
        # next step starts from that state, so its start check is already known (one stability check per step)
        self._end_check = threading.local()
        self._start = threading.local()  # per thread, (the last start state, its stepped form): ``_start_form``

    def __call__(self, state: State, u: Tensor) -> State:
        """One step, ``State (B, ...)``, ``u (B, M, 6)`` -> ``State``."""
        # one layout for every u: a planner's u[:, k] is a view whose strides depend on its horizon, and each new
        # stride would compile the step again (an open-loop plan of each episode's length passed the limit)
        u = u.contiguous()
        # every state in a step's own form (a start state too), so that a rollout compiles one graph per grad mode
        tracked = any(t is not None and t.requires_grad for t in state)
        grad = torch.is_grad_enabled() and (u.requires_grad or tracked)
        if state.phi is None and not tracked:
            state = self._start_form(state)
        state = stepped_form(self.model, state, grad, self._distances)
        return self._copies.run((state, u), self._checked_step, self._eager_substep)

    def _start_form(self, state: State) -> State:
        """``stepped_form`` of a start state outside autograd's graph (its signed distances, its forces' layout), kept
        for the next call on this thread with this very state: a solver rolls out from one start state several
        times per solve (its gradient steps, then the final rollout). A caller that edits a state in place passes
        it anew (as ``State.phi`` already asks)."""
        known = getattr(self._start, "last", None)
        if known is not None and known[0] is state:
            return known[1]
        formed = stepped_form(self.model, state, False, self._distances)
        self._start.last = (state, formed)
        return formed

    @property
    def fallback_reason(self) -> str | None:
        """Why the sub-step, or the start state's signed distances, fell back to eager (None while both compile)."""
        return self._copies.fallback_reason or self._distances.fallback_reason

    @property
    def compiled(self) -> bool:
        """True while the sub-step and the start state's signed distances run compiled."""
        return self.fallback_reason is None

    @property
    def compiled_substep(self):
        """A compiled sub-step ``(state, u_sub, dt_sub) -> state`` alone (no stability check, no lock), for timing it
        from one thread (``bench model``)."""
        return self._copies.any_copy()

    def _checked_step(self, substep: Callable, state: State, u: Tensor) -> State:
        """``_checked_step`` through ``substep``, its start check taken from the last step's end check on this thread
        when ``state`` is the state that step returned."""
        known = getattr(self._end_check, "last", None)
        same = known is not None and state.phi is not None and state.phi is known[0]
        out, needed = _checked_step(self.model, state, u, substep, known[1] if same else None)
        self._end_check.last = None if needed is None else (out.phi, needed)
        return out


def rollout(model: Model, state: State, controls: Tensor) -> list[State]:
    """States ``x_0 .. x_K`` from ``state`` under ``controls (B, K, M, 6)``."""
    states = [state]
    for k in range(controls.shape[1]):
        states.append(step(model, states[-1], controls[:, k]))
    return states


def _unit_quaternions(poses: Tensor) -> Tensor:
    """Poses ``(..., 7)`` with their quaternions normalised."""
    return torch.cat([poses[..., :3], se3.quat_normalize(poses[..., 3:])], dim=-1)


def press_in(model: Model, object_pose: Tensor, body_poses: Tensor, steps: int = 4) -> State:
    """The state reached by pressing each body straight into its given pose from contact-free.

    ``object_pose (B, 7)``, ``body_poses (B, M, 7)``. Each body starts backed off along its own outward SDF
    gradient at the object's centre (by the deepest penetration plus 1 mm) and moves to its pose in
    ``steps`` kinematic steps with the model's contact model, the object held still. This is the consistent
    initial force state for a scene that starts in contact (an object resting on a table, held in a grasp):
    for NH, faces pressed along their normal carry ``E A depth`` and faces sliding in tangentially carry none.
    The poses' quaternions are normalised first, so their scale does not matter.
    """
    object_pose, body_poses = _unit_quaternions(object_pose), _unit_quaternions(body_poses)
    points = se3.transform_points(object_pose, model.points).unsqueeze(1)
    local = se3.transform_points(se3.inverse(body_poses), points)
    depth = torch.relu(-signed_distances(model, local)).amax(-1)
    centre = se3.transform_points(se3.inverse(body_poses), object_pose[:, None, None, :3])[:, :, 0]
    with torch.enable_grad():
        probe = centre.detach().requires_grad_(True)
        (grad,) = torch.autograd.grad(signed_distances(model, probe.unsqueeze(2)).sum(), probe)
    outward = se3.rotate_vectors(body_poses, torch.nn.functional.normalize(grad, dim=-1).unsqueeze(2))[:, :, 0]
    offset = (depth + 1e-3).unsqueeze(-1) * outward
    zeros = torch.zeros_like(offset)
    start = se3.retract(body_poses, torch.cat([-offset, zeros], dim=-1))
    state = State(object_pose, start, torch.zeros(*body_poses.shape[:2], model.n_points, 3, dtype=model.dtype,
                                                  device=model.device))
    for k in range(1, steps + 1):
        poses = se3.retract(body_poses, torch.cat([-offset * (1 - k / steps), zeros], dim=-1))
        state = advance_forces(model, state, object_pose, poses)
    return State(object_pose, body_poses, state.forces)
