"""sim_world (sim-hardware mode only): the simulated plant, and the simulated devices that stand in for the lab's.

- The plant (``SimPlant``): the task scene (``hydrosoft.tasks.make_task(scene.task)``) compiled with the NH contact
  model at surface spacing ``planner.spacing * sim.spacing_factor``, advanced in real time at ``sim.rate_hz``.
  Each tick reads every arm's simulated TCP pose, moves the arm's body there over one ``hydrosoft.dynamics.step``
  (the control ``u (1, M, 6)``: translation and rotation-vector increments from the previous pose, world frame)
  and then sets the body poses exactly to the TCP poses. One tick is ``h = 1 / sim.rate_hz`` s; the scene's
  damping time is scaled to keep its mobility ``h / epsilon`` (so the object moves as fast per second as in the
  task's model), and the sub-steps are at most as long as those of ``hydrosoft.tasks.evaluation.PlantSettings``'
  plant (half the planner's). With ``sim.compile`` the step runs compiled (``CompiledStep``, compiled before
  READY), and a late tick takes the steps it is due, so simulated time keeps up with the simulated arm on two
  cores beside the planner. A tick that fails (a bad TCP pose, ``UnstableStepError``, a torch error, non-finite
  values) is logged and counted under its kind (``PlantStepError``), and the state kept. The plant lies at
  ``scene.task_frame`` in the base frame (``services/arm/task_frame.py``): TCP poses arrive and every pose, point and
  force leaves in the base frame, as in the lab.
- Per arm, a simulated UR controller (``drivers/ur/simulator.py``) on ``arm.ur_host``, started at the scene's pose
  of the arm's body (the TCP frame is the bubble's frame), which the real ``ur_rtde`` client in the arm commander
  talks to; no ``ur_rtde`` client ever runs in this process (the simulator and a client in one process block each
  other). And a simulated FT 300 (``drivers/robotiq_ft300/simulator.py``) on a pseudo-terminal linked at
  ``arm.ft_port``, streaming the wrench the object applies to the bubble (``hydrosoft.dynamics.body_wrenches``,
  about the TCP, in the TCP frame: pressing down on the object reads as +Fz for a TCP whose z points up) plus the
  sensor's zero-load offset ``sim.ft_bias``, which the real serial driver in the F/T reader reads. sim_world stores
  that offset as the arm's tare (``services/arm/ft_bias.py``, in ``state_dir``) before the sensor starts: the tare a
  person would take before the membrane touches the object, since the scenes start in contact.
- Rendered sensors (``sim.render``), each in a worker thread so the physics keeps its rate, on one OpenCV thread
  (``OPENCV_THREADS``): the tag camera's image on ``image/tag_camera`` (``CameraImage``) at ``camera.fps``, and each
  bubble's depth image on ``depth/ARM`` (``DepthFrame``) at ``arm.depth.fps`` or as fast as it renders.
- The truth leaves only on ``eval/object_pose`` and ``eval/contact_forces`` (10 Hz), which no control service
  reads.

The achieved physics rate, step times and render times are logged every ``RATE_LOG_PERIOD_S``. The plant and the
statistics are plain classes tested without sockets; ``serve`` is the loop.
"""

from __future__ import annotations

import argparse
import asyncio
import functools
import math
import time
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import msgspec
import numpy as np
import torch
from torch import Tensor

from hydrosoft.drivers.camera.sim import SimCamera
from hydrosoft.drivers.errors import DriverError
from hydrosoft.drivers.poses import check_pose
from hydrosoft.drivers.robotiq_ft300.simulator import SimulatedFT300
from hydrosoft.drivers.ur.config import URSimulatorConfig
from hydrosoft.drivers.ur.simulator import SimulatedURController
from hydrosoft.dynamics import CompiledStep, Model, State, UnstableStepError, body_wrenches, step, stepped_form
from hydrosoft.geometry import se3
from hydrosoft.scene import Scene, compile_scene
from hydrosoft.services.bus import artefacts
from hydrosoft.services.bus import messages as msg
from hydrosoft.services.bus.sockets import Publisher
from hydrosoft.services.bus import service_cli
from hydrosoft.services.bus.config import ConfigError, StackConfig
from hydrosoft.services.arm.ft_bias import StoredBias, bias_path, save_bias
from hydrosoft.services.bus.runtime import Service
from hydrosoft.services.sim.devices import image_topic
from hydrosoft.services.sim.render import BubbleDepthCamera, tag_camera
from hydrosoft.services.arm.task_frame import TaskFrame
from hydrosoft.services.tag_tracker import OBJECT, TAG_CAMERA
from hydrosoft.tasks import make_task
from hydrosoft.tasks.evaluation import PlantSettings, with_body_materials, with_contact, with_solver_steps

