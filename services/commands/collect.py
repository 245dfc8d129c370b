"""``hydrosoft-stack collect wrench CONFIG --out DIR``: record the wrench-transmission benchmark (paper V-C, Table II).

For each benchmark object (``hydrosoft.bench.wrench_scenes``: plate, triangle and trapezoid prisms, cube, cylinders
R15 and R25), ``--trajectories`` press-and-shear trajectories of ``--steps`` steps: the bubble starts out of contact
over the object (the tare sample), presses straight down to a random depth, then shears in a random direction,
twists, or both. At every step the arm is servoed to the step's target, held until it is at rest and for
``--hold-s`` more, and then one sample is taken: the measured TCP (bubble) pose, the object's pose and the F/T
wrench averaged over ``WRENCH_AVERAGE_S``, once two such windows in a row agree (settled). Each object's samples go
to ``DIR/wrench-<object>.mcap`` (``hydrosoft.bench.wrench_recording``), which ``hydrosoft-stack bench wrench`` reads.

The devices are the config's first arm (``--arm`` for another): the real ``URArm`` (ur_rtde) on ``ur_host`` and the
real ``FT300Sensor`` on ``ft_port``. In sim mode (``mode = "sim"``) the collector starts, per object, a plant process
(``python -m hydrosoft.services.commands.collect CONFIG --object NAME``) that serves a simulated UR controller on
``ur_host`` and a simulated FT 300 on ``ft_port``, fed by an NH plant of the benchmark object clamped to the table
(sim_world's ``SimPlant``, device start-up and physics loop, on the wrench scene). In the lab the same code drives
the real devices; clamp one object at ``--object-at`` (its centre on the table top, base frame) per run. In sim,
``--sim-clamp-error`` clamps it that far off ``--object-at`` while the recording keeps ``--object-at``: a constant
pose error in the recording, as a clamp measured wrong or a tracker's offset gives, for ``fit --pose-offset``.

Safety: every target of every trajectory is checked against the config's workspace box before the arm moves; moves
are interpolated within ``limits.max_speed_m_s`` and ``limits.max_angular_speed_rad_s`` at ``limits.servo_rate_hz``;
every servo period the F/T force (less the trajectory's tare) is checked against ``limits.max_force_n``; a step the
arm does not reach within its time bound, a force over the limit, any driver error or Ctrl-C stops the arm
(``servoStop``) before the collector exits; a trajectory that a driver error interrupted (the arm's state or the F/T
stream went stale on a loaded host, a link dropped and is reconnecting, the controller's watchdog stopped its
program) is stopped and run again from its approach, the program restarted if needed, up to ``TRAJECTORY_ATTEMPTS``
times; a protective stop ends the collection. The first move goes straight up to the approach height, then over.
Only complete trajectories are written. Exit status 0, 1 when the collection failed (the message says why), 2 for a
bad config or option.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import functools
import math
import selectors
import signal
import subprocess
import sys
import time
from dataclasses import asdict
from pathlib import Path

import msgspec
import numpy as np

from hydrosoft.drivers.base import Arm, ArmState, ForceTorqueSensor
from hydrosoft.drivers.base import WrenchSample as WrenchReading
from hydrosoft.drivers.errors import DriverError, Stale
from hydrosoft.drivers.robotiq_ft300.noise import RESOLUTION, SIGNAL_NOISE
from hydrosoft.drivers.robotiq_ft300.protocol import STREAM_RATE_HZ
from hydrosoft.scene_spec import IDENTITY_POSE
from hydrosoft.services.bus.config import ConfigError, LimitsConfig, StackConfig, load_config
from hydrosoft.services.arm.safety import check_target, interpolate, is_moving, rotation_angle_rad

PLANT_SERVICE = "wrench_plant"
PLANT_READY_TIMEOUT_S = 120.0  # import torch, compile the object's plant, start the simulated devices
PLANT_STOP_TIMEOUT_S = 10.0
APPROACH_LIFT_M = 0.01  # trajectories start and end this far above their start pose
LIFT = np.array([0.0, 0.0, APPROACH_LIFT_M, 0.0, 0.0, 0.0, 0.0])
WRENCH_AVERAGE_S = 0.05  # a sample's wrench is the mean of the F/T frames of this window (5 at 100 Hz)
#: Two windows in a row agree (settled) when each component changed by at most this many counts of the FT 300
#: (0.01 N, 0.001 N m) or ``SETTLE_SIGMAS`` standard deviations of the sensor's noise on the change, whichever is
#: more (``settle_change``): the datasheet's noise (0.1 N per frame) alone moves a 5-frame mean by 0.06 N.
SETTLE_COUNTS = 2
SETTLE_SIGMAS = 4.0
SETTLE_TIMEOUT_S = 2.0
WRENCH_MAX_AGE_S = 1.0  # the arm holds still while the F/T reading is stale; stale longer than this: stop, retry
POSITION_TOLERANCE_M = 1e-4  # a step's target counts as reached within this distance and angle, at rest
ANGLE_TOLERANCE_RAD = 2e-3
MOVE_MARGIN_S = 2.0  # a move may take this long beyond its distance over the speed limit
TRAJECTORY_ATTEMPTS = 5  # a trajectory a driver error interrupted (stale, link lost, program stopped) runs this often
RETRY_PAUSE_S = 1.0  # after such a trajectory's stop, wait this long before looking at the arm again
SERVO_LOOKAHEAD_S = 0.05  # servoL: a 30 ms tracking lag (UR range 0.03-0.2 s, 100-2000), for quick settling
SERVO_GAIN = 500.0
MAX_SIM_CLAMP_ERROR_M = 2e-3  # --sim-clamp-error per axis at most: a few tenths of a press's depth


class CollectError(RuntimeError):
    """The collection cannot go on; the arm has been (or is being) stopped. The message says why."""


def _floats(text: str, count: int, what: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{what}: expected {count} comma-separated numbers, got {text!r}") from None
    if len(values) != count or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"{what}: expected {count} finite comma-separated numbers, got {text!r}")
    return values


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``hydrosoft-stack collect wrench``."""
    parser.add_argument("config", help="the stack's TOML config (deploy/sim.toml: simulated devices; deploy/lab.toml)")
    parser.add_argument("--out", type=Path, required=True, help="folder for the wrench-<object>.mcap recordings")
    parser.add_argument("--objects", default="plate,triangle,trapezoid,cube,cylinder_r15,cylinder_r25",
                        help="comma list of benchmark objects (default all six; lab: one per run)")
    parser.add_argument("--trajectories", type=int, default=40, help="trajectories per object (default 40)")
    parser.add_argument("--steps", type=int, default=40, help="steps per trajectory, 2 to 40 (default 40)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the trajectories (default 0)")
    parser.add_argument("--arm", default=None, help="the config's arm to use (default the first)")
    parser.add_argument("--object-at", type=functools.partial(_floats, count=3, what="--object-at"),
                        default=(0.0, 0.0, 0.0), metavar="X,Y,Z",
                        help="where the object is clamped: its centre on the table top, base frame, m (default 0,0,0)")
    parser.add_argument("--tcp-in-sensor", type=functools.partial(_floats, count=7, what="--tcp-in-sensor"),
                        default=IDENTITY_POSE, metavar="X,Y,Z,QW,QX,QY,QZ",
                        help="the TCP (bubble) frame's pose in the F/T sensor's frame, m and wxyz, recorded for the "
                             "benchmark (default identity: the sim's FT 300 reports about the TCP)")
    parser.add_argument("--sim-clamp-error", type=functools.partial(_floats, count=3, what="--sim-clamp-error"),
                        default=(0.0, 0.0, 0.0), metavar="DX,DY,DZ",
                        help="sim only: the plant clamps the object this far (m, base frame) from --object-at while "
                             "the recording still says --object-at, as a clamp measured wrong or a tracker's constant "
                             "error (default 0,0,0; fit --pose-offset finds it back)")
    parser.add_argument("--hold-s", type=float, default=0.1,
                        help="how long the arm holds each step at rest before the sample, s (default 0.1)")


