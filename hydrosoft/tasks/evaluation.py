"""Open- and closed-loop evaluation of a task: a simulated plant, the tactile state estimate, the MPC loop.

The plant (the "world") is its own compiled instance of the task scene, finer than the planner by default:
half the surface spacing and half the time step (each control step runs twice as many sub-steps with the
control split evenly and the mobility ``h / epsilon`` held, ``dynamics.step``), with a configurable contact
model and optional seeded measurement noise. Planner and plant share no tensors and no state: the planner only
sees measurements.

- Open loop: one solve from the measured initial state over the whole episode (horizon = episode length,
  ``open_loop_iterations`` CEM rounds), then the plan is executed on the plant.
- Closed loop: every control step the planner's state is rebuilt from what the plant's sensors observe and
  solved again (paper IV-E, V-A): the object pose (tags, optionally noisy), the body poses (the arm) and, per
  Soft Bubble, the depth of each planner surface point inside its nominal membrane, computed from the plant's
  geometry (``tactile.membrane_penetration``: what its depth camera sees; optionally noisy). The plant's force
  state never leaves it. ``tactile.estimate_state`` turns the observation into the planner's state, carrying
  shear and the table's forces over from the planner's own prediction of this instant (the state after the
  applied action in the solver's rollout of its plan, ``PlanResult.states``); the first action is applied to
  the plant.

The plant is finer than the planner by default (``PlantSettings()``); ``PlantSettings.same_as_planner()`` is the
planner's own model (the paper's simulation setting, as far as we can tell), which separates what model
mismatch costs from what the controller achieves. An episode lasts ``Task.episode_steps(goal)`` control steps
(at least the task's, longer for goals whose travel needs more under the action bounds); a goal beyond reach
even so is marked ``unreachable`` before any planning.

Episode status, the first that applies: ``diverged`` (the plant's state became non-finite; the episode stops at
the last finite state), ``no_finite_plan`` (a solve had no sample with a finite cost; the rest action was
applied), ``unreachable`` (the goal lies beyond what the action bounds could achieve in the episode's steps,
``Task.reachable``), ``reached`` (final ADD <= the task's ``success_mm``), ``not_reached``. Errors are always
finite.
"""

from __future__ import annotations

import functools
import math
import pickle
import time
from dataclasses import dataclass, field, replace
from collections.abc import Mapping
from typing import Callable, Literal, NamedTuple

import msgspec
import torch
from torch import Tensor

from hydrosoft.control import CemGd, CemGdConfig, WorkerProcesses
from hydrosoft.control.costs import orientation_error, position_error
from hydrosoft.dynamics import CompiledStep, Model, State, step, with_object_update
from hydrosoft.geometry import se3
from hydrosoft.scene import Scene, build_surface, compile_scene
from hydrosoft.tactile import TactileObservation, carry_over, estimate_state, membrane_penetration, sensor_bodies
from hydrosoft.tasks.base import EAGER_COST_TERMS, CostTerms, Task, compiled_cost_terms, mean_point_distance

METRIC_SPACING_M = 0.005  # surface spacing of the points the ADD error is measured on (fixed for all settings)
Loop = Literal["open", "closed"]