SERVICE = "sim_world"
PLANT = PlantSettings()  # the evaluation plant's contact model and sub-step factor, which sim_world shares
EVAL_PERIOD_S = 0.1  # ground truth on eval/ at 10 Hz
RATE_LOG_PERIOD_S = 10.0  # how often the achieved rates and step and render times are logged
MAX_LAG_TICKS = 5  # most plant steps one late tick catches up; further behind, the schedule restarts from now
TORCH_THREADS = 1  # per torch op: physics and depth rendering run side by side on a small machine
#: OpenCV threads of the renderers. OpenCV's default (one per core) cost 5.5-6.8 ms of CPU per 640 x 480 tag image
#: against 3.4-3.9 ms with one thread, for no shorter render (3.5-4.6 against 3.4-3.9 ms, 2 cores); the same images.
OPENCV_THREADS = 1


class PlantStepError(Exception):
    """A plant tick that was not carried out (the state is unchanged). ``kind``: the short name errors are counted
    under: ``bad_tcp_pose``, ``unstable_step``, ``step_failed`` (torch raised) or ``non_finite_step``."""

    def __init__(self, kind: str, text: str) -> None:
        super().__init__(text)
        self.kind = kind


# --- the plant --------------------------------------------------------------------------------------------------


def plant_model(config: StackConfig, scene: Scene | None = None) -> tuple[Model, State]:
    """The plant's compiled model and initial state (B = 1, float64) for ``config``.

    The task scene (or ``scene``, e.g. a wrench benchmark object's) with ``PLANT.model`` contact at spacing
    ``planner.spacing * sim.spacing_factor`` (m), its object moved by ``sim.object_offset_m`` (then unpruned: the
    bubble may touch any point once it comes back to the object), one step per tick: ``dt = 1 / sim.rate_hz`` s,
    ``epsilon`` scaled by ``dt / scene.dt`` (the mobility ``dt / epsilon`` kept), and ``ceil(substeps *
    PLANT.substep_factor * dt / scene.dt)`` sub-steps (sub-steps no longer than the evaluation plant's; the step adds
    more when the contacts need them), the bubble's closest points solved in ``sim.sdf_solver_steps`` fixed steps
    (None: to convergence). Each arm's ``[arms.material]`` replaces its bubble body's material.
    """
    scene = make_task(config.scene.task).scene if scene is None else scene
    scene = with_body_materials(scene, config.bubble_materials())
    spacing_m = config.planner.spacing * config.sim.spacing_factor
    dx, dy = config.sim.object_offset_m
    moved = dx != 0.0 or dy != 0.0
    if moved:
        pose = [scene.object.pose[0] + dx, scene.object.pose[1] + dy, *scene.object.pose[2:]]
        scene = msgspec.structs.replace(scene, object=msgspec.structs.replace(scene.object, pose=pose))
    scene = with_solver_steps(with_contact(scene, PLANT.model, spacing_m), config.sim.sdf_solver_steps)
    model, state, _ = compile_scene(scene, prune=not moved)
    dt_s = 1.0 / config.sim.rate_hz
    substeps = max(1, math.ceil(model.substeps * PLANT.substep_factor * dt_s / model.dt - 1e-9))
    return replace(model, dt=dt_s, epsilon=model.epsilon * dt_s / model.dt, substeps=substeps), state


