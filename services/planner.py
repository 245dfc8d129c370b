"""The planner service: the tactile state estimate and the MPC of ``hydrosoft.control`` on the stack's sensors.

Inputs (each refused when older than ``planner.max_age_s``): the object pose from the tag tracker, each arm's TCP
pose from its commander, and each bubble's membrane deformation image from its bubble camera. They become a
``hydrosoft.tactile.TactileObservation`` (the membrane deformation turned into per-point depths inside the nominal
membrane), which ``hydrosoft.tactile.estimate_state`` turns into the planner's state, carrying shear over from the
planner's own prediction of the last plan (the solver's rollout of it, ``PlanResult.states``). Each solve starts on
an object pose newer than the last solve's (``pose_wait_s``): the planner waits for the tag tracker's next pose
instead of solving again on one it solved on, at most ``POSE_WAIT_PERIODS`` camera periods after its last solve
ended (then it solves on the newest it has), and it waits for the next pose too when that is due within
``NEXT_DUE_PERIODS`` of a period, so a solve seldom starts on a pose that waited long. ``CemGd`` plans;
the plan's first actions, applied to the arms' current TCP poses, are the absolute TCP targets sent to the
commanders, each with a deadline: ``target_lead`` after it is sent, twice the p90 of the planner's recent cycles
plus a margin, within ``planner.target_lead_s`` .. ``limits.max_target_lead_s`` (so the next target comes before it
lapses; a lapsed one makes the commander hold the arm). When a goal ends, a halt names its outcome. Stale inputs mean no
solve and no target, also when an input went stale during the solve: the commander's watchdog then stops the arm.
Inputs stale for longer than ``limits.sensor_lost_s``, or from a publisher that restarted meanwhile (its
messages' ``seq`` began again), end the goal ``interrupted`` (``input_lost``): a sensor that comes back (a restarted
tag tracker or camera) does not resume it; a person starts a new goal.

The client API (``planner.cmd``): ``SetGoal``, ``Start``, ``Stop``, ``GetStatus``. A goal set for another stack
launch (``Goal.instance``, not this service's ``instance``) is refused. ``Start`` is refused without
fresh inputs to start from (the drift cost is anchored at the object and TCP poses the goal starts at). A goal ends
``reached`` (the tracked object's ADD error within the goal's tolerance for ``SETTLE_S``), ``timeout``, ``failed``
(with a reason: an unknown task, an unreachable goal, an object lost, no progress for ``planner.stall_s`` of planning:
``services/arm/progress.py``), ``stopped``, or ``interrupted`` when an arm's
commander acts on none of its targets any more (``ended_by_commander``: its goal floor passed the goal's start after
its restart, a reconnect, an ``arm enable``, a refused target or the loss of this planner's heartbeat).

In a one-arm scene the planner solves only while the bubble touches the object (``reapproach.in_contact``); an
object out of contact for ``reapproach.LOST_AFTER_S`` is lost, and the planner drives the arm back onto it
(``services/arm/reapproach.py``: up, across, down to the scene's pressing pose) before it plans again, at most
``planner.max_reapproaches`` times per goal.

Start-up: the planner builds its model, starts its worker processes and loads (or compiles) its solver, then, when
the launcher started it before the arm commanders (``$HYDROSOFT_AWAIT_ARMS``, ``await_arm_commanders``), waits until
each of them has published its arm state; only then does it serve the client API and report ready.

Priority (``planner.nice``): once ready, the planner's computing runs at that niceness, in its worker processes
(``renice``d then) or, without them, in a thread of its own (``compute_threads``: the penetration and the solve), so
that the commander and the sensors go first (each worker process leads a session of its own, and ``renice`` sets its
scheduling group's niceness too: where the kernel schedules each session as one group, Linux's autogroup, a niceness
counts only within its group, and before this the workers' +10 had counted only against the planner's own threads);
its event loop, which takes the inputs, estimates the state and sends the targets
(a few ms per cycle on the camera-to-target path), runs at the niceness it was started with, and so does the
computing thread when worker processes solve (``compute_niceness``: it then computes the penetration and hands the
shares out and in, all on that path). So does its start-up
(the model build, the worker processes' start, the solver's load and first solve), in a thread of its own: no arm
moves before the planner is ready, and at +10 its start-up waited behind every other program on a shared machine.

Device (``planner.device``): the model, the solver and its worker processes compute there; each solve's state moves
there once (``PlannerCore.observation``), and its plan, targets and Plan message come back to the CPU. A device that is
not available (``device_unavailable``) is no reason to plan on the CPU instead: the planner then reports it in its
status (``degraded``, ``device_unavailable``), refuses every goal, and sends no target.

Frames: the bus carries base-frame poses; the planner works in the task scene's frame (``scene.task_frame``,
``services/arm/task_frame.py``). Its inputs are converted on arrival (``fresh_inputs``), its targets, goal and
predictions back to the base frame on the way out.

The pure parts (``PlannerCore``, ``resolve_target``, ``targets_from_plan``) are plain functions and classes that
tests call without sockets; ``main`` is the thin loop.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import functools
import importlib
import math
import os
import time
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import msgspec
import numpy as np
import torch

from hydrosoft.compilation import building_precompiled
from hydrosoft.control import CemGd, PlanResult, WorkerProcesses
from hydrosoft.control import device_unavailable as control_device_unavailable
from hydrosoft.control.cem_gd import pieces
from hydrosoft.control.worker_processes import eager_parts, settle_after_compiling
from hydrosoft.drivers.bubble.deformation import penetration_from_deformation
from hydrosoft.drivers.bubble.render import PinholeDepth
from hydrosoft.dynamics import State, with_object_update
from hydrosoft.geometry import se3
from hydrosoft.geometry.sdf import Ellipsoid
from hydrosoft.scene import Scene, build_surface, compile_scene
from hydrosoft.tactile import TactileObservation, carry_over, estimate_state, sensor_bodies
from hydrosoft.tasks import Task, make_task
from hydrosoft.tasks.base import EAGER_COST_TERMS, CostTerms, mean_point_distance
from hydrosoft.tasks.evaluation import (METRIC_SPACING_M, PlannerSettings, planner_calls, with_body_materials,
                                        with_contact, with_solver_steps)
from hydrosoft.services.bus import artefacts
from hydrosoft.services.bus.artefacts import PROGRESS_PERIOD_S
from hydrosoft.services.bus import messages as msg
from hydrosoft.services.bus.sockets import Stale, quote
from hydrosoft.services.bus import service_cli
from hydrosoft.services.bus.config import StackConfig
from hydrosoft.services.arm.progress import ProgressWatch
from hydrosoft.services.arm.reapproach import LOST_AFTER_S, ContactWatch, Decision, grasp_offset
from hydrosoft.services.arm.safety import check_target, outside_workspace
from hydrosoft.services.bus.runtime import AWAIT_ARMS_ENV, Service
from hydrosoft.services.arm.task_frame import TaskFrame

IDLE_PERIOD_S = 0.05  # s between checks while no goal runs or inputs are stale
SETTLE_S = 0.3  # a goal is reached once the object stayed within its tolerance this long (s)
COMMAND_TIMEOUT_S = 1.0
ARM_WAIT_PERIOD_S = 0.05  # s between checks for the arm commanders' first states (``await_arm_commanders``)
#: The target lead (``target_lead``): a target outlives this many of the planner's slow (p90) cycles, plus a margin
#: (s) for the transport and the commander's tick, so one late cycle does not leave the arm without a target.
LEAD_CYCLES = 2.0
LEAD_MARGIN_S = 0.05
#: How many recent cycles the lead's p90 is taken over.
LEAD_WINDOW = 20
#: A solve waits for an object pose newer than the last solve's, at most this many tag camera periods
#: (``camera.fps``) after that solve ended (``pose_wait_s``): then it plans on the newest pose it has.
POSE_WAIT_PERIODS = 1.0
#: A solve also waits for the next pose when that is due (one period after the newest was published) within this
#: many periods, and for at most ``LATE_PERIODS`` past its due time: a queue of up to half a period becomes almost
#: none, for a wait of an eighth of a period per solve on average. A late pose is still the newer image (a period
#: younger than the newest pose's), so waiting for it beats solving on the newest: half a period covers
#: detection's tail (p99 44 against p50 20 ms at 20 images/s); at 0.2 periods a pose 10 ms late was given up and
#: the solve took an image 1.2 periods old (the queue's p99 of 61 ms).
NEXT_DUE_PERIODS = 0.5
LATE_PERIODS = 0.5
OBJECT_POSE_TOPIC = "object_pose/object"
#: The planner's computing threads (``compute_threads``): one, as a cycle's build, penetration and solve run in turn.
COMPUTE_THREADS = 1
#: The status note while the planner compiles its step (``planner.compile``) before it reports ready.
COMPILING_NOTE = ("compiling the planner step (planner.compile): ready in seconds once its artefact is built "
                  "(hydrosoft-stack compile), minutes without it: the planner then builds its precompiled functions "
                  "first")


def as_pose(values) -> torch.Tensor:
    """A float64 pose tensor ``(7,)`` from any 7 numbers."""
    return torch.as_tensor(np.asarray(values, dtype=np.float64)).clone()


def resolve_target(goal: msg.Goal, start_pose: torch.Tensor) -> torch.Tensor:
    """The object pose ``(7,)`` a goal asks for: its ``target_pose``, or the start pose moved by ``dx_m, dy_m`` (m,
    base frame) and turned by the rotation vector ``(droll_rad, dpitch_rad, dyaw_rad)`` (base axes) about the
    object's centre."""
    if goal.target_pose is not None:
        return as_pose(goal.target_pose)
    delta = torch.tensor([goal.dx_m, goal.dy_m, 0.0, goal.droll_rad, goal.dpitch_rad, goal.dyaw_rad],
                         dtype=torch.float64)
    return se3.retract(start_pose, delta)


