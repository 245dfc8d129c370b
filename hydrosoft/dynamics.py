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
allowed.

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
import types
import warnings
from dataclasses import dataclass, replace
from typing import NamedTuple

import torch
from torch import Tensor

from hydrosoft.contact import ContactModel, ContactStep, Material, wrench
from hydrosoft.geometry import se3


class State(NamedTuple):
    """Quasi-dynamic state (paper IV-D). SI units, world frame.

    object_pose: ``(B, 7)`` pose of the rigid object (origin at its centre of mass).
    body_poses: ``(B, M, 7)`` poses of the compliant bodies.
    forces: ``(B, M, N, 3)`` force each body applies to each object surface point, N.
    phi: optional cache ``(B, P)`` of the signed distances (m) at these poses of the points each body can touch,
        body after body (``touchable_points``; ``P = M N`` when the model was not pruned per body). ``step`` and ``advance_forces`` fill it, and the next step uses it as ``phi_prev`` instead of
        evaluating the SDFs again; ``None`` means "compute it". It must describe this state's poses: build a new
        ``State`` without it (or ``_replace(phi=None)``) after editing the poses.
    """

    object_pose: Tensor
    body_poses: Tensor
    forces: Tensor
    phi: Tensor | None = None


@dataclass(frozen=True)
class Model:
    """A compiled scene: the minimal tensors and callables one step needs, in one dtype and device.

    points, normals: ``(N, 3)`` object-frame surface points (m) and outward unit normals; areas ``(N,)`` m^2.
    bodies: ``M`` signed distance functions, each mapping body-frame points ``(..., 3)`` to ``(...)`` metres.
    material: per-body ``E, K, mu``, each ``(M,)``. actuated: ``(M,)`` bool, bodies the controls move.
    mass (kg), inertia ``(3, 3)`` (kg m^2, object frame, about the centre of mass), gravity ``(3,)`` m/s^2.
    dt: step h (s); epsilon: the quasi-dynamic damping time (s); substeps: sub-steps per step.
    planar: the object moves in (x, y, yaw) only, its height and tilt held.
    touchable: per body, the indices ``(N_m,)`` of the points it can touch (per-body pruning by the scene
    compiler: a point out of a body's reach is never evaluated against it); ``()`` means every point for every body.
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


def stiffness_bound(model: Model, active: Tensor | None = None) -> float:
    """Upper bound of ``lambda_max(M^{-1} K_c)`` (1/s^2) over the points that can touch each body.

    ``K_c = sum_{m,i} active_{m,i} A_i J_i^T S_{m,i} J_i`` with ``S = E_m n n^T + K_m (I - n n^T)`` the per-point
    stiffness against body ``m`` and ``J_i = [I, -[p_i]x]`` the point Jacobian, in the object frame (so the
    bound does not depend on the object's pose); restricted to (x, y, yaw) for planar models. ``active (M, N)``
    bool marks the points that can touch each body (all by default). Exact when all of them are in contact
    at once, an upper bound otherwise (contact only removes terms).
    """
    p, n, a = model.points.double(), model.normals.double(), model.areas.double()
    if active is None:
        active = torch.ones(model.n_bodies, model.n_points, dtype=torch.bool)
    eye = torch.eye(3, dtype=torch.float64)
    nnT = n.unsqueeze(-1) * n.unsqueeze(-2)
    skew = torch.zeros(p.shape[0], 3, 3, dtype=torch.float64)
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -p[:, 2], p[:, 1], -p[:, 0]
    skew = skew - skew.transpose(1, 2)
    J = torch.cat([eye.expand_as(skew), -skew], dim=-1)
    weights = active.to(torch.float64).cpu() * a.cpu()
    E = (weights * model.material.E.double().cpu().view(-1, 1)).sum(0)
    K = (weights * model.material.K.double().cpu().view(-1, 1)).sum(0)
    S = E.view(-1, 1, 1) * nnT.cpu() + K.view(-1, 1, 1) * (eye - nnT.cpu())
    K_c = torch.einsum("nji,njk,nkl->il", J.cpu(), S, J.cpu())
    mass = torch.block_diag(model.mass * eye, model.inertia.double().cpu())
    if model.planar:
        keep = [0, 1, 5]
        K_c, mass = K_c[keep][:, keep], mass[keep][:, keep]
    return float(torch.linalg.eigvals(torch.linalg.solve(mass, K_c)).real.max())


def substeps_for(model: Model, max_substeps: int, active: Tensor | None = None) -> int:
    """Sub-steps per step that keep the explicit update stable, ``ceil(h^2 lambda / (2 * 0.9 epsilon))``.

    ``active (M, N)`` as in ``stiffness_bound``. Raises ValueError naming the bound when more than
    ``max_substeps`` would be needed.
    """
    lam = stiffness_bound(model, active)
    ratio = model.dt**2 * lam / model.epsilon
    n = max(1, math.ceil(ratio / (2 * 0.9)))
    if n > max_substeps:
        raise ValueError(
            f"quasi-dynamic step unstable: h^2/epsilon * lambda_max(M^-1 K_c) = {ratio:.3g} must stay below 2 "
            f"(h = {model.dt} s, epsilon = {model.epsilon} s, lambda <= {lam:.3g} 1/s^2 from the contact "
            f"stiffness E, K times the active area over mass {model.mass} kg); it needs {n} sub-steps but "
            f"max_substeps = {max_substeps}. Raise epsilon to >= {model.dt**2 * lam / 1.8:.3g} s, lower dt, "
            f"soften E/K, or allow more sub-steps."
        )
    return n


def _frame(pose: Tensor) -> tuple[Tensor, Tensor]:
    """Rotation matrices ``(..., 3, 3)`` and translations ``(..., 3, 1)`` of poses ``(..., 7)``."""
    return se3.quat_to_matrix(pose[..., 3:]), pose[..., :3].unsqueeze(-1)


def _world_points(model: Model, object_pose: Tensor) -> Tensor:
    """World-frame surface points ``(B, N, 3)`` (m) of the object at ``object_pose (B, 7)``.

    Computed as one ``(B, 3, 3) @ (3, N)`` product, so the result is a transposed view of a ``(B, 3, N)``
    tensor: each coordinate is contiguous over the points (see ``contact_geometry``).
    """
    R, t = _frame(object_pose)
    return (R @ model.points.mT + t).mT


def object_wrench(model: Model, state: State) -> Tensor:
    """Net wrench ``(B, 6)`` (N, N m) of the contact forces and gravity on the object, about its centre of mass."""
    w = wrench(state.forces.sum(1), _world_points(model, state.object_pose), state.object_pose[:, :3])
    gravity = torch.cat([model.mass * model.gravity, torch.zeros_like(model.gravity)])
    return w + gravity


def body_wrenches(model: Model, state: State) -> Tensor:
    """Wrench ``(B, M, 6)`` the object applies to each compliant body, about each body's origin (eq. 11)."""
    return wrench(-state.forces, _world_points(model, state.object_pose).unsqueeze(1), state.body_poses[..., :3])


def _object_motion(model: Model, state: State, w: Tensor, dt_sub: float) -> Tensor:
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
    return R_bT @ R_o.unsqueeze(1), R_bT @ (t_o.unsqueeze(1) - t_b), R_b, R_o


def touchable_points(model: Model) -> tuple[Tensor | None, ...]:
    """Per body, the indices ``(N_m,)`` of the surface points it can touch, or None for all ``N`` points."""
    return model.touchable if model.touchable else (None,) * model.n_bodies


def pair_counts(model: Model) -> list[int]:
    """Per body, the number ``N_m`` of points it is evaluated on; their sum is the width ``P`` of ``State.phi``."""
    return [model.n_points if index is None else index.numel() for index in touchable_points(model)]


def _body_groups(model: Model) -> list[tuple[slice, Tensor | None]]:
    """Bodies evaluated together, each group on one point set: all ``M`` bodies on every point (one batched
    evaluation) when the model is not pruned per body, else each body alone on its ``touchable`` indices."""
    if not model.touchable:
        return [(slice(0, model.n_bodies), None)]
    return [(slice(m, m + 1), index) for m, index in enumerate(model.touchable)]


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
    groups = _body_groups(model)
    cached = None if prev.phi is None else prev.phi.split(pair_counts(model), dim=-1)  # per body

    def distances(A: Tensor, c: Tensor, P: Tensor, bodies: slice) -> Tensor:
        local = (A[:, bodies] @ P + c[:, bodies]).mT
        return torch.stack([model.bodies[m](local[:, j]) for j, m in enumerate(range(bodies.start, bodies.stop))], 1)

    geometries = []
    for bodies, index in groups:
        points, normals, areas = model.points, model.normals, model.areas
        if index is not None:
            points, normals, areas = points[index], normals[index], areas[index]
        P = points.mT
        R = R_b1[:, bodies]
        geometries.append(ContactStep(
            phi_prev=distances(A0, c0, P, bodies) if cached is None else torch.stack(cached[bodies], dim=1),
            phi_next=distances(A1, c1, P, bodies),
            displacement=((R @ (A0[:, bodies] - A1[:, bodies])) @ P + R @ (c0[:, bodies] - c1[:, bodies])).mT,
            normal=(R_o1 @ -normals.mT).mT.unsqueeze(1),
            area=areas,
        ))
    return geometries


def advance_forces(model: Model, state: State, object_pose: Tensor, body_poses: Tensor) -> State:
    """Move object and bodies kinematically to the given poses and update the forces (step 4 of IV-D).

    ``object_pose (B, 7)`` and ``body_poses (B, M, 7)``; used by the step and to replay prescribed motions
    (force benchmarks, tactile estimation). Each body's forces are updated on the points it can touch
    (``touchable_points``) and stay zero elsewhere. The returned state caches its signed distances (``State.phi``).
    """
    n = model.n_points
    forces, phis = [], []
    geometries = contact_geometry(model, state, object_pose, body_poses)
    for geometry, (bodies, index) in zip(geometries, _body_groups(model)):
        material = Material(*(t[bodies] for t in model.material))
        previous = state.forces[:, bodies]
        if index is not None:
            previous = previous[:, :, index]
        f = model.contact.step(geometry, previous, material)
        if index is not None:
            f = f.new_zeros(f.shape[0], f.shape[1], n, 3).index_copy(2, index, f)
        forces.append(f)
        phis.append(geometry.phi_next.flatten(1))
    return State(object_pose, body_poses, torch.cat(forces, dim=1), torch.cat(phis, dim=-1))


def _substep(model: Model, state: State, u: Tensor, dt_sub: float) -> State:
    body_poses = se3.retract(state.body_poses, u * model.actuated.view(1, -1, 1))
    w = object_wrench(model, state)
    object_pose = se3.retract(state.object_pose, _object_motion(model, state, w, dt_sub))
    return advance_forces(model, state, object_pose, body_poses)


def _substep_of(model: Model):
    """The sub-step of ``model`` as a function ``(state, u_sub) -> state`` (``model`` and ``h / n`` bound)."""
    return functools.partial(_substep, model, dt_sub=model.dt / model.substeps)


def _integrate(model: Model, state: State, u: Tensor, substep) -> State:
    """``model.substeps`` applications of ``substep(state, u / n)``: one step of length ``model.dt``."""
    n = model.substeps
    u_sub = u if n == 1 else u / n
    for _ in range(n):
        state = substep(state, u_sub)
    return state


def step(model: Model, state: State, u: Tensor) -> State:
    """One quasi-dynamic step of length ``model.dt``: ``State (B, ...)``, ``u (B, M, 6)`` -> ``State``."""
    return _integrate(model, state, u, _substep_of(model))


def _bound_substep(model: Model):
    """The sub-step of ``model`` as a plain function ``(state, u_sub) -> state``."""
    substep = _substep_of(model)

    def compiled_substep(state: State, u: Tensor) -> State:
        return substep(state, u)

    return compiled_substep


def _private_copy(fn):
    """``fn`` with a code object of its own.

    Dynamo keeps compiled graphs, and counts recompilations against ``torch._dynamo.config.recompile_limit``
    (8), per code object. Every ``CompiledStep`` would otherwise compile the same code: the third model
    compiled in a process (4 signatures each) would pass the limit and silently run eager.
    """
    return types.FunctionType(fn.__code__.replace(), fn.__globals__, fn.__name__, fn.__defaults__, fn.__closure__)


class CompiledStep:
    """``step(model, state, u)`` with its sub-step compiled by ``torch.compile`` (inductor), and an eager fallback.

    Only one sub-step is compiled and the sub-step loop stays in Python, so the graphs stay small whatever
    ``model.substeps`` is (compiling the whole step put every sub-step into each graph: minutes to compile).

    ``CompiledStep(model, **options)(state, u)`` returns what ``step(model, state, u)`` returns, within float
    rounding (the compiled kernels reassociate sums: about 1e-7 relative in float32, 1e-15 in float64). The
    first call for each new input signature (dtype, device, shape, whether ``state.phi`` is cached, whether
    gradients are needed) compiles: tens of seconds on a CPU, which pays off over long rollouts or many planner
    iterations. ``options`` go to ``torch.compile`` (e.g. ``dynamic=True`` to compile once for all batch sizes).
    With the default inductor backend and no ``mode``/``options`` given, inductor's C++ wrapper is used
    (``options={"cpp_wrapper": True}``): it launches the kernels from C++ instead of Python, which halves a
    batch-1 step (0.27 -> 0.14 ms measured on the pushing scene) for a few more seconds of compilation.
    If compilation fails (no C++ compiler, an unsupported platform, more than dynamo's ``recompile_limit`` of 8
    input signatures on one instance), it warns once and runs the eager ``step`` from then on;
    ``fallback_reason`` then says why: dynamo's own fallback past its limit would be silent. Each instance
    compiles a private copy of the sub-step's code, so any number of instances (one per model) stay compiled.
    Nothing in the library requires it.
    """

    def __init__(self, model: Model, **options) -> None:
        self.model = model
        self.fallback_reason: str | None = None
        if options.get("backend", "inductor") == "inductor" and not {"mode", "options"} & options.keys():
            options["options"] = {"cpp_wrapper": True}
        self._compiled = torch.compile(_private_copy(_bound_substep(model)), **options)

    @property
    def compiled(self) -> bool:
        """True while the compiled path is in use (False after a fallback to eager)."""
        return self.fallback_reason is None

    def __call__(self, state: State, u: Tensor) -> State:
        """One step, ``State (B, ...)``, ``u (B, M, 6)`` -> ``State``."""
        if self.fallback_reason is None:
            config = torch._dynamo.config  # set and restored by hand: config.patch costs ~16 us per call
            previous, config.fail_on_recompile_limit_hit = config.fail_on_recompile_limit_hit, True
            try:
                return _integrate(self.model, state, u, self._compiled)
            except Exception as err:  # noqa: BLE001 - a compiler failure; a genuine error recurs in the eager step
                self.fallback_reason = f"{type(err).__name__}: {err}"
                warnings.warn(f"torch.compile of the step failed, running eager: {self.fallback_reason}",
                              RuntimeWarning, stacklevel=2)
            finally:
                config.fail_on_recompile_limit_hit = previous
        return step(self.model, state, u)


def rollout(model: Model, state: State, controls: Tensor) -> list[State]:
    """States ``x_0 .. x_K`` from ``state`` under ``controls (B, K, M, 6)``."""
    states = [state]
    for k in range(controls.shape[1]):
        states.append(step(model, states[-1], controls[:, k]))
    return states


def press_in(model: Model, object_pose: Tensor, body_poses: Tensor, steps: int = 4) -> State:
    """The state reached by pressing each body straight into its given pose from contact-free.

    ``object_pose (B, 7)``, ``body_poses (B, M, 7)``. Each body starts backed off along its own outward SDF
    gradient at the object's centre (by the deepest penetration plus 1 mm) and moves to its pose in
    ``steps`` kinematic steps with the model's contact model, the object held still. This is the consistent
    initial force state for a scene that starts in contact (an object resting on a table, held in a grasp):
    for NH, faces pressed along their normal carry ``E A depth`` and faces sliding in tangentially carry none.
    """
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