def body_control(previous: Tensor, target: Tensor) -> Tensor:
    """The control ``u (M, 6)`` that moves bodies from ``previous (M, 7)`` to ``target (M, 7)`` poses in one
    ``hydrosoft.dynamics.step``: world-frame translation increments (m) and rotation-vector increments (rad,
    shortest rotation, ``q_target = exp(u_rot) q_previous``)."""
    turn = se3.quat_multiply(target[:, 3:], se3.quat_conjugate(previous[:, 3:]))
    return torch.cat([target[:, :3] - previous[:, :3], se3.so3_log(turn)], dim=-1)


@dataclass(frozen=True, eq=False)
class PlantSnapshot:
    """The plant after one tick, for readers in other threads (a snapshot is never modified; the plant replaces
    it). stamp_ns: ``time.monotonic_ns()`` of the tick. object_pose: ``(7,)`` base frame. tcp_poses: per arm
    ``(7,)`` base frame. tcp_wrenches: per arm ``(6,)`` [N, N m], the wrench the object applies to the arm's body
    about the TCP, in the TCP frame."""

    stamp_ns: int
    object_pose: np.ndarray
    tcp_poses: dict[str, np.ndarray]
    tcp_wrenches: dict[str, np.ndarray]


class SimPlant:
    """The plant: a compiled model, its state, and the step that carries the arms' bodies to their TCP poses.

    Args:
        model, state: from ``plant_model`` (or any compiled scene with ``B = 1``).
        arms: the scene bodies the arms carry; each must be an actuated body of ``model``.
        compiled: step through ``CompiledStep`` (``compiled_step``; ``compile`` compiles it, or loads its artefact).
        frame: where the scene lies in the base frame (identity when None); ``state`` is in the scene's frame, what
            goes in and out (``step_to``, ``snapshot``, ``contact_forces``) in the base frame.

    ``step_to`` runs in one thread at a time; ``snapshot`` may be read from any thread.
    """

    def __init__(self, model: Model, state: State, arms: Sequence[str], compiled: bool = False,
                 frame: TaskFrame | None = None) -> None:
        missing = [arm for arm in arms if arm not in model.body_names]
        if missing:
            raise ValueError(f"arms {missing} are not bodies of the plant (its bodies: {list(model.body_names)})")
        self.model = model
        # in a step's own form (its signed distances cached, eager: one evaluation), so that a compiled step meets
        # one input signature from the first tick on and compiles no graph of its own for a start state's distances
        self.state = stepped_form(model, State(*state[:3]))
        self.frame = TaskFrame.from_pose(se3.identity()) if frame is None else frame
        self.compiled_step = CompiledStep(model, dynamic=False) if compiled else None
        self.arm_index = {arm: model.body_names.index(arm) for arm in arms}
        unactuated = [arm for arm, index in self.arm_index.items() if not bool(model.actuated[index])]
        if unactuated:
            raise ValueError(f"arms {unactuated} carry bodies the scene does not actuate")
        self.snapshot = self._snapshot()
        self._at_rest = False  # the last tick moved no body and changed nothing: the state is a fixed point
        self._last_tcp_poses: dict[str, bytes] = {}  # the TCP poses the last step_to was given, as bytes

    @classmethod
    def from_config(cls, config: StackConfig) -> SimPlant:
        """The plant of ``config`` (``plant_model``) with its arms, its step compiled when ``sim.compile``."""
        model, state = plant_model(config)
        return cls(model, state, [arm.name for arm in config.arms], config.sim.compile,
                   TaskFrame.from_pose(config.scene.task_frame))

    def step_to(self, tcp_poses: Mapping[str, np.ndarray], ticks: int = 1) -> None:
        """Move each arm's body to ``tcp_poses[arm]`` (``(7,)``, base frame) over ``ticks`` plant steps (equal
        increments; a late physics loop catches up with real time this way), then set the body poses exactly to
        them, and update ``snapshot``. The steps reach the targets to rounding (about 1e-16 m), so the signed
        distances the last step cached stay with the state: the next tick's stability check reuses them instead of
        solving every point's closest point again (``CompiledStep``), the plant's largest eager cost. At rest (no
        body moves and the last such tick left the state exactly as it was) the step is a fixed point and is
        skipped: only the snapshot's stamp advances.

        Raises:
            PlantStepError: for a missing or malformed TCP pose, an ``UnstableStepError``, a numerical failure
                (a torch ``RuntimeError`` or an ``ArithmeticError``) or a non-finite result; the state is then
                unchanged (all ``ticks`` steps or none).
        """
        self._last_tcp_poses = {}
        target = self.state.body_poses.clone()
        for arm, index in self.arm_index.items():
            try:
                pose = check_pose(tcp_poses[arm], f"TCP pose of arm {arm!r}")
            except KeyError:
                raise PlantStepError("bad_tcp_pose", f"no TCP pose for arm {arm!r}") from None
            except ValueError as error:
                raise PlantStepError("bad_tcp_pose", str(error)) from error
            target[0, index] = torch.as_tensor(self.frame.to_task_np(pose), dtype=self.model.dtype)
        still = torch.equal(target, self.state.body_poses)
        if still and self._at_rest:
            self._remember(tcp_poses)
            self.keep_still()
            return
        u = body_control(self.state.body_poses[0], target[0]).unsqueeze(0) / ticks
        nxt = self.state
        with torch.no_grad():
            for _ in range(ticks):
                nxt = self._step(nxt, u)
        self._at_rest = (still and torch.equal(nxt.object_pose, self.state.object_pose)
                         and torch.equal(nxt.forces, self.state.forces))
        self.state = State(nxt.object_pose, target, nxt.forces, nxt.phi)
        self.snapshot = self._snapshot()
        self._remember(tcp_poses)

    def rests_at(self, tcp_poses: Mapping[str, np.ndarray]) -> bool:
        """Whether ``step_to(tcp_poses)`` would only advance the snapshot's stamp: the state is a fixed point (see
        ``step_to``) and every arm's TCP pose is a float64 ``(7,)`` array equal, bit for bit, to the one the last
        completed ``step_to`` was given. A cheap check (no torch) for the physics loop, which then calls
        ``keep_still`` instead of stepping."""
        if not self._at_rest:
            return False
        for arm in self.arm_index:
            pose = tcp_poses.get(arm)
            if not isinstance(pose, np.ndarray) or pose.dtype != np.float64 or (
                    pose.tobytes() != self._last_tcp_poses.get(arm)):
                return False
        return True

    def keep_still(self) -> None:
        """A tick at rest (``rests_at``): only the snapshot's stamp advances."""
        self.snapshot = replace(self.snapshot, stamp_ns=time.monotonic_ns())

    def _remember(self, tcp_poses: Mapping[str, np.ndarray]) -> None:
        """Keep the TCP poses a completed ``step_to`` was given (as float64 bytes), for ``rests_at``."""
        self._last_tcp_poses = {arm: np.asarray(tcp_poses[arm], dtype=np.float64).tobytes()
                                for arm in self.arm_index}

    def _step(self, state: State, u: Tensor) -> State:
        """One plant step of ``u (1, M, 6)`` from ``state`` (no gradient); PlantStepError when it fails."""
        try:
            nxt = step(self.model, state, u) if self.compiled_step is None else self.compiled_step(state, u)
        except UnstableStepError as error:
            raise PlantStepError("unstable_step", str(error)) from error
        except (RuntimeError, ArithmeticError) as error:  # torch's numerical failures on a broken state
            raise PlantStepError("step_failed", f"{type(error).__name__}: {error}") from error
        if not all(bool(torch.isfinite(t).all()) for t in nxt[:3]):
            raise PlantStepError("non_finite_step", "the plant step gave non-finite poses or forces; state kept")
        return nxt

    def warm_up(self) -> None:
        """Run the step twice at rest, from the plant's state and from the state that step returns, and keep neither
        result: a compiled step compiles its graph here, not in the physics loop. Both states are in a step's own form
        (``stepped_form``), so it is one graph; a state of another form would compile a graph of its own here (an
        unpruned plant, ``sim.object_offset_m``, compiled a second graph at its second tick: 11 s)."""
        u = torch.zeros(1, self.model.n_bodies, 6, dtype=self.model.dtype)
        with torch.no_grad():
            self._step(self._step(self.state, u), u)

    def compile(self) -> str | None:
        """Compile the step (``warm_up``): None when it runs compiled, else why it fell back to eager."""
        self.warm_up()
        return None if self.compiled_step is None else self.compiled_step.fallback_reason

    def tcp_wrench(self, arm: str) -> np.ndarray:
        """The newest wrench ``(6,)`` [N, N m] on ``arm``'s body, TCP frame (``snapshot``; any thread)."""
        return self.snapshot.tcp_wrenches[arm]

    def contact_forces(self) -> tuple[np.ndarray, np.ndarray]:
        """``(points (N, 3), forces (M, N, 3))`` float64 copies: the object-frame surface points (m) and the force
        each body applies to each of them (base frame, N)."""
        return (self.model.points.double().numpy().copy(), self.frame.vectors_to_base(self.state.forces[0]).numpy())

    def _snapshot(self) -> PlantSnapshot:
        state = self.state
        wrenches = body_wrenches(self.model, state)[0]
        tcp_poses, tcp_wrenches = {}, {}
        for arm, index in self.arm_index.items():
            pose = state.body_poses[0, index]
            R = se3.quat_to_matrix(pose[3:])
            tcp_poses[arm] = self.frame.to_base_np(pose.double().numpy())
            tcp_wrenches[arm] = torch.cat([R.mT @ wrenches[index, :3], R.mT @ wrenches[index, 3:]]).double().numpy()
        return PlantSnapshot(time.monotonic_ns(), self.frame.to_base_np(state.object_pose[0].double().numpy()),
                             tcp_poses, tcp_wrenches)