def target_lead(floor_s: float, cycles_s: Sequence[float], ceiling_s: float) -> float:
    """How long (s) a target sent now stays valid: ``LEAD_CYCLES`` times the p90 of the recent planning cycles
    ``cycles_s`` (s, a cycle's start, its wait for a new pose included, to its targets sent) plus ``LEAD_MARGIN_S``,
    at least ``floor_s`` (``planner.target_lead_s``; alone while no cycle was measured) and at most ``ceiling_s``
    (the commander's ``limits.max_target_lead_s``, which it enforces anyway)."""
    lead = floor_s
    if len(cycles_s) > 0:
        lead = max(floor_s, LEAD_CYCLES * float(np.percentile(np.asarray(cycles_s, dtype=np.float64), 90))
                   + LEAD_MARGIN_S)
    return min(lead, ceiling_s)


def device_unavailable(device: str) -> str | None:
    """Why the torch device ``device`` (``planner.device``: ``cpu``, ``cuda`` or ``cuda:N``) cannot run the planner
    here (``control.device_unavailable``), naming the key, or None when it can."""
    problem = control_device_unavailable(device)
    if problem is None:
        return None
    return (f"planner.device = {device!r}, but {problem}: the planner plans nothing (set planner.device = \"cpu\" or "
            f"run the planner on a host with that GPU)")


def pose_wait_s(newest_pose_ns: int, solved_pose_ns: int, solved_at_ns: int, now_ns: int, period_s: float) -> float:
    """How long (s) the planner still waits before its next solve; 0: solve now.

    Stamps are ``time.monotonic_ns()``: ``newest_pose_ns`` the publish stamp of the newest object pose (0: none),
    ``solved_pose_ns`` that of the pose the last solve planned on (0: no solve yet), ``solved_at_ns`` when that solve
    ended, ``now_ns`` now. ``period_s``: the tag camera's period (s), the time between poses.

    A pose newer than the last solve's is solved on at once, unless the next one is due (one period after the newest
    was published) within ``NEXT_DUE_PERIODS`` periods: then the wait lasts until that is ``LATE_PERIODS`` late (a
    new pose ends it sooner). Without a newer pose, the solve waits for one at most ``POSE_WAIT_PERIODS`` periods
    after the last solve ended, then goes on with the same pose: a slow camera, or images that gave no pose, never
    stall planning for long."""
    if newest_pose_ns == 0:
        return 0.0  # no pose at all: the solve's input check says so
    if newest_pose_ns <= solved_pose_ns:
        return max(0.0, POSE_WAIT_PERIODS * period_s - (now_ns - solved_at_ns) * 1e-9)
    due_in_s = period_s - (now_ns - newest_pose_ns) * 1e-9
    if -LATE_PERIODS * period_s < due_in_s <= NEXT_DUE_PERIODS * period_s:
        return due_in_s + LATE_PERIODS * period_s
    return 0.0


def planner_scene(task: Task, config: StackConfig) -> Scene:
    """``task``'s scene as the planner of ``config`` models it: its contact model, surface spacing, bubble SDF solve
    and the arms' bubble materials (``[arms.material]``)."""
    planner = config.planner
    scene = with_body_materials(task.scene, config.bubble_materials())
    return with_solver_steps(with_contact(scene, planner.model, planner.spacing), planner.sdf_solver_steps)