# --- one trajectory's motion and samples ----------------------------------------------------------------------------


def settle_change(noise_scale: float) -> np.ndarray:
    """The largest change ``(6,)`` (N, N m) between two ``WRENCH_AVERAGE_S`` windows of a settled wrench, for an FT
    300 whose noise is ``noise_scale`` times the datasheet's (1 in the lab; ``sim.ft_noise`` in sim): the larger of
    ``SETTLE_COUNTS`` counts and ``SETTLE_SIGMAS`` standard deviations of the difference of two windows' means."""
    frames = WRENCH_AVERAGE_S * STREAM_RATE_HZ
    return np.maximum(SETTLE_COUNTS * RESOLUTION, SETTLE_SIGMAS * noise_scale * SIGNAL_NOISE * math.sqrt(2 / frames))


class Collector:
    """Drives ``arm`` (an ``Arm`` with ``restart_script``: ``URArm``) through targets and samples ``sensor``, within
    ``limits``; ``collect_object`` stops the arm on any error. ``tare`` is the wrench the force limit is judged
    against (set at each trajectory's start). ``noise_scale``: the F/T sensor's noise, times the datasheet's, which
    sets how far two windows of a settled wrench may differ (``settle_change``)."""

    def __init__(self, arm: Arm, sensor: ForceTorqueSensor, limits: LimitsConfig, hold_s: float, log=print,
                 noise_scale: float = 1.0) -> None:
        self.arm = arm
        self.settle_change = settle_change(noise_scale)
        self.log = log
        self.sensor = sensor
        self.limits = limits
        self.hold_s = hold_s
        self.period_s = 1.0 / limits.servo_rate_hz
        self.tare = np.zeros(6)
        self._command: np.ndarray | None = None
        self._fresh_ns = time.monotonic_ns()

    async def reading(self) -> WrenchReading | None:
        """The F/T sensor's newest reading, or None while it has been stale for less than ``WRENCH_MAX_AGE_S`` (the
        stream hiccups on a loaded host); ``Stale`` past that."""
        try:
            reading = await self.sensor.read()
        except Stale as error:
            age_s = (time.monotonic_ns() - self._fresh_ns) / 1e9
            if age_s > WRENCH_MAX_AGE_S:
                raise Stale(f"no fresh F/T reading for {age_s:.2f} s: {error}") from error
            return None
        self._fresh_ns = reading.stamp_ns
        return reading

    async def fresh_wrench(self) -> np.ndarray:
        """The next fresh wrench ``(6,)`` (sensor frame), waiting for it (``reading``)."""
        while (reading := await self.reading()) is None:
            await asyncio.sleep(self.period_s)
        return np.asarray(reading.wrench, dtype=np.float64)

    async def check_force(self, reading: WrenchReading | None = None) -> bool:
        """Whether a fresh force (``reading``, default: the newest) was checked; ``CollectError`` when it, less the
        tare's, exceeds ``limits.max_force_n`` (N)."""
        reading = reading or await self.reading()
        if reading is None:
            return False
        force_n = float(np.linalg.norm(np.asarray(reading.wrench[:3]) - self.tare[:3]))
        if force_n > self.limits.max_force_n:
            raise CollectError(f"contact force {force_n:.1f} N above the limit {self.limits.max_force_n} N")
        return True

    async def move_to(self, target: np.ndarray, hold_s: float = 0.0) -> ArmState:
        """Servo to ``target (7,)`` within the speed limits until the TCP is there (``POSITION_TOLERANCE_M``,
        ``ANGLE_TOLERANCE_RAD``) and at rest, then ``hold_s`` more; the force is checked every period, and the arm
        holds its place while the F/T reading is stale. Returns the last state. ``CollectError`` when the target is
        outside the workspace or not reached in time."""
        reason = check_target(target, self.limits)
        if reason is not None:
            raise CollectError(f"refused: {reason}")
        loop = asyncio.get_running_loop()
        state = await self.arm.read_state()
        if self._command is None:
            self._command = state.tcp_pose.copy()
        distance_m = float(np.linalg.norm(target[:3] - self._command[:3]))
        angle_rad = rotation_angle_rad(self._command[3:], target[3:])
        deadline_s = loop.time() + MOVE_MARGIN_S + max(distance_m / self.limits.max_speed_m_s,
                                                        angle_rad / self.limits.max_angular_speed_rad_s)
        reached_s = None
        next_s = loop.time()
        while True:
            if await self.check_force():  # without a fresh force the arm holds its place
                self._command = interpolate(self._command, target, self.period_s, self.limits)
            await self.arm.servo_to(self._command)
            state = await self.arm.read_state()
            now_s = loop.time()
            if reached_s is None and self._at(state, target):
                reached_s = now_s
            if reached_s is not None and now_s - reached_s >= hold_s:
                return state
            if reached_s is None and now_s > deadline_s:
                raise CollectError(f"the arm did not reach {np.round(target, 5).tolist()} in time (at "
                                   f"{np.round(state.tcp_pose, 5).tolist()})")
            next_s = max(next_s + self.period_s, now_s)
            await asyncio.sleep(next_s - now_s)

    @staticmethod
    def _at(state: ArmState, target: np.ndarray) -> bool:
        return (float(np.linalg.norm(state.tcp_pose[:3] - target[:3])) <= POSITION_TOLERANCE_M
                and rotation_angle_rad(state.tcp_pose[3:], target[3:]) <= ANGLE_TOLERANCE_RAD
                and not is_moving(state.tcp_speed))

    async def sample(self, target: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
        """Move to ``target`` and hold; then, still holding, average the wrench over windows of ``WRENCH_AVERAGE_S``
        until two windows in a row agree within ``settle_change`` (the membrane, or a
        sim plant running late on a loaded host, has settled) or ``SETTLE_TIMEOUT_S`` passed (logged). Returns the
        TCP pose ``(7,)`` (base frame), the last window's mean wrench ``(6,)`` (sensor frame) and the stamp (ns)."""
        await self.move_to(target, self.hold_s)
        loop = asyncio.get_running_loop()
        deadline_s = loop.time() + SETTLE_TIMEOUT_S
        previous = await self._mean_wrench()
        while True:
            wrench = await self._mean_wrench()
            change = np.abs(wrench - previous)
            if np.all(change <= self.settle_change):
                break
            if loop.time() > deadline_s:
                self.log(f"the wrench did not settle within {SETTLE_TIMEOUT_S} s at "
                         f"{np.round(target[:3], 4).tolist()} (last change {np.round(change, 3).tolist()}); "
                         "sampled anyway")
                break
            previous = wrench
        state = await self.arm.read_state()
        return state.tcp_pose.copy(), wrench, time.monotonic_ns()

    async def _mean_wrench(self) -> np.ndarray:
        """The mean wrench ``(6,)`` of the F/T readings of one ``WRENCH_AVERAGE_S`` window, holding the arm."""
        loop = asyncio.get_running_loop()
        end_s = loop.time() + WRENCH_AVERAGE_S
        wrenches, stamps = [], set()
        while True:
            reading = await self.reading()
            if reading is not None and reading.stamp_ns not in stamps:
                stamps.add(reading.stamp_ns)
                wrenches.append(np.asarray(reading.wrench, dtype=np.float64))
                await self.check_force(reading)
            await self.arm.servo_to(self._command)
            if loop.time() >= end_s and wrenches:
                return np.mean(wrenches, axis=0)
            await asyncio.sleep(self.period_s)

    async def trajectory(self, plan: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, int]]:
        """One trajectory: to ``APPROACH_LIFT_M`` over its start (``approach``), a ``sample`` at each target of ``plan
        (K + 1, 7)`` (the first, out of contact, becomes the tare of the force limit), back up over the start.
        Returns per target the TCP pose, the mean wrench and the stamp."""
        self.tare = await self.fresh_wrench()
        await self.approach(plan[0] + LIFT)
        samples = []
        for step, target in enumerate(plan):
            samples.append(await self.sample(target))
            if step == 0:
                self.tare = samples[0][1]
        await self.move_to(plan[0] + LIFT)
        return samples

    async def recover(self) -> None:
        """Before running a stopped trajectory again: wait ``RETRY_PAUSE_S``, then restart the controller's program
        when its watchdog stopped it meanwhile; the next move starts from where the arm came to rest.
        ``CollectError`` while the safety system stops the arm (a person must look at it)."""
        self._command = None
        await asyncio.sleep(RETRY_PAUSE_S)
        state = await self.arm.read_state()
        if state.protective_stop or state.emergency_stop:
            raise CollectError("the arm is protectively or emergency stopped; unlock it on the pendant first")
        if not state.running:
            await self.arm.restart_script()

    async def approach(self, target: np.ndarray) -> None:
        """Go to ``target`` without touching anything: straight up to its height (or stay higher), over, down."""
        current = (await self.arm.read_state()).tcp_pose
        reason = check_target(current, self.limits)
        if reason is not None:
            raise CollectError(f"the arm is not in the workspace box ({reason}); jog it there first")
        height = max(float(current[2]), float(target[2]))
        for waypoint in (np.concatenate([current[:2], [height], current[3:]]),
                         np.concatenate([target[:2], [height], target[3:]]), target):
            await self.move_to(waypoint)