# --- rates --------------------------------------------------------------------------------------------------------


@dataclass
class DurationStats:
    """How often a repeated job ran and how long it took, since the last ``summary``."""

    name: str
    count: int = 0
    total_s: float = 0.0
    max_s: float = 0.0

    def add(self, duration_s: float, runs: int = 1) -> None:
        """Count ``runs`` runs done together in ``duration_s`` s (the max is per such batch)."""
        self.count += runs
        self.total_s += duration_s
        self.max_s = max(self.max_s, duration_s)

    def summary(self, window_s: float) -> str:
        """``"<name> <rate> Hz, <mean> ms mean, <max> ms max"`` over ``window_s`` s (mean per run); starts a new
        window."""
        mean_ms = 1e3 * self.total_s / self.count if self.count else 0.0
        text = f"{self.name} {self.count / window_s:.1f} Hz, {mean_ms:.1f} ms mean, {1e3 * self.max_s:.1f} ms max"
        self.count, self.total_s, self.max_s = 0, 0.0, 0.0
        return text


# --- the service --------------------------------------------------------------------------------------------------


#: Who the simulated sensors' tares are stored as (``StoredBias.source``).
SIM_TARE_SOURCE = "sim_world, sim.ft_bias"


def store_sim_tare(config: StackConfig, arm: str) -> None:
    """Store the simulated FT 300's zero-load offset ``sim.ft_bias`` as ``arm``'s tare, replacing any stored one
    (it is what a tare out of contact reads on this sensor). Raises OSError when the file cannot be written."""
    stored = StoredBias(arm=arm, port=config.arm(arm).ft_port, bias=config.sim.ft_bias, taken_unix_ns=time.time_ns(),
                        samples=0, source=SIM_TARE_SOURCE)
    save_bias(bias_path(config.state_path(), arm), stored)