@dataclass
class PlannerCore:
    """The planner's model, solver factory and geometry for one stack config.

    model: the compiled task scene at the planner's spacing, contact model and dtype. arms: for each config arm,
    its body index in the model. sensors: the model's sensor bodies (``tactile.sensor_bodies``). fixed_poses:
    ``(M, 7)`` the scene's body poses (unactuated bodies stay there). metric_points: ``(N, 3)`` object-frame
    points (5 mm spacing) on which the ADD error is measured. frame: the task frame in the base frame.
    grasp_offset: ``(3,)`` m, the one arm's TCP position relative to the object in the scene (``reapproach``), or
    ``None`` in a scene with several arms (no re-approach). cost_terms: what evaluates the costs of every goal
    (``Task.costs``), compiled with the step. Poses are in the task frame unless a name says base. The model, the
    sensors and the solvers are on ``planner.device``; the geometry (poses, points, offset) stays on the CPU.
    """

    config: StackConfig
    task: object
    settings: PlannerSettings
    model: object
    dynamics: object
    arms: dict[str, int]
    sensors: torch.Tensor
    fixed_poses: torch.Tensor
    metric_points: torch.Tensor
    membranes: dict[str, Ellipsoid] = field(default_factory=dict)
    frame: TaskFrame = field(default_factory=lambda: TaskFrame.from_pose(se3.identity()))
    grasp_offset: torch.Tensor | None = None
    cost_terms: CostTerms = EAGER_COST_TERMS
    processes: WorkerProcesses | None = None

    @classmethod
    def build(cls, config: StackConfig) -> PlannerCore:
        """Compile the planner's model for ``config`` on ``planner.device`` (raises ValueError naming an arm that is not
        a scene body, RuntimeError with ``device_unavailable``'s reason for a device this machine lacks)."""
        pc = config.planner
        unavailable = device_unavailable(pc.device)
        if unavailable is not None:
            raise RuntimeError(unavailable)
        task = make_task(config.scene.task)
        settings = PlannerSettings(model=pc.model, spacing=pc.spacing, samples=pc.samples, elites=pc.elites,
                                   horizon=pc.horizon, grad_steps=pc.grad_steps, dtype=getattr(torch, pc.dtype),
                                   seed=pc.seed, sdf_solver_steps=pc.sdf_solver_steps, compile=pc.compile,
                                   workers=pc.workers, chunks=pc.chunks, object_update=pc.object_update)
        model, state, _ = compile_scene(planner_scene(task, config), dtype=settings.dtype)
        model = with_object_update(model.to(device=torch.device(pc.device)), pc.object_update)
        arms = {}
        for arm in config.arms:
            if arm.name not in model.body_names:
                raise ValueError(f"arms: {arm.name!r} is not a body of the {task.name} scene "
                                 f"(bodies: {', '.join(model.body_names)})")
            arms[arm.name] = model.body_names.index(arm.name)
        dynamics, cost_terms = planner_calls(model, settings)
        metric = build_surface(msgspec.structs.replace(task.scene.object, spacing=METRIC_SPACING_M)).points
        membranes = {name: model.bodies[index] for name, index in arms.items()}
        offset = None
        if len(arms) == 1:
            (index,) = arms.values()
            offset = grasp_offset(state.object_pose[0].double(), state.body_poses[0, index].double())
        processes = None
        if pc.worker_processes:
            low, high = task.bounds(model.body_names, model.dtype)
            # by its module's name: run as a service this module is __main__, which a worker cannot import
            build = importlib.import_module("hydrosoft.services.planner").core_problem
            processes = WorkerProcesses(build, pc.workers, low, high, settings.config(settings.horizon, 1),
                                        settings.dtype, threads=pc.threads, device=model.device)
            # each worker builds its core now, at start, not at the first goal (on the service's event loop)
            arm_poses = {name: state.body_poses[0, index].double() for name, index in arms.items()}
            processes.set_problem(worker_problem(config, task.initial_pose(), state.object_pose[0].double(),
                                                 arm_poses))
        return cls(config, task, settings, model, dynamics, arms, sensor_bodies(model), state.body_poses[0].double(),
                   metric, membranes, TaskFrame.from_pose(config.scene.task_frame), offset, cost_terms, processes)

    def problem(self, goal_pose: torch.Tensor, object_pose: torch.Tensor, arm_poses: dict[str, torch.Tensor]
                ) -> tuple[Callable, Callable, Callable]:
        """``(dynamics, stage_cost, terminal_cost)`` towards ``goal_pose (7,)``, the drift cost anchored at the object
        pose ``(7,)`` and TCP poses ``(7,)`` the goal starts from (``Task.costs``), all moved to the model's device."""
        device = self.model.device
        stage, terminal = self.task.costs(self.model, goal_pose.to(device),
                                          anchor=(object_pose.to(device), self.body_poses(arm_poses).to(device)),
                                          terms=self.cost_terms)
        return self.dynamics, stage, terminal

    def solver(self, goal_pose: torch.Tensor, object_pose: torch.Tensor, arm_poses: dict[str, torch.Tensor]) -> CemGd:
        """A fresh CEM-GD solver for ``problem(goal_pose, object_pose, arm_poses)`` (its warm start then follows the
        episode), on the worker processes when the config asks for them (given the same problem first)."""
        low, high = self.task.bounds(self.model.body_names, self.model.dtype)
        if self.processes is not None:
            self.processes.set_problem(worker_problem(self.config, goal_pose, object_pose, arm_poses))
        return CemGd(*self.problem(goal_pose, object_pose, arm_poses), low, high,
                     config=self.settings.config(self.settings.horizon, 1), dtype=self.model.dtype,
                     device=self.model.device, processes=self.processes)

    def close(self) -> None:
        """Stop the worker processes, if any."""
        if self.processes is not None:
            self.processes.close()

    def error_mm(self, object_pose: torch.Tensor, goal_pose: torch.Tensor) -> float:
        """ADD error (mm) of ``object_pose (7,)`` against ``goal_pose (7,)``."""
        return 1e3 * float(mean_point_distance(self.metric_points, object_pose.double(), goal_pose.double()))

    def body_poses(self, arm_poses: dict[str, torch.Tensor]) -> torch.Tensor:
        """``(M, 7)`` float64: the arms' TCP poses on their bodies, the scene's poses elsewhere."""
        poses = self.fixed_poses.clone()
        for name, index in self.arms.items():
            poses[index] = arm_poses[name]
        return poses

    def observation(self, object_pose: torch.Tensor, arm_poses: dict[str, torch.Tensor],
                    penetration: torch.Tensor) -> TactileObservation:
        """The ``TactileObservation`` (B = 1, the model's dtype and device) of a tag pose, TCP poses and per-sensor
        penetration depths ``(S, N)`` (m, in ``sensors`` order): a solve's inputs, moved to the device once."""
        dtype, device = self.model.dtype, self.model.device
        return TactileObservation(*(t.to(device=device, dtype=dtype).unsqueeze(0)
                                    for t in (object_pose, self.body_poses(arm_poses), penetration)))

    def points_in_bubble(self, object_pose: torch.Tensor, arm_pose: torch.Tensor) -> np.ndarray:
        """The planner's surface points ``(N, 3)`` (m) in an arm's bubble frame, at the sensed poses."""
        world = se3.transform_points(object_pose, self.model.points.to(object_pose.device, torch.float64))
        return se3.transform_points(se3.inverse(arm_pose), world).numpy()


def ended_by_commander(started_ns: int, states: Iterable[msg.ArmState]) -> str | None:
    """Why a goal started at ``started_ns`` (this host's ``time.monotonic_ns()``) has ended, or None: an arm's
    commander acts only on goals started after its goal floor (``ArmState.goal_floor_ns``, on this host's clock),
    and that floor lies at or after the goal's start in one of ``states``."""
    for state in states:
        if state.goal_floor_ns >= started_ns:
            return (f"arm {state.arm}'s commander acts only on goals started after {state.goal_floor_cause}: "
                    "start a new goal")
    return None


def arm_end_positions(task, arm_poses: dict[str, torch.Tensor], start_pose: torch.Tensor,
                      target: torch.Tensor) -> dict[str, torch.Tensor]:
    """Where each arm's TCP ends ``(3,)`` (m, task frame) when the object goes from ``start_pose (7,)`` to ``target
    (7,)`` and each arm keeps its contact from ``arm_poses`` (``(7,)`` each): its position moved by the object's
    translation over the task's ``travel_ratio`` (twice as far for rolling, whose contact on top moves twice as fast
    as the centre). The goal's workspace check (``Planner.start``)."""
    travel = (target[:3] - start_pose[:3]) / task.travel_ratio
    return {name: pose[:3] + travel for name, pose in arm_poses.items()}