# --- the collection ---------------------------------------------------------------------------------------------


def plan_object(name: str, trajectories: int, steps: int, seed: int, origin,
                limits: LimitsConfig) -> tuple[list, list[np.ndarray]]:
    """Per trajectory its parameters (``PressAndShear``) and its targets ``(steps + 1, 7)``, seeded per object (an
    object's trajectories do not depend on which other objects are collected). ``CollectError`` when a target or
    a trajectory's approach pose (``APPROACH_LIFT_M`` over its start) lies outside the workspace box."""
    from hydrosoft.bench.wrench_scenes import BENCH_OBJECTS, bench_object, press_and_shear, sample_press_and_shear

    obj = bench_object(name)
    rng = np.random.default_rng([seed, list(BENCH_OBJECTS).index(name)])
    params = [sample_press_and_shear(rng, steps) for _ in range(trajectories)]
    plans = [press_and_shear(obj, p, origin) for p in params]
    for index, plan in enumerate(plans):
        for pose in (*plan, plan[0] + LIFT):
            reason = check_target(pose, limits)
            if reason is not None:
                raise CollectError(f"{name} trajectory {index}: {reason}; move --object-at or widen the box")
    return params, plans


def _floats_of(array: np.ndarray) -> tuple[float, ...]:
    return tuple(float(v) for v in array)