async def start_devices(service: Service, config: StackConfig,
                         plant: SimPlant) -> dict[str, SimulatedURController]:
    """Start each arm's simulated UR controller (returned by arm) and FT 300; register their shutdown."""
    loop = asyncio.get_running_loop()
    controllers = {}
    for index, arm in enumerate(config.arms):
        controller = SimulatedURController(URSimulatorConfig(host=arm.ur_host, tick_hz=config.sim.ur_tick_hz,
                                                             tcp_pose=plant.snapshot.tcp_poses[arm.name]))
        try:
            await controller.start()
        except OSError as error:
            raise RuntimeError(f"arm {arm.name}: cannot serve the simulated UR controller on {arm.ur_host}: "
                               f"{error}") from error
        service.on_shutdown(controller.stop)
        controllers[arm.name] = controller
        if not arm.ft_port:
            service.log.warning("arm %s has no ft_port: no simulated FT 300 for it", arm.name)
            continue
        Path(arm.ft_port).parent.mkdir(parents=True, exist_ok=True)
        store_sim_tare(config, arm.name)
        sensor = SimulatedFT300(functools.partial(plant.tcp_wrench, arm.name), link=arm.ft_port,
                                bias=np.array(config.sim.ft_bias), noise_scale=config.sim.ft_noise,
                                seed=index).start()
        service.on_shutdown(functools.partial(loop.run_in_executor, None, sensor.stop))
        service.log.info("arm %s: UR controller on %s, FT 300 at %s", arm.name, arm.ur_host, arm.ft_port)
    return controllers