def targets_from_plan(core: PlannerCore, arm_poses: dict[str, torch.Tensor], plan: torch.Tensor,
                      steps: int) -> dict[str, torch.Tensor]:
    """Absolute TCP targets ``(7,)`` per arm, base frame: each arm's current pose (task frame) moved by the plan's
    first ``steps`` actions (``plan (K, M, 6)``, task-frame increments as ``dynamics.step`` applies them)."""
    targets = {}
    for name, index in core.arms.items():
        pose = arm_poses[name].clone()
        for k in range(min(steps, plan.shape[0])):
            pose = se3.retract(pose, plan[k, index].to(pose))  # from the solver's device and dtype
        targets[name] = core.frame.to_base(pose)
    return targets


@dataclass
class Episode:
    """One goal being pursued."""

    goal: msg.Goal
    target: torch.Tensor
    solver: CemGd
    started_s: float
    prediction: State | None = None
    within_since: float | None = None
    solve_s: list[float] = field(default_factory=list)
    error_mm: float = math.nan
    solved_pose_ns: int = 0  # publish stamp of the object pose the last solve planned on (0: none yet)
    solved_at_ns: int = 0  # when that solve ended, time.monotonic_ns()
    outcome: msg.Outcome = "running"
    reason: str = ""
    contact: ContactWatch | None = None
    progress: ProgressWatch | None = None
    stale_since_s: float | None = None  # when the inputs went stale (time.monotonic()), None while fresh
    input_seqs: dict[str, int] = field(default_factory=dict)  # per input topic, the seq of its newest message used

    def finish(self, outcome: msg.Outcome, reason: str = "") -> None:
        if self.outcome == "running":
            self.outcome, self.reason = outcome, reason

    def note_stale(self, now_s: float, why: str, lost_after_s: float) -> bool:
        """Note inputs stale at ``now_s`` (s, monotonic) for ``why``; once they have been stale for longer than
        ``lost_after_s`` the goal ends ``interrupted`` (returns True): the arm was stopped for it, and a sensor
        that comes back does not move it again on this goal."""
        if self.stale_since_s is None:
            self.stale_since_s = now_s
        if self.progress is not None:
            self.progress.pause()  # no plan on stale inputs: that time is no stall
        if now_s - self.stale_since_s <= lost_after_s:
            return False
        self.finish("interrupted", f"input lost: {why}, for over {lost_after_s:g} s (the arm was stopped); "
                                   "start a new goal")
        return True

    def note_fresh(self, seqs: dict[str, int]) -> bool:
        """Note fresh inputs whose newest messages have these ``seq`` per topic; when one is lower than the last
        one used, its publisher restarted (a new process numbers from 1): the goal ends ``interrupted`` (returns
        True), so a sensor that comes back does not move the arm again on this goal."""
        self.stale_since_s = None
        restarted = sorted(topic for topic, seq in seqs.items() if seq < self.input_seqs.get(topic, 0))
        self.input_seqs.update(seqs)
        if not restarted:
            return False
        self.finish("interrupted", f"input lost: the publisher of {', '.join(restarted)} restarted during the goal "
                                   "(its messages are numbered from 1 again); start a new goal")
        return True

    def note_progress(self, now_s: float) -> bool:
        """Note the goal's current ``error_mm`` at ``now_s`` (s, monotonic) in its ``progress`` watch; once the
        error has stalled (``ProgressWatch.update``) the goal ends ``failed`` with the watch's reason (returns True).
        While the bubble is off the object (``contact``: waiting, or re-approaching) the planner does not plan, and
        the watch's clock stops."""
        if self.progress is None:
            return False
        if self.contact is not None and self.contact.out_of_contact_since is not None:
            self.progress.pause()
            return False
        stalled = self.progress.update(now_s, self.error_mm)
        if stalled is None:
            return False
        self.finish("failed", stalled)
        return True


