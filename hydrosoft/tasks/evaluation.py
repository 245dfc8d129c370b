"""Open- and closed-loop evaluation of a task: a simulated plant, the tactile state estimate, the MPC loop.

The plant (the "world") is its own compiled instance of the task scene, finer than the planner by default:
half the surface spacing and half the time step (each control step runs twice as many sub-steps with the
control split evenly and the mobility ``h / epsilon`` held, ``dynamics.step``), with a configurable contact
model and optional seeded measurement noise. Planner and plant share no tensors and no state: the planner only
sees measurements.

- Open loop: one solve from the measured initial state over the whole episode (horizon = episode length,
  ``open_loop_iterations`` CEM rounds), then the plan is executed on the plant.
- Closed loop: every control step the planner's state is rebuilt from the plant's measurement and solved
  again (paper IV-E, V-A): object pose (optionally noisy), body poses (proprioception) and contact forces from
  the tactile model: plant forces -> ``deformation_from_forces`` (plant areas, materials) -> ``resample`` to
  the planner's points by object-frame nearest neighbour -> ``forces_from_deformation`` (planner areas,
  materials); the first action is applied to the plant.

Episode status, the first that applies: ``diverged`` (the plant's state became non-finite; the episode stops at
the last finite state), ``no_finite_plan`` (a solve had no sample with a finite cost; the rest action was
applied), ``unreachable`` (the goal lies beyond what the action bounds could achieve in the episode's steps,
``Task.reachable``), ``reached`` (final ADD <= the task's ``success_mm``), ``not_reached``. Errors are always
finite.
"""

from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass, field, replace
from typing import Callable, Literal, NamedTuple

import msgspec
import torch
from torch import Tensor

from hydrosoft.control import CemGd, CemGdConfig
from hydrosoft.control.costs import orientation_error, position_error
from hydrosoft.dynamics import CompiledStep, Model, State, step
from hydrosoft.geometry import se3
from hydrosoft.scene import Scene, build_surface, compile_scene
from hydrosoft.tactile import deformation_from_forces, forces_from_deformation, nearest_indices, resample
from hydrosoft.tasks.base import Task, mean_point_distance

METRIC_SPACING_M = 0.005  # surface spacing of the points the ADD error is measured on (fixed for all settings)
Loop = Literal["open", "closed"]


@dataclass(frozen=True)
class PlannerSettings:
    """The planner's model and CEM-GD settings (paper Algorithm 1).

    model: contact model (``nh``, ``snh``, ``pf``, ``pff``). spacing: object surface spacing (m), None for the
    scene's. samples B, elites M, horizon K, grad_steps G, cem_iterations per closed-loop solve;
    open_loop_iterations: CEM rounds of the single open-loop solve. substep_factor: sub-steps per compiled sub-step
    (a finer integration step ``dt / (substeps * factor)`` within each control step). lr, init_std, min_std: fractions of the
    action half-range (``CemGdConfig``). dtype: the planner's float type. seed: the solver's seed.
    sdf_solver_steps: None, or a fixed number of solver steps for the planner's iteratively solved body SDFs
    (the ellipsoid's ``solver_steps``: 2 is exact to rounding within 1 cm of the membrane and fuses into one
    kernel when compiled); the plant always solves to convergence.
    compile: run the planner's step through ``dynamics.CompiledStep`` (``torch.compile``, eager fallback with a
    warning). ``prepare`` builds one instance per setup, shared by every solver made from it, so each input
    signature compiles once: the first solve pays for the four a CEM-GD solve uses (gradient-enabled and no-grad
    rollouts, each with a first step from the measured state and later steps from the step's own outputs, which
    differ in strides, cached signed distances and ``requires_grad``); ``CompiledStep`` compiles one sub-step, so
    this is about two minutes on one CPU thread for the full pushing planner.
    """

    model: str = "nh"
    spacing: float | None = None
    samples: int = 64
    elites: int = 8
    horizon: int = 10
    grad_steps: int = 2
    cem_iterations: int = 1
    open_loop_iterations: int = 4
    substep_factor: int = 1
    lr: float = 0.1
    init_std: float = 0.5
    min_std: float = 0.05
    dtype: torch.dtype = torch.float64
    seed: int = 0
    sdf_solver_steps: int | None = None
    compile: bool = False

    def config(self, horizon: int, iterations: int) -> CemGdConfig:
        """The solver configuration for a plan of ``horizon`` steps and ``iterations`` CEM rounds."""
        return CemGdConfig(
            samples=self.samples, elites=min(self.elites, self.samples), horizon=horizon,
            grad_steps=self.grad_steps, cem_iterations=iterations, lr=self.lr, init_std=self.init_std,
            min_std=self.min_std, seed=self.seed,
        )