@dataclass(frozen=True)
class PlannerSettings:
    """The planner's model and CEM-GD settings (paper Algorithm 1).

    model: contact model (``nh``, ``snh``, ``pf``, ``pff``, ``nh_pressure_normal``). spacing: object surface
    spacing (m), None for the scene's. samples B, elites M, horizon K, grad_steps G, cem_iterations per closed-loop
    solve; open_loop_iterations: CEM rounds of the single open-loop solve. substep_factor: sub-steps per compiled sub-step
    (a finer integration step ``dt / (substeps * factor)`` within each control step). lr, init_std, min_std: fractions of the
    action half-range (``CemGdConfig``). dtype: the planner's float type. seed: the solver's seed.
    workers: solver threads that each roll out a share of the B samples (``CemGdConfig.workers``; 1: none).
    chunks: with two workers or more, the pieces the samples are cut into, each taken by whichever worker is free
    (``CemGdConfig.chunks``; 0: one per worker).
    worker_processes: run the ``workers`` shares in processes of their own instead of threads
    (``control.WorkerProcesses``; each builds its own copy of the model, step and costs: ``build_problem``).
    sdf_solver_steps: None, or a fixed number of solver steps for the planner's iteratively solved body SDFs
    (the ellipsoid's ``solver_steps``: 2 is exact to rounding within 1 cm of the membrane and fuses into one
    kernel when compiled); the plant always solves to convergence.
    object_update: the planner model's object update (``Model.object_update``): ``"explicit"`` (the paper's,
    sub-stepped as the scene's contacts need) or ``"linearly_implicit"`` (one sub-step per control step, stable at
    any stiffness; NH and SNH). substep_factor multiplies either count.
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
    workers: int = 1
    chunks: int = 0
    object_update: str = "explicit"
    worker_processes: bool = False

    def config(self, horizon: int, iterations: int) -> CemGdConfig:
        """The solver configuration for a plan of ``horizon`` steps and ``iterations`` CEM rounds."""
        return CemGdConfig(
            samples=self.samples, elites=min(self.elites, self.samples), horizon=horizon,
            grad_steps=self.grad_steps, cem_iterations=iterations, lr=self.lr, init_std=self.init_std,
            min_std=self.min_std, seed=self.seed, workers=self.workers, chunks=self.chunks,
        )


@dataclass(frozen=True)
class PlantSettings:
    """The simulated world.

    model: its contact model (``nh`` by default: the best model of the membrane we have). spacing_factor: its
    surface spacing relative to the planner's (0.5: finer). substep_factor: sub-steps per planner sub-step (2:
    half the time step). pose_noise_m / pose_noise_rad: std of the seeded Gaussian noise on the observed
    object position (m, per axis) and orientation (rad, rotation vector per axis). deformation_noise_m: std of
    the noise on the observed membrane deformation (m, at points in contact; the result is clipped at 0).
    seed: noise seed.
    """

    model: str = "nh"
    spacing_factor: float = 0.5
    substep_factor: int = 2
    pose_noise_m: float = 0.0
    pose_noise_rad: float = 0.0
    deformation_noise_m: float = 0.0
    seed: int = 0

    @classmethod
    def same_as_planner(cls, model: str = "nh") -> PlantSettings:
        """A plant with the planner's own spacing and time step (and contact model ``model``)."""
        return cls(model=model, spacing_factor=1.0, substep_factor=1)

    @property
    def label(self) -> str:
        """``finer`` or ``same`` (spacing and step as the planner's), as the benchmarks name plants."""
        return "same" if self.spacing_factor == 1.0 and self.substep_factor == 1 else "finer"


def with_contact(scene: Scene, contact: str, spacing: float) -> Scene:
    """The scene with another contact model and object surface spacing (m)."""
    return msgspec.structs.replace(
        scene, contact=contact, object=msgspec.structs.replace(scene.object, spacing=spacing)
    )


def with_body_materials(scene: Scene, materials: Mapping[str, Mapping[str, float]]) -> Scene:
    """The scene with the material of some bodies replaced: ``materials`` maps a body's name to the values it
    changes (``E``, ``K`` in Pa/m, ``mu``), e.g. a fitted Soft Bubble's; ValueError naming a body the scene lacks
    or a key that is not E, K or mu (``BodySpec`` checks the values and names the field)."""
    names = [b.name for b in scene.bodies]
    for name, values in materials.items():
        if name not in names:
            raise ValueError(f"no body {name!r} in the scene to give a material (bodies: {', '.join(names)})")
        unknown = sorted(set(values) - {"E", "K", "mu"})
        if unknown:
            raise ValueError(f"bodies[{name}]: {', '.join(unknown)} is not a material value (E, K, mu)")
    bodies = [msgspec.structs.replace(b, **materials[b.name]) if b.name in materials else b for b in scene.bodies]
    return msgspec.structs.replace(scene, bodies=bodies)


def with_solver_steps(scene: Scene, steps: int | None) -> Scene:
    """The scene with its ellipsoid bodies solved in ``steps`` fixed solver steps (None: unchanged)."""
    if steps is None:
        return scene
    bodies = [msgspec.structs.replace(b, params={**b.params, "solver_steps": steps}) if b.sdf == "ellipsoid" else b
              for b in scene.bodies]
    return msgspec.structs.replace(scene, bodies=bodies)