async def physics_forever(service: Service, plant: SimPlant, controllers: Mapping[str, SimulatedURController],
                           stats: DurationStats) -> None:
    """Tick the plant towards the controllers' TCP poses (in a thread of its own; a tick at rest, ``rests_at``, in
    the loop without a step), one step per ``plant.model.dt`` s of real time: a tick that starts late takes the steps
    it is due (at most ``MAX_LAG_TICKS + 1``) over the motion since the last one, so simulated time keeps up with the
    simulated arm's real time on a busy machine. Further behind, it counts ``physics_behind`` and restarts its
    schedule from now (simulated time then lags)."""
    loop = asyncio.get_running_loop()
    period_s = plant.model.dt
    physics = ThreadPoolExecutor(max_workers=1, thread_name_prefix="physics")
    try:
        next_s = loop.time()  # when the next plant step is due
        while True:
            late_s = loop.time() - next_s
            if late_s > MAX_LAG_TICKS * period_s:
                service.count_error("physics_behind", f"the plant is {late_s * 1e3:.0f} ms behind its schedule: "
                                                      "simulated time runs slower than real time")
                next_s, late_s = loop.time(), 0.0
            due = 1 + max(0, int(late_s / period_s))
            tcp_poses = {arm: controller.tcp_pose() for arm, controller in controllers.items()}
            tic_s = time.perf_counter()
            if plant.rests_at(tcp_poses):
                plant.keep_still()
            else:
                try:
                    await loop.run_in_executor(physics, plant.step_to, tcp_poses, due)
                except PlantStepError as error:
                    service.count_error(error.kind, str(error))
            stats.add(time.perf_counter() - tic_s, due)
            next_s += due * period_s
            await asyncio.sleep(max(next_s - loop.time(), 0.0))
    finally:
        physics.shutdown(wait=False)  # a tick still running ends on its own; the loop does not wait for it


async def _tag_camera_forever(service: Service, camera: SimCamera, out: Publisher, stats: DurationStats) -> None:
    """Publish the tag camera's frames; ``stats`` gets each frame's latency from its exposure to its image."""
    topic = image_topic(TAG_CAMERA)
    await camera.connect()
    while True:
        try:
            frame = await camera.read()
        except DriverError as error:
            service.count_error("tag_camera", str(error))
            continue
        stats.add((frame.stamp_ns - frame.hw_stamp_ns) * 1e-9)
        await out.send(msg.CameraImage.of(TAG_CAMERA, frame.image, frame.hw_stamp_ns), topic)


async def _depth_forever(camera: BubbleDepthCamera, plant: SimPlant, out: Publisher, rate_hz: float,
                         stats: DurationStats) -> None:
    """Publish ``camera``'s depth images at ``rate_hz``, or as fast as they render."""
    loop = asyncio.get_running_loop()
    topic = msg.topic_for(msg.DepthFrame, camera.arm)
    next_s = loop.time()
    while True:
        snapshot = plant.snapshot
        tic_s = time.perf_counter()
        counts = await loop.run_in_executor(None, camera.render, snapshot.tcp_poses[camera.arm],
                                            snapshot.object_pose)
        stats.add(time.perf_counter() - tic_s)
        await out.send(camera.message(counts, snapshot.stamp_ns), topic)
        next_s = max(next_s + 1.0 / rate_hz, loop.time())
        await asyncio.sleep(next_s - loop.time())


async def _truth_forever(plant: SimPlant, out: Publisher) -> None:
    """Publish the object's pose and the contact forces on eval/ every ``EVAL_PERIOD_S``."""
    bodies = tuple(plant.model.body_names)
    while True:
        await out.send(msg.EvalObjectPose(object=OBJECT, pose=plant.snapshot.object_pose))
        points, forces = plant.contact_forces()
        await out.send(msg.EvalContactForces(bodies=bodies, points=points, forces=forces))
        await asyncio.sleep(EVAL_PERIOD_S)