@dataclass(frozen=True)
class PlantSettings:
    """The simulated world.

    model: its contact model (``nh`` by default: the best model of the membrane we have). spacing_factor: its
    surface spacing relative to the planner's (0.5: finer). substep_factor: sub-steps per planner sub-step (2:
    half the time step). pose_noise_m / pose_noise_rad: std of the seeded Gaussian noise on the observed
    object position (m, per axis) and orientation (rad, rotation vector per axis). deformation_noise_m: std of
    the noise on the observed membrane deformation (m, per axis, at points in contact). seed: noise seed.
    """

    model: str = "nh"
    spacing_factor: float = 0.5
    substep_factor: int = 2
    pose_noise_m: float = 0.0
    pose_noise_rad: float = 0.0
    deformation_noise_m: float = 0.0
    seed: int = 0


class Measurement(NamedTuple):
    """What the sensors report: ``object_pose (1, 7)`` (tags, maybe noisy), ``body_poses (1, M, 7)``
    (proprioception), ``deformation (1, M, N, 3)`` (m, world frame, on the plant's surface points)."""

    object_pose: Tensor
    body_poses: Tensor
    deformation: Tensor


def with_contact(scene: Scene, contact: str, spacing: float) -> Scene:
    """The scene with another contact model and object surface spacing (m)."""
    return msgspec.structs.replace(
        scene, contact=contact, object=msgspec.structs.replace(scene.object, spacing=spacing)
    )


def with_solver_steps(scene: Scene, steps: int | None) -> Scene:
    """The scene with its ellipsoid bodies solved in ``steps`` fixed solver steps (None: unchanged)."""
    if steps is None:
        return scene
    bodies = [msgspec.structs.replace(b, params={**b.params, "solver_steps": steps}) if b.sdf == "ellipsoid" else b
              for b in scene.bodies]
    return msgspec.structs.replace(scene, bodies=bodies)


class Plant:
    """The simulated world of a task: a compiled model, its state, and its sensors.

    ``apply(u)`` runs one control step with ``u (M, 6)`` in the plant's body order; ``measure()`` returns a
    ``Measurement``. Its tensors never leave it: measurements are fresh tensors.
    """

    def __init__(self, scene: Scene, settings: PlantSettings, planner_spacing: float) -> None:
        spacing = planner_spacing * settings.spacing_factor
        model, state, _ = compile_scene(with_contact(scene, settings.model, spacing))
        self.model = replace(model, substeps=model.substeps * settings.substep_factor)
        self.initial = state
        self.settings = settings
        self.reset()

    def reset(self) -> None:
        """Back to the initial state; reseed the sensor noise."""
        self.state = State(*(t.clone() for t in self.initial[:3]))
        self.generator = torch.Generator().manual_seed(self.settings.seed)

    def apply(self, u: Tensor) -> bool:
        """One control step under ``u (M, 6)``; returns False (and keeps the old state) if it became non-finite."""
        nxt = step(self.model, self.state, u.to(self.model.dtype).unsqueeze(0))
        if not all(bool(torch.isfinite(t).all()) for t in nxt[:3]):
            return False
        self.state = State(*(t.detach() for t in nxt[:3]))
        return True

    def inward_normals(self, object_pose: Tensor) -> Tensor:
        """Inward object normals ``(1, 1, N, 3)`` in the world frame at ``object_pose (1, 7)``."""
        return -se3.rotate_vectors(object_pose, self.model.normals).unsqueeze(1)

    def measure(self) -> Measurement:
        """Sensor readings of the current state, with the configured noise."""
        s, m, g = self.settings, self.model, self.generator
        true_pose = self.state.object_pose
        deformation = deformation_from_forces(self.state.forces, self.inward_normals(true_pose), m.areas, m.material)
        if s.deformation_noise_m > 0:
            touching = (self.state.forces.abs().sum(-1, keepdim=True) > 0).to(deformation.dtype)
            noise = torch.randn(deformation.shape, generator=g, dtype=deformation.dtype)
            deformation = deformation + s.deformation_noise_m * touching * noise
        pose = true_pose.clone()
        if s.pose_noise_m > 0 or s.pose_noise_rad > 0:
            noise = torch.randn(1, 6, generator=g, dtype=pose.dtype)
            scale = torch.tensor([s.pose_noise_m] * 3 + [s.pose_noise_rad] * 3, dtype=pose.dtype)
            pose = se3.retract(pose, noise * scale)
        return Measurement(pose, self.state.body_poses.clone(), deformation)