class Planner:
    """The service's state: the core, the goal, the current episode and the input subscribers."""

    def __init__(self, service: Service, config: StackConfig, core: PlannerCore,
                 compute: ThreadPoolExecutor | None = None) -> None:
        self.service, self.config, self.core = service, config, core
        self.compute = compute  # runs the penetration and the solve (``compute_threads``); None: the loop's default
        self.goal: msg.Goal | None = None
        self.plan_seq = 0
        self.episode: Episode | None = None
        self.last_outcome: Episode | None = None
        ages = config.planner.max_age_s
        self.max_age = {kind: ages.get(kind, 0.5) for kind in ("object_pose", "arm_state", "deformation")}
        self.inputs = service.subscriber(
            [config.endpoint("tag_tracker")] + [config.endpoint(f"arm_commander-{a.name}") for a in config.arms]
            + [config.endpoint(f"bubble_camera-{a.name}") for a in config.arms],
            topics=["object_pose/", "arm_state/", "deformation/"], background=True)
        self.out = service.publisher(config.endpoint("planner"))
        self.pose_stamps = (0, 0)  # (image, publish) stamps of the object pose fresh_inputs returned last, ns
        self.input_seqs: dict[str, int] = {}  # per topic, the seq of the message fresh_inputs returned last
        self.cycles_s: deque[float] = deque(maxlen=LEAD_WINDOW)  # recent cycles, start to targets sent (s)
        self.camera_period_s = 1.0 / config.camera.fps  # the time between object poses (pose_wait_s)
        self.sensor_lost_s = config.limits.sensor_lost_s  # inputs stale for longer: the goal ends

    # --- client API ---

    async def handle(self, request: msg.Request) -> msg.Reply:
        """The reply to one client request; a refused one is counted (``unknown_task``, ``other_instance``: a goal
        set for another stack launch, ``start_refused``)."""
        if isinstance(request, msg.SetGoal):
            if request.goal.task != self.config.scene.task:
                error = (f"unknown task {quote(request.goal.task)} for this stack: it serves "
                         f"{self.config.scene.task!r} (see the config's scene.task)")
                self.service.count_error("unknown_task", error)
                return msg.CommandReply(ok=False, error=error)
            if request.goal.instance not in ("", self.service.instance):
                error = (f"the goal was set for the stack launch {quote(request.goal.instance)}; this is launch "
                         f"{self.service.instance!r}: a goal never moves to another launch (set it again)")
                self.service.count_error("other_instance", error)
                return msg.CommandReply(ok=False, error=error)
            self.goal = request.goal
            return msg.CommandReply(ok=True)
        if isinstance(request, msg.Start):
            reply = self.start()
            if not reply.ok:
                self.service.count_error("start_refused", reply.error)
            return reply
        if isinstance(request, msg.Stop):
            if self.episode is not None:
                self.episode.finish("stopped", request.reason)
                self._end_episode()
            return msg.CommandReply(ok=True)
        if isinstance(request, msg.GetStatus):
            return self.status_reply()
        return msg.CommandReply(ok=False, error=f"unsupported request {type(request).__name__}")

    def start(self) -> msg.CommandReply:
        if self.goal is None:
            return msg.CommandReply(ok=False, error="no goal: send SetGoal first")
        try:
            start_pose, arm_poses, _ = self.fresh_inputs()
        except Stale as err:
            return msg.CommandReply(ok=False, error=f"{msg.NO_FRESH_INPUT} ({err})")
        frame = self.core.frame
        target = frame.to_task(resolve_target(self.goal, frame.to_base(start_pose)))
        episode = Episode(self.goal, target, self.core.solver(target, start_pose, arm_poses), time.monotonic(),
                          progress=ProgressWatch(self.config.planner.stall_s, self.goal.tolerance_mm))
        if self.core.grasp_offset is not None:
            episode.contact = ContactWatch(self.core.grasp_offset, self.config.planner.max_reapproaches)
        task = self.core.task
        if not task.reachable(start_pose, target, int(self.goal.timeout_s / self.core.model.dt)):
            episode.finish("failed", f"unreachable: the goal lies beyond what the action bounds allow within "
                                     f"{self.goal.timeout_s} s")
        else:
            for name, end in arm_end_positions(task, arm_poses, start_pose, target).items():
                refusal = outside_workspace(frame.points_to_base(end).numpy(), self.config.limits)
                if refusal is not None:
                    episode.finish("failed", f"unreachable: arm {name} would leave the workspace box to get there "
                                             f"({refusal})")
        episode.error_mm = self.core.error_mm(start_pose, target)
        episode.progress.update(episode.started_s, episode.error_mm)  # progress counts from the start's error
        if episode.outcome == "running":
            self.episode = episode
        else:
            self.service.count_error("unreachable_goal", episode.reason)
            self.last_outcome = episode
        return msg.CommandReply(ok=True)

    def status_reply(self) -> msg.StatusReply:
        episode = self.episode or self.last_outcome
        if episode is None:
            return msg.StatusReply(ok=True, goal=self.goal, status=self.service.status())
        goal = msgspec.structs.replace(episode.goal, target_pose=self.core.frame.to_base(episode.target).numpy(),
                                       dx_m=0.0, dy_m=0.0, dyaw_rad=0.0, droll_rad=0.0, dpitch_rad=0.0)
        solves = len(episode.solve_s)
        return msg.StatusReply(
            ok=True, running=episode.outcome == "running", goal=goal, status=self.service.status(),
            outcome=episode.outcome, outcome_reason=episode.reason,
            error_mm=episode.error_mm if math.isfinite(episode.error_mm) else 0.0,
            elapsed_s=time.monotonic() - episode.started_s, solves=solves,
            mean_solve_ms=1e3 * sum(episode.solve_s) / solves if solves else 0.0,
            reapproaches=episode.contact.count if episode.contact is not None else 0)

    def _end_episode(self) -> None:
        self.last_outcome, self.episode = self.episode, None
        task = asyncio.get_running_loop().create_task(self._halt_arms())
        self._halting = task  # held: the loop keeps only weak references to tasks

    async def _halt_arms(self) -> None:
        """Tell every commander to stop now: a target at the arm's current pose whose deadline has passed and which
        names the goal's outcome (``ArmTarget.goal_end``: the arm's stop cause reads "goal reached"); the last real
        target would otherwise stay valid, and the arm keep moving, until its own deadline."""
        poses = {}
        for arm in self.config.arms:
            try:
                poses[arm.name] = np.array(self.inputs.latest(f"arm_state/{arm.name}", 1.0).value.tcp_pose)
            except Stale:
                continue
        ended = self.last_outcome.outcome if self.last_outcome is not None else "stopped"
        await self.send_targets(poses, time.monotonic_ns(), goal_end=ended if ended != "running" else "stopped")

    # --- the loop ---

    def arm_states(self) -> list[msg.ArmState]:
        """The newest state of each arm, at any age (an arm without one is left out)."""
        states = []
        for arm in self.config.arms:
            try:
                states.append(self.inputs.latest(f"arm_state/{arm.name}", math.inf, msg.ArmState).value)
            except Stale:
                continue
        return states

    def has_arm_state(self, arm: str) -> bool:
        """Whether the commander of ``arm`` has published a state yet (at any age)."""
        try:
            self.inputs.latest(f"arm_state/{arm}", math.inf, msg.ArmState)
        except Stale:
            return False
        return True

    def fresh_inputs(self) -> tuple[torch.Tensor, dict[str, torch.Tensor], dict[str, msg.MembraneDeformation]]:
        """The newest object pose, TCP poses (task frame) and deformation images, each within its maximum age
        (else Stale). ``pose_stamps`` keeps the object pose's image and publish stamps (ns) for the Plan,
        ``input_seqs`` each input message's ``seq``."""
        to_task = self.core.frame.to_task
        tracked = self.inputs.latest(OBJECT_POSE_TOPIC, self.max_age["object_pose"]).value
        seqs = {OBJECT_POSE_TOPIC: tracked.seq}
        object_pose = to_task(as_pose(tracked.pose))
        arms, deformations = {}, {}
        for arm in self.config.arms:
            state = self.inputs.latest(f"arm_state/{arm.name}", self.max_age["arm_state"]).value
            arms[arm.name] = to_task(as_pose(state.tcp_pose))
            deformations[arm.name] = self.inputs.latest(f"deformation/{arm.name}", self.max_age["deformation"]).value
            seqs[f"arm_state/{arm.name}"], seqs[f"deformation/{arm.name}"] = state.seq, deformations[arm.name].seq
        self.pose_stamps, self.input_seqs = (tracked.hw_stamp_ns or 0, tracked.stamp_ns), seqs
        return object_pose, arms, deformations

    def penetration(self, object_pose: torch.Tensor, arm_poses: dict[str, torch.Tensor],
                    deformations: dict[str, msg.MembraneDeformation]) -> torch.Tensor:
        """Per sensor body, the depth ``(S, N)`` (m) of each planner point inside the nominal membrane, from the
        deformation images (``drivers.bubble.deformation``)."""
        rows = []
        for index in self.core.sensors.tolist():
            name = self.core.model.body_names[index]
            depth = self.config.arm(name).depth
            camera = PinholeDepth(depth.width, depth.height, depth.fx, depth.fy, depth.cx, depth.cy)
            rows.append(torch.as_tensor(penetration_from_deformation(
                deformations[name].deformation, camera, self.core.membranes[name].radii, depth.camera_in_bubble(),
                self.core.points_in_bubble(object_pose, arm_poses[name]))))
        return torch.stack(rows)

    async def tick(self) -> None:
        """One planning cycle of the running episode (or nothing when none runs)."""
        episode = self.episode
        if episode is None:
            await asyncio.sleep(IDLE_PERIOD_S)
            return
        if time.monotonic() - episode.started_s > episode.goal.timeout_s:
            episode.finish("timeout", f"not reached within {episode.goal.timeout_s} s")
            self._end_episode()
            return
        ended = ended_by_commander(int(episode.started_s * 1e9), self.arm_states())
        if ended is not None:
            episode.finish("interrupted", ended)
            self.service.count_error("goal_ended", ended)
            self._end_episode()
            return
        cycle_start_ns = time.monotonic_ns()
        await self.wait_for_new_pose(episode)
        if self.episode is not episode:
            return  # stopped meanwhile
        try:
            object_pose, arm_poses, deformations = self.fresh_inputs()
        except Stale as err:
            self.service.count_error("stale_input", str(err))
            if episode.note_stale(time.monotonic(), str(err), self.sensor_lost_s):
                self.service.count_error("input_lost", episode.reason)
                self._end_episode()
                return
            await asyncio.sleep(IDLE_PERIOD_S)
            return
        if episode.note_fresh(self.input_seqs):
            self.service.count_error("input_lost", episode.reason)
            self._end_episode()
            return
        stamps = {"image_stamp_ns": self.pose_stamps[0], "pose_stamp_ns": self.pose_stamps[1],
                  "inputs_ns": time.monotonic_ns()}
        episode.error_mm = self.core.error_mm(object_pose, episode.target)
        now = time.monotonic()
        if episode.error_mm > episode.goal.tolerance_mm:
            episode.within_since = None
        elif episode.within_since is None:
            episode.within_since = now
        elif now - episode.within_since >= SETTLE_S:
            episode.finish("reached")
            self._end_episode()
            return
        if episode.note_progress(now):
            self.service.count_error("goal_stalled", episode.reason)
            self.service.log.warning("goal failed: %s", episode.reason)
            self._end_episode()
            return
        loop = asyncio.get_running_loop()
        try:
            penetration = await loop.run_in_executor(self.compute, self.penetration, object_pose, arm_poses,
                                                     deformations)
        except ValueError as err:  # a deformation image that does not fit its camera: no solve on it
            self.service.count_error("bad_input", str(err))
            await asyncio.sleep(IDLE_PERIOD_S)
            return
        if self.episode is not episode:
            return  # stopped meanwhile
        decision = "plan" if episode.contact is None else episode.contact.decide(penetration, now)
        if decision != "plan":
            await self.out_of_contact(episode, decision, object_pose, arm_poses)
            if self.episode is episode:
                await asyncio.sleep(IDLE_PERIOD_S)
            return
        observation = self.core.observation(object_pose, arm_poses, penetration)
        state = estimate_state(self.core.model, observation, self.core.sensors, episode.prediction)
        tic = time.perf_counter()
        stamps["solve_start_ns"] = time.monotonic_ns()
        result = await loop.run_in_executor(self.compute, episode.solver.solve, state)
        solve_s = time.perf_counter() - tic
        episode.solved_pose_ns, episode.solved_at_ns = stamps["pose_stamp_ns"], time.monotonic_ns()
        if self.episode is not episode or episode.outcome != "running":
            return  # stopped while solving: send nothing
        episode.solve_s.append(solve_s)
        if result.status != "ok":
            self.service.count_error("no_finite_plan", "no sample had a finite cost; no target sent")
            return
        try:
            self.fresh_inputs()  # a sensor that died during the solve: its plan is not acted on
        except Stale as err:
            self.service.count_error("stale_input", f"after the solve: {err}; no target sent")
            return
        steps = max(1, round(solve_s / self.core.model.dt))
        targets = targets_from_plan(self.core, arm_poses, result.plan.detach(), steps)
        await self.send_targets({name: pose.numpy() for name, pose in targets.items()}, self.target_deadline_ns())
        stamps["targets_ns"] = time.monotonic_ns()
        self.cycles_s.append((stamps["targets_ns"] - cycle_start_ns) * 1e-9)
        await self.out.send(self.plan_message(result, stamps), topic=f"plan/{self.config.scene.task}")
        episode.prediction = carry_over(result.states, steps)

    async def wait_for_new_pose(self, episode: Episode) -> None:
        """Wait until ``pose_wait_s`` says solve (re-asked whenever an object pose arrives)."""
        arrival = self.inputs.arrival(OBJECT_POSE_TOPIC)
        while (wait_s := pose_wait_s(self.newest_pose_ns(), episode.solved_pose_ns, episode.solved_at_ns,
                                     time.monotonic_ns(), self.camera_period_s)) > 0:
            arrival.clear()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(arrival.wait(), wait_s)

    def newest_pose_ns(self) -> int:
        """The publish stamp (ns) of the newest object pose, at any age (0: none yet)."""
        try:
            return self.inputs.latest(OBJECT_POSE_TOPIC, math.inf).stamp_ns
        except Stale:
            return 0

    async def out_of_contact(self, episode: Episode, decision: Decision, object_pose: torch.Tensor,
                             arm_poses: dict[str, torch.Tensor]) -> None:
        """One tick of a goal whose bubble is off the object (``ContactWatch.decide``'s ``decision``): nothing while
        it waits, the goal failed once the object is lost past its re-approaches, otherwise the re-approach's next
        waypoint to the arm; once the bubble presses on the object again, a fresh solver anchored at the new
        contact. A waypoint the commander would refuse (outside the workspace box) fails the goal and sends
        nothing."""
        watch = episode.contact
        if decision == "lost":
            self._fail(episode, f"lost the object: no contact for {LOST_AFTER_S} s after {watch.count} re-approaches "
                                f"(planner.max_reapproaches = {watch.allowed})")
            return
        if decision == "wait":
            return
        if decision == "start":
            self.service.log.info("lost contact with the object for %.1f s: re-approach %d of %d", LOST_AFTER_S,
                                  watch.count, watch.allowed)
        (name,) = self.core.arms
        target = watch.target(object_pose, arm_poses[name])
        if target is None:
            self.service.log.info("re-approach %d done: planning from the new contact", watch.count)
            episode.prediction = None
            episode.progress.restart()
            episode.solver = self.core.solver(episode.target, object_pose, arm_poses)
            return
        base = self.core.frame.to_base(target).numpy()
        refusal = check_target(base, self.config.limits)
        if refusal is not None:
            self._fail(episode, f"lost the object out of reach: re-approach {watch.reapproach.phase_name}: {refusal}")
            return
        await self.send_targets({name: base}, self.target_deadline_ns())

    def target_deadline_ns(self) -> int:
        """The deadline (``time.monotonic_ns()``) of a target sent now: ``target_lead`` from now, from the recent
        cycles (shown in the service's status note)."""
        lead_s = target_lead(self.config.planner.target_lead_s, self.cycles_s, self.config.limits.max_target_lead_s)
        if self.cycles_s:
            self.service.note = (f"target lead {lead_s:.2f} s (p90 of the last {len(self.cycles_s)} cycles: "
                                 f"{1e3 * float(np.percentile(self.cycles_s, 90)):.0f} ms)")
        return time.monotonic_ns() + int(lead_s * 1e9)

    async def send_targets(self, poses: dict[str, np.ndarray], deadline_ns: int, goal_end: msg.GoalEnd = "") -> None:
        """Send each arm's TCP target ``(7,)`` (m, wxyz, base frame), all with one new ``plan_seq`` and
        ``deadline_ns`` (the plan they come from: a solve, a re-approach waypoint, or the halt at a goal's end, which
        names the goal's outcome in ``goal_end``), stamped with the goal's start and with now as the plan's
        completion (it is sent as soon as it is made)."""
        self.plan_seq += 1
        episode, plan_done_ns = self.episode or self.last_outcome, time.monotonic_ns()
        goal_started_ns = 0 if episode is None else int(episode.started_s * 1e9)  # time.monotonic() in ns
        for name, pose in poses.items():
            await self.out.send(msg.ArmTarget(arm=name, tcp_pose=pose, deadline_ns=deadline_ns, plan_seq=self.plan_seq,
                                              goal_started_ns=goal_started_ns, plan_done_ns=plan_done_ns,
                                              goal_end=goal_end),
                                topic=f"arm_target/{name}")

    def _fail(self, episode: Episode, reason: str) -> None:
        episode.finish("failed", reason)
        self.service.count_error("object_lost", reason)
        self._end_episode()

    def plan_message(self, result: PlanResult, stamps: dict[str, int]) -> msg.Plan:
        """The Plan message of a solve, base frame: actions, predicted object poses (``result.states``, the solver's
        rollout of its plan) and the first step's contact forces, with the ``stamps`` (ns) of its way from the camera
        to the targets (``msg.Plan``); the solver's tensors come to the CPU here."""
        dtype = np.float32 if self.core.model.dtype == torch.float32 else np.float64
        frame = self.core.frame
        poses = frame.to_base(torch.stack([s.object_pose[0] for s in result.states]).detach().cpu())
        forces = result.states[0].forces[0].detach().cpu()
        poses[:, 3:] = torch.nn.functional.normalize(poses[:, 3:], dim=-1)
        actions = frame.vectors_to_base(result.plan.detach().cpu().unflatten(-1, (2, 3))).flatten(-2)
        return msg.Plan(task=self.config.scene.task, actions=actions.numpy().astype(dtype),
                        predicted_object_poses=poses.numpy().astype(dtype),
                        predicted_forces=frame.vectors_to_base(forces).numpy().astype(dtype),
                        cost=float(result.cost) if math.isfinite(result.cost) else 0.0,
                        solve_ms=1e3 * sum(result.timings.values()), **stamps)