async def log_rates_forever(service: Service, stats: Sequence[DurationStats]) -> None:
    loop = asyncio.get_running_loop()
    since_s = loop.time()
    while True:
        await asyncio.sleep(RATE_LOG_PERIOD_S)
        now_s = loop.time()
        service.log.info("; ".join(s.summary(now_s - since_s) for s in stats))
        since_s = now_s


def _warm_up(plant: SimPlant, camera: SimCamera, depth_cameras: Sequence[BubbleDepthCamera]) -> None:
    """The plant's steps at rest (``SimPlant.warm_up``) and one image of each camera, before READY: the first calls
    fill caches (slow; a compiled plant compiles here), and a scene that cannot be simulated or rendered fails at
    start rather than in the loop."""
    plant.warm_up()
    snapshot = plant.snapshot
    camera.render(snapshot.object_pose)
    for depth in depth_cameras:
        depth.render(snapshot.tcp_poses[depth.arm], snapshot.object_pose)


async def serve(service: Service, config: StackConfig) -> None:
    """Run the plant, the simulated devices, the renderers and the truth until cancelled."""
    if config.mode != "sim":
        raise ConfigError(f"sim_world runs only in mode = 'sim', the config says {config.mode!r}")
    torch.set_num_threads(TORCH_THREADS)
    cv2.setNumThreads(OPENCV_THREADS)
    loop = asyncio.get_running_loop()
    if config.sim.compile:
        artefacts.use_precompiled(config, artefacts.plant_key(config))  # before the plant's compiled step is made
    plant = await loop.run_in_executor(None, SimPlant.from_config, config)
    service.log.info("plant: %s task, %d surface points, %s bodies, %.0f Hz, %d sub-steps", config.scene.task,
                     plant.model.n_points, list(plant.model.body_names), 1.0 / plant.model.dt, plant.model.substeps)
    out = service.publisher(config.endpoint(service.name, "data"))
    controllers = await start_devices(service, config, plant)
    camera = tag_camera(config, lambda: plant.snapshot.object_pose)
    depth_cameras = [BubbleDepthCamera.from_config(config, arm.name, index) for index, arm in enumerate(config.arms)]
    physics_stats = DurationStats("physics")
    image_stats = DurationStats("tag camera (exposure to image)")
    depth_stats = [DurationStats(f"depth {c.arm}") for c in depth_cameras]
    if plant.compiled_step is None:
        service.compilation = "eager (sim.compile = false)"
    else:
        build = artefacts.PartBuild(artefacts.plant_key(config), artefacts.cache_dir(config))
        service.compilation = build.status
        if not await loop.run_in_executor(None, build.run, plant.compile, service.log.info):
            service.log.warning("the plant step runs eager: %s", build.fallback)
        service.compilation = build.status
    await loop.run_in_executor(None, _warm_up, plant, camera, depth_cameras)
    await service.ready()
    async with asyncio.TaskGroup() as tasks:
        tasks.create_task(physics_forever(service, plant, controllers, physics_stats))
        tasks.create_task(_tag_camera_forever(service, camera, out, image_stats))
        for depth, stats in zip(depth_cameras, depth_stats):
            tasks.create_task(_depth_forever(depth, plant, out, config.arm(depth.arm).depth.fps, stats))
        tasks.create_task(_truth_forever(plant, out))
        tasks.create_task(log_rates_forever(service, [physics_stats, image_stats, *depth_stats]))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments: CONFIG (mode = 'sim') [--name sim_world] (``service_cli``)."""
    service_cli.add_arguments(parser, SERVICE)


def run(args: argparse.Namespace) -> int:
    """Run sim_world until SIGINT/SIGTERM; the exit code (2 for a config that cannot be used)."""
    return service_cli.run(args, serve)


def main(argv: list[str] | None = None) -> int:
    return service_cli.main(SERVICE, __doc__, argv, add_arguments, run)


if __name__ == "__main__":
    service_cli.exit_process(main())