@dataclass(frozen=True)
class Setup:
    """A task compiled for evaluation: planner model, plant, and the maps between their points and bodies.

    point_index ``(N_planner,)``: nearest plant point of each planner point (object frame, normals weighted so
    faces do not mix). body_index ``(M_planner,)``: plant body of each planner body (by name), which maps
    measurements to the planner and actions to the plant. metric_points ``(N, 3)``: object-frame points (5 mm
    spacing, the same for every setting) on which the ADD error is measured. dynamics: the planner's step
    ``(state, u) -> state`` on planner_model, a ``CompiledStep`` when ``planner.compile`` is set (one per setup,
    shared by every solve on it, so it compiles once).
    """

    task: Task
    planner: PlannerSettings
    planner_model: Model
    dynamics: Callable[[State, Tensor], State]
    plant: Plant
    point_index: Tensor
    body_index: Tensor
    metric_points: Tensor


def prepare(
    task: Task,
    planner: PlannerSettings = PlannerSettings(),
    plant: PlantSettings = PlantSettings(),
    compile_options: dict | None = None,
) -> Setup:
    """Compile the planner's model and the plant for ``task``.

    ``compile_options`` go to ``CompiledStep`` (``torch.compile`` options, e.g. ``backend="eager"``) when
    ``planner.compile`` is set, on top of ``dynamic=False``: the planner's shapes are fixed per setup, and static
    kernels are the fast ones (inductor with its C++ wrapper by default).
    """
    spacing = planner.spacing or task.scene.object.spacing
    scene = with_solver_steps(with_contact(task.scene, planner.model, spacing), planner.sdf_solver_steps)
    model, _, _ = compile_scene(scene, dtype=planner.dtype)
    model = replace(model, substeps=model.substeps * planner.substep_factor)
    world = Plant(task.scene, plant, spacing)
    weight = spacing
    source = torch.cat([world.model.points, weight * world.model.normals], -1)
    target = torch.cat([model.points.double(), weight * model.normals.double()], -1)
    missing = [name for name in model.body_names if name not in world.model.body_names]
    if missing:
        raise ValueError(f"the plant has no body {missing} that the planner moves")
    body_index = torch.tensor([world.model.body_names.index(name) for name in model.body_names])
    metric = build_surface(msgspec.structs.replace(task.scene.object, spacing=METRIC_SPACING_M)).points
    if planner.compile:
        dynamics = CompiledStep(model, **{"dynamic": False, **(compile_options or {})})
    else:
        dynamics = functools.partial(step, model)
    return Setup(task, planner, model, dynamics, world, nearest_indices(source, target), body_index, metric)


def estimate_state(setup: Setup, measurement: Measurement) -> State:
    """The planner's state ``(B = 1)`` from a measurement: pose, proprioception and tactile forces (eq. 22-24)."""
    model = setup.planner_model
    pose = measurement.object_pose.to(model.dtype)
    deformation = resample(measurement.deformation[:, setup.body_index], setup.point_index).to(model.dtype)
    normal = -se3.rotate_vectors(pose, model.normals).unsqueeze(1)
    forces = forces_from_deformation(deformation, normal, model.areas, model.material)
    return State(object_pose=pose, body_poses=measurement.body_poses[:, setup.body_index].to(model.dtype), forces=forces)