_WORKER_CORES: dict[bytes, PlannerCore] = {}
"""In a solver worker process: the planner core per config (JSON), built once and kept for every goal."""


def worker_problem(config: StackConfig, goal_pose: torch.Tensor, object_pose: torch.Tensor,
                   arm_poses: dict[str, torch.Tensor]) -> tuple:
    """What a solver worker process builds a goal's problem from (``core_problem``): ``config`` as one worker without
    processes of its own, and the goal and anchor ``PlannerCore.problem`` takes."""
    alone = msgspec.structs.replace(config.planner, workers=1, chunks=0, worker_processes=False)
    return msgspec.structs.replace(config, planner=alone), goal_pose, object_pose, arm_poses


def core_problem(problem: tuple) -> tuple[Callable, Callable, Callable]:
    """``(dynamics, stage_cost, terminal_cost)`` in a solver worker process (``control.WorkerProcesses``) for
    ``problem = (config, goal_pose, object_pose, arm_poses)``: ``PlannerCore.problem`` on the config's core (one
    worker, no processes of its own)."""
    config, goal_pose, object_pose, arm_poses = problem
    key = msgspec.json.encode(config)
    if key not in _WORKER_CORES:
        _WORKER_CORES[key] = PlannerCore.build(config)
    return _WORKER_CORES[key].problem(goal_pose, object_pose, arm_poses)