class Plant:
    """The simulated world of a task: a compiled model, its state, and its sensors.

    ``apply(u)`` runs one control step with ``u (M, 6)`` in the plant's body order; ``observe(...)`` returns what
    the sensors see. Its tensors never leave it: observations are fresh tensors computed from its geometry.
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

    def observe(self, points: Tensor, body_index: Tensor, sensors: Tensor) -> TactileObservation:
        """What the sensors see, with the configured noise, for a planner whose surface points are ``points
        (N, 3)`` (object frame) and whose bodies are the plant's ``body_index (M,)``, with sensor bodies ``sensors
        (S,)`` (planner indices): the object pose (tags), the planner's bodies' poses (arm) and the depth of each
        planner point inside each sensor's nominal membrane at the true poses (float64)."""
        s, m, g = self.settings, self.model, self.generator
        true_pose = self.state.object_pose
        plant_sensors = body_index[sensors]
        penetration = membrane_penetration([m.bodies[int(j)] for j in plant_sensors], points.double(), true_pose,
                                           self.state.body_poses[:, plant_sensors])
        if s.deformation_noise_m > 0:
            noise = torch.randn(penetration.shape, generator=g, dtype=penetration.dtype)
            penetration = torch.relu(penetration + s.deformation_noise_m * (penetration > 0) * noise)
        pose = true_pose.clone()
        if s.pose_noise_m > 0 or s.pose_noise_rad > 0:
            noise = torch.randn(1, 6, generator=g, dtype=pose.dtype)
            scale = torch.tensor([s.pose_noise_m] * 3 + [s.pose_noise_rad] * 3, dtype=pose.dtype)
            pose = se3.retract(pose, noise * scale)
        return TactileObservation(pose, self.state.body_poses[:, body_index].clone(), penetration)


@dataclass(frozen=True)
class Setup:
    """A task compiled for evaluation: planner model, plant, and the map between their bodies.

    body_index ``(M_planner,)``: plant body of each planner body (by name), which maps observations to the
    planner and actions to the plant. sensors ``(S,)``: the planner's sensor bodies (``tactile.sensor_bodies``). metric_points ``(N, 3)``: object-frame points (5 mm
    spacing, the same for every setting) on which the ADD error is measured. dynamics: the planner's step
    ``(state, u) -> state`` on planner_model, a ``CompiledStep`` when ``planner.compile`` is set (one per setup,
    shared by every solve on it, so it compiles once). cost_terms: what evaluates the costs (``Task.costs``),
    compiled with the step, and as it is shared by every goal. processes: the solver's worker processes when
    ``planner.worker_processes`` is set (``solver_processes`` gives them each goal's problem; ``close`` stops them).
    compile_options: what ``prepare`` was given, which the worker processes compile their steps with.
    """

    task: Task
    planner: PlannerSettings
    planner_model: Model
    dynamics: Callable[[State, Tensor], State]
    plant: Plant
    body_index: Tensor
    sensors: Tensor
    metric_points: Tensor
    cost_terms: CostTerms = EAGER_COST_TERMS
    processes: WorkerProcesses | None = None
    compile_options: dict | None = None

    def close(self) -> None:
        """Stop the worker processes, if any."""
        if self.processes is not None:
            self.processes.close()