@dataclass
class EpisodeResult:
    """One episode. Errors are ADD (mm), position (mm) and angle (deg) of the plant's object vs the goal.

    errors_mm: ADD after each control step, ``steps + 1`` values (the first is the initial error).
    actions: ``(steps, M, 6)`` actions applied (planner body order). solve_s and the split rollout_s,
    backward_s, cem_s: mean wall seconds per solve call
    (solve_s includes the state estimate). solves: number of solve calls.
    """

    task: str
    model: str
    loop: str
    status: str
    error_mm: float
    position_mm: float
    angle_deg: float
    initial_error_mm: float
    success: bool
    solves: int
    solve_s: float
    rollout_s: float
    backward_s: float
    cem_s: float
    errors_mm: list[float] = field(default_factory=list)
    actions: Tensor | None = None
    final_pose: Tensor | None = None


def _errors(setup: Setup, pose: Tensor, goal: Tensor) -> tuple[float, float, float]:
    """``(ADD mm, position mm, angle deg)`` of ``pose (1, 7)`` against ``goal (7,)``."""
    add = float(mean_point_distance(setup.metric_points, pose[0].double(), goal))
    pos = float(position_error(pose[0].double(), goal))
    ang = float(orientation_error(pose[0].double(), goal))
    return 1e3 * add, 1e3 * pos, math.degrees(ang)


def run_episode(
    setup: Setup,
    goal: Tensor,
    loop: Loop = "closed",
    steps: int | None = None,
    on_step: Callable[[int, float], None] | None = None,
) -> EpisodeResult:
    """Run one episode of ``steps`` control steps (the task's by default) towards ``goal (7,)`` (float64).

    ``on_step(k, error_mm)`` is called after every control step (progress reports). Never raises for an
    unreachable goal, a contact-free start or a plan without a finite sample: the status says what happened.
    """
    task, planner, plant = setup.task, setup.planner, setup.plant
    steps = task.steps if steps is None else steps
    model = setup.planner_model
    plant.reset()
    low, high = task.bounds(model.body_names, model.dtype)
    stage, terminal = task.costs(model, goal)
    horizon, iterations = (steps, planner.open_loop_iterations) if loop == "open" else (
        planner.horizon, planner.cem_iterations)
    solver = CemGd(
        setup.dynamics, stage, terminal, low, high,
        config=planner.config(horizon, iterations), dtype=model.dtype,
    )
    start_error = _errors(setup, plant.state.object_pose, goal)[0]
    errors, actions, timings = [start_error], [], []
    no_finite = diverged = False
    plan = None
    for k in range(steps):
        if loop == "closed" or plan is None:
            tic = time.perf_counter()
            result = solver.solve(estimate_state(setup, plant.measure()))
            timings.append({**result.timings, "solve_s": time.perf_counter() - tic})
            no_finite |= result.status != "ok"
            plan = result.plan
        u = plan[0] if loop == "closed" else plan[k]
        u = u.detach().clamp(low, high)
        plant_u = torch.zeros(plant.model.n_bodies, 6, dtype=plant.model.dtype)
        plant_u[setup.body_index] = u.to(plant.model.dtype)
        if not plant.apply(plant_u):
            diverged = True
            break
        actions.append(u.double())
        errors.append(_errors(setup, plant.state.object_pose, goal)[0])
        if on_step is not None:
            on_step(k, errors[-1])

    add, pos, ang = _errors(setup, plant.state.object_pose, goal)
    success = add <= task.success_mm
    start = plant.initial.object_pose[0]
    if diverged:
        status = "diverged"
    elif no_finite:
        status = "no_finite_plan"
    elif not task.reachable(start, goal, steps):
        status = "unreachable"
    else:
        status = "reached" if success else "not_reached"
    keys = ("solve_s", "rollout_s", "backward_s", "cem_s")
    mean = {key: sum(t[key] for t in timings) / max(len(timings), 1) for key in keys}
    return EpisodeResult(
        task=task.name, model=planner.model, loop=loop, status=status, error_mm=add, position_mm=pos,
        angle_deg=ang, initial_error_mm=start_error, success=success, solves=len(timings),
        solve_s=mean["solve_s"], rollout_s=mean["rollout_s"], backward_s=mean["backward_s"], cem_s=mean["cem_s"],
        errors_mm=errors,
        actions=torch.stack(actions) if actions else torch.zeros(0, model.n_bodies, 6, dtype=torch.float64),
        final_pose=plant.state.object_pose[0].clone(),
    )