WARM_UP_SOLVES = 2
"""Solves of the planner's start-up (``compile_step``): the first compiles the step's graphs, the second (warm-started,
as a goal's) those of the step from its own outputs."""


def compile_step(core: PlannerCore) -> float:
    """Compile the planner's step for every input signature a solve uses, by ``WARM_UP_SOLVES`` solves of one solver
    from the scene's initial state (the later ones warm-started, as a goal's; their results are dropped), then settle
    the garbage collector (``garbage_collection.settle_garbage_collector``: the compiler's objects out of its way) in
    each solver worker process (``WorkerProcesses.settle``) and in this one; the seconds it took. With torch's compile
    cache warm this loads the compiled code instead (seconds, not minutes).

    Why the workers settle here: a worker's first settle walks the compiler's half a million objects (about 0.2 s on
    2 cores); later ones walk only what came after. When each worker settled by itself after a count of its own
    solves, with one solve here that first settle fell on the first goal's second solve: 211 against 31-41 ms for
    every other solve (idle, the paper planner); with the samples cut into chunks a worker's count no longer followed
    the solves."""
    started = time.monotonic()
    _, initial, _ = compile_scene(planner_scene(core.task, core.config), dtype=core.model.dtype)
    arm_poses = {name: initial.body_poses[0, index].double() for name, index in core.arms.items()}
    solver = core.solver(core.task.initial_pose(), initial.object_pose[0].double(), arm_poses)
    for _ in range(WARM_UP_SOLVES):
        solver.solve(initial)
    settle_after_compiling(core.processes)
    return time.monotonic() - started