def _phase(step: int, press_steps: int) -> str:
    return "start" if step == 0 else "press" if step <= press_steps else "shear"


async def collect_object(config: StackConfig, config_path: str, arm_name: str, name: str, params: list,
                         plans: list[np.ndarray], seed: int, out: Path, origin, tcp_in_sensor, hold_s: float,
                         log=print) -> Path:
    """Record the trajectories ``plans`` (``plan_object``) of object ``name`` with ``arm_name``'s UR arm and FT 300;
    returns the recording's path. Raises ``CollectError`` (a force over the limit, a step not reached, the arm
    outside the workspace) or ``DriverError``, after stopping the arm."""
    from hydrosoft.bench.wrench_recording import RecordingInfo, WrenchRecordingWriter, WrenchSample
    from hydrosoft.bench.wrench_scenes import bench_object
    from hydrosoft.drivers.robotiq_ft300.config import FT300Config
    from hydrosoft.drivers.robotiq_ft300.sensor import FT300Sensor
    from hydrosoft.drivers.ur.arm import URArm
    from hydrosoft.drivers.ur.config import URArmConfig

    arm_config = config.arm(arm_name)
    object_pose = bench_object(name).pose(origin)
    limits = config.limits
    arm = URArm(URArmConfig(host=arm_config.ur_host, servo_rate_hz=limits.servo_rate_hz,
                            servo_lookahead_s=SERVO_LOOKAHEAD_S, servo_gain=SERVO_GAIN,
                            max_tcp_speed_m_s=limits.max_speed_m_s, max_age_s=limits.state_timeout_s))
    sensor = FT300Sensor(FT300Config(port=arm_config.ft_port))
    info = RecordingInfo(object=name, config=config_path, mode=config.mode, tcp_in_sensor=tuple(tcp_in_sensor),
                         plant_spacing_m=config.planner.spacing * config.sim.spacing_factor if config.mode == "sim"
                         else None, seed=seed, epoch_offset_ns=time.time_ns() - time.monotonic_ns(),
                         trajectories=[asdict(p) for p in params], config_toml=Path(config_path).read_text())
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"wrench-{name}.mcap"
    try:
        await arm.connect()
        await sensor.connect()
        collector = Collector(arm, sensor, limits, hold_s, log, config.sim.ft_noise if config.mode == "sim" else 1.0)
        with WrenchRecordingWriter(path, info) as writer:
            for index, (trajectory, plan) in enumerate(zip(params, plans)):
                tic = time.monotonic()
                for attempt in range(1, TRAJECTORY_ATTEMPTS + 1):
                    try:
                        if attempt > 1:
                            await collector.recover()
                        samples = await collector.trajectory(plan)
                        break
                    except DriverError as error:
                        if attempt == TRAJECTORY_ATTEMPTS:
                            raise
                        with contextlib.suppress(DriverError):
                            await arm.stop()
                        log(f"{name} trajectory {index + 1}: {error}; the arm was stopped, the trajectory starts "
                            f"again (retry {attempt} of {TRAJECTORY_ATTEMPTS - 1})")
                for step, ((tcp_pose, wrench, stamp_ns), target) in enumerate(zip(samples, plan)):
                    writer.add(WrenchSample(object=name, trajectory=index, step=step,
                                            phase=_phase(step, trajectory.press_steps), stamp_ns=stamp_ns,
                                            bubble_pose=_floats_of(tcp_pose), target_pose=_floats_of(target),
                                            object_pose=_floats_of(object_pose), wrench=_floats_of(wrench)))
                log(f"{name} trajectory {index + 1}/{len(plans)} ({trajectory.kind}, depth "
                    f"{1e3 * trajectory.depth_m:.1f} mm, shear {1e3 * trajectory.shear_m:.1f} mm, twist "
                    f"{math.degrees(trajectory.twist_rad):.1f} deg): {time.monotonic() - tic:.1f} s")
    except BaseException:
        with contextlib.suppress(DriverError):
            await arm.stop()
        raise
    finally:
        await sensor.close()
        await arm.close()
    return path