def prepare(
    task: Task,
    planner: PlannerSettings = PlannerSettings(),
    plant: PlantSettings = PlantSettings(),
    compile_options: dict | None = None,
) -> Setup:
    """Compile the planner's model and the plant for ``task``.

    ``compile_options`` go to ``CompiledStep`` (``torch.compile`` options, e.g. ``backend="eager"``) when
    ``planner.compile`` is set, on top of ``dynamic=False``: the planner's shapes are fixed per setup, and static
    kernels are the fast ones (inductor with its C++ wrapper by default on the CPU, CUDA graphs on a GPU:
    ``compilation.with_default_options``). They go to the compiled cost terms
    (``compiled_cost_terms``) too, where dynamo's automatic dynamic shapes stay on: an open-loop plan's horizon
    is each episode's length. With ``planner.worker_processes`` it starts the solver's worker processes, which build
    their own step with the same options (``build_problem``; ``Setup.close`` stops them).
    """
    spacing = planner.spacing or task.scene.object.spacing
    model = planner_model(task, planner)
    world = Plant(task.scene, plant, spacing)
    missing = [name for name in model.body_names if name not in world.model.body_names]
    if missing:
        raise ValueError(f"the plant has no body {missing} that the planner moves")
    body_index = torch.tensor([world.model.body_names.index(name) for name in model.body_names])
    metric = build_surface(msgspec.structs.replace(task.scene.object, spacing=METRIC_SPACING_M)).points
    dynamics, costs = planner_calls(model, planner, compile_options)
    processes = None
    if planner.worker_processes:
        low, high = task.bounds(model.body_names, model.dtype)
        processes = WorkerProcesses(build_problem, planner.workers, low, high, planner.config(planner.horizon, 1),
                                    planner.dtype, threads=torch.get_num_threads())
    return Setup(task, planner, model, dynamics, world, body_index, sensor_bodies(model), metric, costs, processes,
                 compile_options)


def planner_model(task: Task, planner: PlannerSettings) -> Model:
    """The planner's model of ``task``'s scene: its contact model, spacing, SDF solver steps, object update and
    sub-steps as ``planner`` sets them."""
    spacing = planner.spacing or task.scene.object.spacing
    scene = with_solver_steps(with_contact(task.scene, planner.model, spacing), planner.sdf_solver_steps)
    model, _, _ = compile_scene(scene, dtype=planner.dtype)
    model = with_object_update(model, planner.object_update)
    return replace(model, substeps=model.substeps * planner.substep_factor)


class SolverProblem(NamedTuple):
    """What a solver worker process builds its share's problem from (``build_problem``); picklable."""

    task: Task
    planner: PlannerSettings
    compile_options: dict | None
    goal: Tensor  # (7,) float64
    anchor: tuple[Tensor, Tensor] | None  # as ``Task.costs`` takes it
    eager_costs: bool = False  # the costs eager even when the step is compiled (benchmarks compare the two)


_WORKER_PLANNERS: dict[bytes, tuple[Model, Callable, CostTerms]] = {}
"""In a worker process: the planner model, step and cost terms per pickled ``(task, planner, compile options)``,
made once and kept for every goal."""


def build_problem(problem: SolverProblem) -> tuple[Callable, Callable, Callable]:
    """``(dynamics, stage_cost, terminal_cost)`` of ``problem`` for ``control.WorkerProcesses``: in a worker
    process, its own planner model and step (one worker: ``planner.workers`` is the parent's count of processes)
    and the costs of the goal."""
    planner = replace(problem.planner, workers=1, chunks=0, worker_processes=False)
    key = pickle.dumps((problem.task, planner, problem.compile_options))
    if key not in _WORKER_PLANNERS:
        model = planner_model(problem.task, planner)
        _WORKER_PLANNERS[key] = (model, *planner_calls(model, planner, problem.compile_options))
    model, dynamics, terms = _WORKER_PLANNERS[key]
    stage, terminal = problem.task.costs(model, problem.goal, anchor=problem.anchor,
                                         terms=EAGER_COST_TERMS if problem.eager_costs else terms)
    return dynamics, stage, terminal


def solver_processes(setup: Setup, goal: Tensor, anchor: tuple[Tensor, Tensor] | None,
                     eager_costs: bool = False) -> WorkerProcesses | None:
    """The setup's worker processes, set to plan for ``goal`` from ``anchor`` (``CemGd``'s ``processes``), or None
    when the planner runs its shares on threads."""
    if setup.processes is not None:
        setup.processes.set_problem(SolverProblem(setup.task, setup.planner, setup.compile_options, goal, anchor,
                                                  eager_costs))
    return setup.processes