def share_sizes(samples: int, workers: int, chunks: int = 0) -> list[int]:
    """The batch sizes of the solver's shares, each once: ``samples`` cut into ``cem_gd.pieces(workers, chunks)``
    as ``CemGd`` cuts them (``Tensor.tensor_split``: the first ``samples % cut`` shares one larger)."""
    cut = pieces(workers, chunks)
    return sorted({samples // cut + (index < samples % cut) for index in range(cut)} - {0})


def build_precompiled(config: StackConfig, directory: Path) -> None:
    """Build the planner's precompiled functions (step and costs, ``compilation.Precompiled``) into ``directory``, in
    this process alone, for every input signature a solver worker's solve uses: per share size (``share_sizes``: the
    chunks' sizes when the samples are cut into chunks),
    one solve of a one-worker core whose batch is that share, as a worker process (or thread) runs its share.
    Functions already there are loaded, not built again. A function that fails to build is left without a file:
    the processes that load the others compile it the usual way, and say so if that fails too (``compile_planner``).
    (Each worker process building its own copy took about 10 minutes per file under load, all of them building the
    same files.)"""
    for size in share_sizes(config.planner.samples, config.planner.workers, config.planner.chunks):
        alone = msgspec.structs.replace(config.planner, workers=1, chunks=0, worker_processes=False, samples=size,
                                        elites=min(config.planner.elites, size))
        with building_precompiled(directory):  # only this core's functions build
            core = PlannerCore.build(msgspec.structs.replace(config, planner=alone))
        compile_step(core)


def build_precompiled_rollouts(config: StackConfig, directory: Path) -> None:
    """Build the planner's precompiled functions without gradients alone (``build_precompiled`` of a solve without
    gradient steps: its final rollout), so that a process beside the one that builds them all (``hydrosoft-stack
    compile``) can build them at the same time; that one then loads those it finds ready."""
    build_precompiled(msgspec.structs.replace(config, planner=msgspec.structs.replace(config.planner, grad_steps=0)),
                      directory)


def compile_planner(core: PlannerCore, precompile: Path | None = None) -> str | None:
    """Compile the planner's step and costs (``compile_step``), after building their precompiled functions into
    ``precompile`` (``build_precompiled``) when given, so that this process and its solver worker processes load
    them; None when all of them run compiled, in this process and in each solver worker process, else each that
    fell back to eager with its reason."""
    if precompile is not None:
        build_precompiled(core.config, precompile)
    compile_step(core)
    own = eager_parts((core.dynamics, core.cost_terms.stage, core.cost_terms.terminal))
    failed = [own] if own else []
    if core.processes is not None:
        failed += [worker_fallback(index, why) for index, why in sorted(core.processes.fallbacks.items())]
    return "; ".join(failed) if failed else None


async def serve_without_device(service: Service, config: StackConfig, reason: str) -> None:
    """A planner whose ``planner.device`` is not available (``reason``): it reports ``degraded`` with the reason in its
    status (note, ``device_unavailable`` error), answers ``GetStatus``, refuses every other request with the reason,
    and never plans nor sends a target, until it is stopped."""
    service.log.error("%s", reason)
    service.count_error("device_unavailable", reason)
    service.note = reason
    service.degrade("device_unavailable")

    async def refuse(request: msg.Request) -> msg.Reply:
        if isinstance(request, msg.GetStatus):
            return msg.StatusReply(ok=True, status=service.status())
        service.count_error("device_unavailable", reason)
        return msg.CommandReply(ok=False, error=reason)

    server = service.request_server(config.endpoint("planner", "cmd"), refuse)
    serving = service.supervise(asyncio.create_task(server.serve(), name="planner.serve"))
    await service.ready()
    try:
        await asyncio.Event().wait()  # until the service is stopped
    finally:
        serving.cancel()


def compute_niceness(config: StackConfig, worker_processes: bool) -> int:
    """The niceness the planner's computing threads add (``compute_threads``): ``planner.nice`` where they solve
    (worker threads, or the solver in the thread itself), 0 where the solver's worker processes do (those are
    ``renice``d to ``planner.nice``). The thread then computes the penetration (a few ms) and hands the shares to the
    processes and takes their results, all on the camera-to-target path: at +10 each of those steps waited behind
    every other service's burst (docs/decisions.md, 2026-11-29)."""
    return 0 if worker_processes else config.planner.nice


def compute_threads(nice: int) -> ThreadPoolExecutor:
    """``COMPUTE_THREADS`` threads that each add ``nice`` to their niceness as they start (on Linux a thread's own;
    ``os.nice``): what runs on them, and the threads and processes they start, runs at that niceness, the calling
    thread at its own."""
    return ThreadPoolExecutor(COMPUTE_THREADS, thread_name_prefix="planner-compute", initializer=os.nice,
                              initargs=(nice,))


def renice(pids: Iterable[int], increment: int) -> list[str]:
    """Add ``increment`` to the niceness of every thread of the processes ``pids`` (on Linux each thread has its
    own, listed in ``/proc/PID/task``; elsewhere the process's). A process that leads a session of its own (the
    solver's worker processes do) also gets its scheduling group set to its new niceness (``/proc/PID/autogroup``,
    where the kernel groups each session: without it the niceness counts only within the group). A process that is
    gone is left out. Returns what could not be set, in words ([] when all was)."""
    problems = []
    for pid in pids:
        try:
            threads = [int(tid) for tid in os.listdir(f"/proc/{pid}/task")]
        except FileNotFoundError:
            threads = [pid]
        try:
            for tid in threads:
                with contextlib.suppress(ProcessLookupError):
                    os.setpriority(os.PRIO_PROCESS, tid, os.getpriority(os.PRIO_PROCESS, tid) + increment)
            if os.getsid(pid) == pid:
                with contextlib.suppress(FileNotFoundError), open(f"/proc/{pid}/autogroup", "w") as group:
                    group.write(str(os.getpriority(os.PRIO_PROCESS, pid)))
        except ProcessLookupError:
            continue
        except OSError as error:
            problems.append(f"process {pid}: {error}")
    return problems


def worker_fallback(index: int, why: str) -> str:
    """A solver worker process's parts that run eager (``WorkerProcesses.fallbacks``), in words."""
    return f"solver worker process {index}: {why}"


def watch_worker_fallbacks(service: Service, core: PlannerCore) -> None:
    """Once the planner runs, a solver worker process whose parts fall back to eager (a new input signature that
    fails to compile) shows in the service's status (``eager: ...``) and its log, as the planner's own would."""
    def fell_back(index: int, why: str) -> None:
        service.compilation = f"eager: {worker_fallback(index, why)}"
        service.log.warning("the planner runs eager in part: %s", worker_fallback(index, why))

    if core.processes is not None:
        core.processes.on_fallback = fell_back


async def run(service: Service, config: StackConfig) -> None:
    """The planner's loop: build (and compile) the model, serve the client API, plan while a goal runs, its computing
    at a lower priority (``planner.nice``, ``compute_threads``); without its device, ``serve_without_device``."""
    unavailable = device_unavailable(config.planner.device)
    if unavailable is not None:
        await serve_without_device(service, config, unavailable)
        return
    loop = asyncio.get_running_loop()
    start_up = ThreadPoolExecutor(1, thread_name_prefix="planner-start")  # at the service's niceness (``renice``)
    if config.planner.nice:
        service.log.info("computing at niceness +%d (planner.nice) once ready: the other services go first",
                         config.planner.nice)
    torch.set_num_threads(config.planner.threads)
    if config.planner.compile:  # before the model and the worker processes: they load its precompiled functions
        precompiled = artefacts.use_precompiled(config, artefacts.planner_key(config))
    core = await loop.run_in_executor(start_up, PlannerCore.build, config)
    compute = compute_threads(compute_niceness(config, core.processes is not None))
    planner = Planner(service, config, core, compute)  # its inputs arrive from now on, while its solver loads
    if config.planner.compile:
        build = artefacts.PartBuild(artefacts.planner_key(config), artefacts.cache_dir(config))
        service.compilation = build.status
        service.note = COMPILING_NOTE
        compile = functools.partial(compile_planner, core, None if build.ready else precompiled)
        elsewhere = None if core.processes is None else core.processes.precompiled
        if not await loop.run_in_executor(start_up, build.run, compile, service.log.info, PROGRESS_PERIOD_S,
                                          elsewhere):
            service.log.warning("the planner runs eager: %s", build.fallback)
        service.note = ""
        service.compilation = build.status
        watch_worker_fallbacks(service, core)
    else:
        service.compilation = "eager (planner.compile = false)"
    start_up.shutdown()
    if core.processes is not None:
        for problem in renice(core.processes.pids, config.planner.nice):
            service.log.warning("the solver's worker processes may not run at niceness +%d: %s",
                                config.planner.nice, problem)
    await await_arm_commanders(service, planner, arms_to_await())
    server = service.request_server(config.endpoint("planner", "cmd"), planner.handle)
    serving = service.supervise(asyncio.create_task(server.serve(), name="planner.serve"))
    await service.ready()
    try:
        while True:
            await planner.tick()
    finally:
        serving.cancel()
        core.close()
        compute.shutdown(wait=False)


def arms_to_await() -> list[str]:
    """The arms whose commanders the launcher starts after the planner (``$HYDROSOFT_AWAIT_ARMS``, comma separated;
    none when it is unset: a planner started alone, or restarted, waits for no arm)."""
    return [name for name in os.environ.get(AWAIT_ARMS_ENV, "").split(",") if name]


async def await_arm_commanders(service: Service, planner: Planner, arms: Sequence[str]) -> None:
    """Return once the commander of each of ``arms`` has published its arm state (a commander publishes it only once
    it is ready, connected to its arm), checking every ``ARM_WAIT_PERIOD_S``; until then the planner serves no
    client request and is not ready, and its status note names the arms it waits for. The launcher starts the
    planner first, so that it builds and loads its solver while the arms' owners start; this keeps the rule that
    nothing takes a goal for an arm before the arm's commander runs."""
    waiting = [arm for arm in arms if not planner.has_arm_state(arm)]
    if waiting:
        service.note = f"waiting for the state of the arm commanders of {', '.join(waiting)} before taking goals"
        service.log.info("%s", service.note)
    while waiting:
        await asyncio.sleep(ARM_WAIT_PERIOD_S)
        waiting = [arm for arm in waiting if not planner.has_arm_state(arm)]
    service.note = ""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments: CONFIG [--name planner] (``service_cli``)."""
    service_cli.add_arguments(parser, "planner")


def main(argv: list[str] | None = None) -> int:
    return service_cli.main("planner", __doc__, argv, add_arguments, lambda args: service_cli.run(args, run))


if __name__ == "__main__":
    service_cli.exit_process(main())