class PlantProcess:
    """The sim plant of one object as a child process (``python -m hydrosoft.services.commands.collect``): started
    and awaited READY by ``start``, stopped by its pid (SIGINT, then SIGKILL) by ``stop``."""

    def __init__(self, config_path: str, name: str, origin, arm: str) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "hydrosoft.services.commands.collect", config_path, "--object", name, "--arm", arm,
             "--object-at", ",".join(repr(float(v)) for v in origin)], stdout=subprocess.PIPE)

    def wait_ready(self, timeout_s: float = PLANT_READY_TIMEOUT_S) -> None:
        with selectors.DefaultSelector() as selector:
            selector.register(self.proc.stdout, selectors.EVENT_READ)
            line = self.proc.stdout.readline().decode() if selector.select(timeout_s) else ""
        if not line.startswith(f"READY {PLANT_SERVICE} {self.proc.pid}"):
            exited = self.proc.poll() is not None
            self.stop()
            raise CollectError(f"the sim plant exited with status {self.proc.returncode} before it was ready (its "
                               "log is above)" if exited else f"the sim plant was not ready within {timeout_s} s")

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(PLANT_STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(PLANT_STOP_TIMEOUT_S)
        self.proc.stdout.close()


def plant_origin(args: argparse.Namespace) -> tuple[float, ...]:
    """Where the sim plant clamps the object (its centre on the table top, base frame, m): ``--object-at`` moved by
    ``--sim-clamp-error``; the recording keeps ``--object-at``, so its object poses are off by minus that error."""
    return tuple(float(a) + float(e) for a, e in zip(args.object_at, args.sim_clamp_error))


async def collect(config: StackConfig, args: argparse.Namespace, objects: list[str], log=print) -> list[Path]:
    """Every object's recording (sim: each with its own plant process); see the module docstring."""
    arm = args.arm or config.arms[0].name
    plans = {name: plan_object(name, args.trajectories, args.steps, args.seed, args.object_at, config.limits)
             for name in objects}  # every target checked before anything starts or moves
    paths = []
    for name in objects:
        plant = None
        if config.mode == "sim":
            Path(config.run_dir).mkdir(parents=True, exist_ok=True)
            plant = PlantProcess(args.config, name, plant_origin(args), arm)
            if any(args.sim_clamp_error):
                log(f"{name}: the sim plant clamps it at {plant_origin(args)} m, {args.sim_clamp_error} m off "
                    "--object-at; the recording keeps --object-at")
        try:
            if plant is not None:
                await asyncio.to_thread(plant.wait_ready)
            paths.append(await collect_object(config, args.config, arm, name, *plans[name], args.seed, args.out,
                                              args.object_at, args.tcp_in_sensor, args.hold_s, log))
        finally:
            if plant is not None:
                await asyncio.to_thread(plant.stop)
    return paths


def _check_options(config: StackConfig, args: argparse.Namespace) -> list[str]:
    """The objects to collect; ConfigError naming a bad option."""
    from hydrosoft.bench.wrench_scenes import BENCH_OBJECTS, MAX_STEPS

    objects = [o.strip() for o in args.objects.split(",") if o.strip()]
    unknown = [o for o in objects if o not in BENCH_OBJECTS]
    if unknown or not objects:
        raise ConfigError(f"--objects: unknown {unknown}; the objects are {', '.join(BENCH_OBJECTS)}")
    if config.mode == "lab" and len(objects) != 1:
        raise ConfigError("--objects: in the lab, collect one object per run (clamp it, then run again)")
    if args.trajectories < 1:
        raise ConfigError(f"--trajectories must be at least 1, got {args.trajectories}")
    if not 2 <= args.steps <= MAX_STEPS:
        raise ConfigError(f"--steps must be 2 to {MAX_STEPS}, got {args.steps}")
    if not (math.isfinite(args.hold_s) and args.hold_s >= 0):
        raise ConfigError(f"--hold-s must be a non-negative number of seconds, got {args.hold_s}")
    if any(args.sim_clamp_error) and config.mode != "sim":
        raise ConfigError("--sim-clamp-error: the sim plant's clamp only (mode = 'sim'); in the lab the clamp is where "
                          "it is")
    if not all(math.isfinite(e) and abs(e) <= MAX_SIM_CLAMP_ERROR_M for e in args.sim_clamp_error):
        raise ConfigError(f"--sim-clamp-error must be within {1e3 * MAX_SIM_CLAMP_ERROR_M:g} mm per axis, got "
                          f"{args.sim_clamp_error}")
    arm = config.arm(args.arm or config.arms[0].name)
    if not arm.ft_port:
        raise ConfigError(f"arms.{arm.name}.ft_port: the benchmark needs the F/T sensor")
    return objects


def run(args: argparse.Namespace) -> int:
    """Collect; the exit status (see the module docstring)."""
    def log(text: str) -> None:
        print(f"[collect wrench] {text}", file=sys.stderr, flush=True)

    try:
        config = load_config(args.config)
        objects = _check_options(config, args)
    except ConfigError as error:
        print(f"collect wrench: {error}", file=sys.stderr)
        return 2
    try:
        paths = asyncio.run(collect(config, args, objects, log))
    except KeyboardInterrupt:
        log("interrupted: the arm was stopped; complete trajectories are in the recording")
        return 1
    except (CollectError, DriverError, OSError) as error:
        log(f"failed, the arm was stopped: {error}")
        return 1
    for path in paths:
        print(path)
    return 0


# --- the sim plant process ------------------------------------------------------------------------------------------


async def serve_plant(service, config: StackConfig, name: str, origin, arm_name: str) -> None:
    """The sim plant of benchmark object ``name`` clamped at ``origin``: arm ``arm_name``'s simulated UR controller
    and FT 300, fed by sim_world's ``SimPlant`` of the wrench scene (its bubble starts over the object), ticked in
    real time."""
    import torch

    from hydrosoft.bench.wrench_scenes import bench_object, start_pose, wrench_scene
    from hydrosoft.services.sim_world import (
        TORCH_THREADS,
        DurationStats,
        SimPlant,
        log_rates_forever,
        physics_forever,
        start_devices,
        plant_model,
    )

    torch.set_num_threads(TORCH_THREADS)
    arm = config.arm(arm_name)
    single = msgspec.structs.replace(config, arms=[arm])
    obj = bench_object(name)
    scene = wrench_scene(name, body=arm.name, object_pose=obj.pose(origin),
                         bubble_pose=start_pose(obj, origin) + LIFT)
    loop = asyncio.get_running_loop()
    model, state = await loop.run_in_executor(None, plant_model, single, scene)
    plant = SimPlant(model, state, [arm.name])
    service.log.info("wrench plant: %s, %d surface points, %.0f Hz, %d sub-steps", name, model.n_points,
                     1.0 / model.dt, model.substeps)
    controllers = await start_devices(service, single, plant)
    stats = DurationStats("physics")
    await service.ready()
    async with asyncio.TaskGroup() as tasks:
        tasks.create_task(physics_forever(service, plant, controllers, stats))
        tasks.create_task(log_rates_forever(service, [stats]))


def main(argv: list[str] | None = None) -> int:
    """``python -m hydrosoft.services.commands.collect CONFIG --object NAME``: the sim plant alone, until SIGINT."""
    from hydrosoft.bench.wrench_scenes import BENCH_OBJECTS
    from hydrosoft.services.bus.runtime import run_service

    parser = argparse.ArgumentParser(prog="python -m hydrosoft.services.commands.collect",
                                     description="the wrench benchmark's sim plant (collect wrench starts it)")
    parser.add_argument("config", help="the stack's TOML config (mode = 'sim')")
    parser.add_argument("--object", required=True, choices=list(BENCH_OBJECTS), help="the benchmark object")
    parser.add_argument("--arm", default=None, help="the config's arm whose devices it simulates (default the first)")
    parser.add_argument("--object-at", type=functools.partial(_floats, count=3, what="--object-at"),
                        default=(0.0, 0.0, 0.0), metavar="X,Y,Z", help="the object's centre on the table top, m")
    args = parser.parse_args(argv)
    try:
        config = load_config(args.config)
        if config.mode != "sim":
            raise ConfigError(f"the sim plant runs only in mode = 'sim', the config says {config.mode!r}")
        arm = config.arm(args.arm or config.arms[0].name).name
    except ConfigError as error:
        print(f"{PLANT_SERVICE}: {error}", file=sys.stderr)
        return 2
    Path(config.run_dir).mkdir(parents=True, exist_ok=True)
    return run_service(PLANT_SERVICE, config.runtime(PLANT_SERVICE),
                       functools.partial(serve_plant, config=config, name=args.object, origin=args.object_at,
                                         arm_name=arm))


if __name__ == "__main__":
    sys.exit(main())