def planner_calls(model: Model, planner: PlannerSettings, compile_options: dict | None = None
                  ) -> tuple[Callable[[State, Tensor], State], CostTerms]:
    """The planner's step on ``model`` and its cost terms: compiled together when ``planner.compile`` is set (a
    ``CompiledStep`` with ``dynamic=False`` and ``compiled_cost_terms``, both for the solver's ``workers`` and with
    ``compile_options``, as ``prepare`` says), else the eager ``step`` and ``EAGER_COST_TERMS``."""
    if not planner.compile:
        return functools.partial(step, model), EAGER_COST_TERMS
    options = compile_options or {}
    return (CompiledStep(model, workers=planner.workers, **{"dynamic": False, **options}),
            compiled_cost_terms(workers=planner.workers, device=model.device, **options))


def observed_state(setup: Setup, prediction: State | None = None) -> State:
    """The planner's state ``(B = 1)`` from what the plant's sensors see now and the planner's ``prediction`` of
    this instant (None before the first action): ``tactile.estimate_state``."""
    model = setup.planner_model
    seen = setup.plant.observe(model.points, setup.body_index, setup.sensors)
    seen = TactileObservation(*(t.to(model.dtype) for t in seen))
    return estimate_state(model, seen, setup.sensors, prediction)


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
    keep_plant: bool = False,
) -> EpisodeResult:
    """Run one episode of ``steps`` control steps (``task.episode_steps(goal)`` by default) towards ``goal (7,)``
    (float64), from the scene's initial state, or with ``keep_plant`` from where the last episode left the plant
    (goals back to back, as the stack runs them: the drift cost anchored there, a fresh solver).

    ``on_step(k, error_mm)`` is called after every control step (progress reports). Never raises for an
    unreachable goal, a contact-free start or a plan without a finite sample: the status says what happened. A
    goal beyond reach of the action bounds within its sized episode is reported ``unreachable`` without
    planning; an episode cut short by an explicit ``steps`` (a warm-up, a test) runs, and is reported
    ``unreachable`` when the goal was out of reach in that many steps.
    """
    task, planner, plant = setup.task, setup.planner, setup.plant
    sized = steps is None
    steps = task.episode_steps(goal) if sized else steps
    model = setup.planner_model
    if not keep_plant:
        plant.reset()
    start = plant.state.object_pose[0].clone()
    reachable = task.reachable(start, goal, steps)
    if sized and not reachable:
        add, pos, ang = _errors(setup, plant.state.object_pose, goal)
        return EpisodeResult(
            task=task.name, model=planner.model, loop=loop, status="unreachable", error_mm=add, position_mm=pos,
            angle_deg=ang, initial_error_mm=add, success=False, solves=0, solve_s=0.0, rollout_s=0.0,
            backward_s=0.0, cem_s=0.0, errors_mm=[add], actions=torch.zeros(0, model.n_bodies, 6, dtype=torch.float64),
            final_pose=plant.state.object_pose[0].clone(),
        )
    low, high = task.bounds(model.body_names, model.dtype)
    anchor = (start, plant.state.body_poses[0, setup.body_index].clone())
    stage, terminal = task.costs(model, goal, anchor=anchor, terms=setup.cost_terms)
    horizon, iterations = (steps, planner.open_loop_iterations) if loop == "open" else (
        planner.horizon, planner.cem_iterations)
    solver = CemGd(
        setup.dynamics, stage, terminal, low, high,
        config=planner.config(horizon, iterations), dtype=model.dtype,
        processes=solver_processes(setup, goal, anchor),
    )
    start_error = _errors(setup, plant.state.object_pose, goal)[0]
    errors, actions, timings = [start_error], [], []
    no_finite = diverged = False
    plan = prediction = None
    for k in range(steps):
        if loop == "closed" or plan is None:
            tic = time.perf_counter()
            state = observed_state(setup, prediction)
            result = solver.solve(state)
            timings.append({**result.timings, "solve_s": time.perf_counter() - tic})
            no_finite |= result.status != "ok"
            plan = result.plan
        u = plan[0] if loop == "closed" else plan[k]
        u = u.detach().clamp(low, high)
        if loop == "closed":
            prediction = carry_over(result.states, 1)
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
    if diverged:
        status = "diverged"
    elif no_finite:
        status = "no_finite_plan"
    elif not reachable:
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
