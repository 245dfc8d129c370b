"""The stack's configuration: one TOML file (``deploy/sim.toml``, ``deploy/lab.toml``) read into frozen structs.

Every service reads the same file and takes its own part. ``load_config`` validates it on load; an unknown or
bad key raises ``ConfigError`` naming the file and the key (``limits.max_speed_m_s: must be > 0``).

Layout (see ``deploy/sim.toml`` for a commented example)::

    run_dir, log_level, mode          where ipc sockets and pty links live; "sim" or "lab"
    log_dir                           where each service writes its own log file NAME.log (default RUN_DIR/logs)
    compile_cache_dir                 torch's compile cache for the compiled planner and plant (kept between
                                      launches; default /tmp/torchinductor_USER)
    state_dir                         what the stack keeps between launches (the F/T sensors' stored tares);
                                      relative: under run_dir (default run_dir/state)
    [scene]                           the task whose scene is on the table, where it lies (task_frame), the tags
    [camera]                          the tag camera: intrinsics, pose in the base frame, rate
    [[arms]]                          per arm: the scene body it carries (its TCP is that body's frame), the UR
                                      controller's address, its bubble's depth camera, its F/T sensor's port,
                                      optionally its bubble's fitted material ([arms.material]: E, K, mu)
    [limits]                          the arm commander's safety limits and watchdog timeouts
    [planner]                         the MPC settings and the maximum age of each input; ``preset = "paper"`` or
                                      ``"quick"`` starts from a named set of settings (``PLANNER_PRESETS``), which
                                      the table's own keys override
    [sim]                             sim_world: rate, plant resolution, noise
    [services.NAME]                   per service: restart policy and readiness timeout
    [endpoints]                       optional overrides "SERVICE.data|status|cmd" = "tcp://..." (else ipc://)
    [curve]                           CURVE key files, required for endpoints other than loopback or ipc;
                                      ``loopback = true`` puts CURVE on tcp://127.x endpoints too (CI)
    [hosts.NAME]                      a stack split across hosts: each host's address, services, first tcp port,
                                      CURVE public key and (optionally) its own run_dir
    host                              the host this process runs on (``launch --host``, ``$HYDROSOFT_HOST``)

Service names: ``sim_world`` (sim mode only), ``tag_tracker``, ``planner`` and one ``arm_commander-ARM``,
``bubble_camera-ARM`` and ``ft_reader-ARM`` per arm. Each binds ``ipc://RUN_DIR/NAME.data`` (its topics) and
``ipc://RUN_DIR/NAME.status`` (status, heartbeat); the planner also ``ipc://RUN_DIR/planner.cmd`` (the client API).

Split across hosts. With ``[hosts.NAME]`` tables every service belongs to one host. Each service binds its ipc
endpoints and, beside them, ``tcp://ADDRESS:PORT`` on its host's address (``RuntimeConfig.also_bind``), the port
``first_port + 3 * i + k`` (``i``: its place in ``service_names()``, ``k``: 0 data, 1 status, 2 cmd), so the ports
follow from the config alone. A process reads a service of its own host (``host``) over ipc and any other over
tcp; a process that names no host (a tool run without ``$HYDROSOFT_HOST``) reads every service over tcp.
"""

from __future__ import annotations

import ipaddress
import math
import os
import re
from pathlib import Path
from typing import Literal

import msgspec

from hydrosoft.services.bus.sockets import CurveKeys, CurveServer, check_endpoint
from hydrosoft.services.bus.runtime import RuntimeConfig

Pose = tuple[float, float, float, float, float, float, float]
Vec3 = tuple[float, float, float]
RestartPolicy = Literal["never", "on-failure", "always"]
ENDPOINT_KINDS = ("data", "status", "cmd")
#: Environment variable naming the host a process runs on (the launcher's ``--host`` sets it for its services).
HOST_ENV = "HYDROSOFT_HOST"
SDF_SOLVER_STEPS_MAX = 32  # hydrosoft.geometry.sdf.Ellipsoid.MAX_SOLVER_STEPS, not imported: config loads no torch
#: The planner devices a config may name (``planner.device``): the CPU, the current CUDA GPU, or CUDA GPU N.
PLANNER_DEVICE = re.compile(r"cpu|cuda(:[0-9]+)?")


class ConfigError(ValueError):
    """A configuration that cannot be used; the message names the file and the key."""


def _require(condition: bool, key: str, text: str) -> None:
    if not condition:
        raise ConfigError(f"{key}: {text}")


def _check_pose(pose: Pose, key: str) -> None:
    _require(all(math.isfinite(v) for v in pose), key, f"a pose is 7 finite numbers [x, y, z, qw, qx, qy, qz], got {pose}")
    _require(abs(math.sqrt(sum(v * v for v in pose[3:])) - 1.0) <= 1e-6, key, f"quaternion {pose[3:]} is not unit length")


def _positive(owner: object, prefix: str, *names: str) -> None:
    for name in names:
        value = getattr(owner, name)
        _require(isinstance(value, (int, float)) and math.isfinite(value) and value > 0, f"{prefix}.{name}",
                 f"must be a positive number, got {value!r}")


class Strict(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Base of every config table: unknown keys are errors."""


MAX_TASK_FRAME_TILT_DEG = 2.0
"""The largest angle between the task frame's z axis and the base's: the scenes' gravity acts along the task
frame's -z, so a task frame that is not level (for a table-mounted arm) is a wrong quaternion, not a slope."""


class SceneConfig(Strict):
    """task: the ``hydrosoft.tasks`` task whose scene is on the table. tag_size_m: AprilTag black-square edge on
    each face of the object (m). task_frame: ``T_base_task``, where the task scene's frame (its table top at
    z = 0, the object's start near its origin) lies in the robot's base frame (``services/arm/task_frame.py``); level,
    so only a turn about z; identity by default."""

    task: Literal["pushing", "rotation", "rolling", "in_hand"] = "pushing"
    tag_size_m: float = 0.032
    task_frame: Pose = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        _positive(self, "scene", "tag_size_m")
        _check_pose(self.task_frame, "scene.task_frame")
        _, qx, qy, _ = self.task_frame[3:]
        tilt = math.degrees(math.acos(max(-1.0, min(1.0, 1.0 - 2.0 * (qx * qx + qy * qy)))))
        _require(tilt <= MAX_TASK_FRAME_TILT_DEG, "scene.task_frame",
                 f"its z axis is {tilt:.1f} deg from the base's z axis (at most {MAX_TASK_FRAME_TILT_DEG} deg): the "
                 "table must be level in the base frame, so the quaternion may only turn about z (is it in "
                 "[qw, qx, qy, qz] order?)")


class CameraConfig(Strict):
    """The tag camera: image size (px), pinhole intrinsics (px), ``pose`` = T_base_camera (OpenCV axes: x right,
    y down, z forward), frame rate (Hz); ``calibration``: a calibration TOML file that overrides the intrinsics
    and pose (the lab's), or "" to use these numbers; ``device``: OpenCV device index or URL (lab only).
    ``detector_threads``: OpenCV's threads in the tag tracker (``cv2.setNumThreads``); 1 by default: on 2 cores
    OpenCV's pool cost about a quarter more CPU per image than one thread for 0.7 ms less latency (``bench tracker
    --threads``)."""

    width: int = 640
    height: int = 480
    fx: float = 600.0
    fy: float = 600.0
    cx: float = 319.5
    cy: float = 239.5
    pose: Pose = (0.25, -0.35, 0.33, 0.433949, -0.847676, -0.271651, 0.139066)  # deploy/sim.toml's: sees every sim task
    fps: float = 15.0
    calibration: str = ""
    device: str = ""
    detector_threads: int = 1

    def __post_init__(self) -> None:
        _positive(self, "camera", "width", "height", "fx", "fy", "fps", "detector_threads")
        _check_pose(self.pose, "camera.pose")


class DepthConfig(Strict):
    """A bubble's depth camera, sitting at the bubble frame's origin and looking along its ``axis`` (``-z`` or
    ``+z`` of the bubble frame, whichever side of the membrane touches the object; its image x axis along the
    bubble's x): image size (px), intrinsics (px), rate (Hz), depth unit (m per count). Lab only: ``device``, the
    camera's OpenCV source (a device index such as ``"2"``, a ``/dev/v4l/by-id/...`` path, a URL, or a recorded
    16-bit stream: an FFV1 ``.mkv`` or a ``frame_%04d.png`` sequence), and ``reference``, the reference membrane
    file (``.npz``) that ``hydrosoft-stack capture reference`` writes; both empty by default (sim mode renders the
    depth and uses the nominal membrane)."""

    axis: Literal["-z", "+z"] = "-z"
    width: int = 160
    height: int = 120
    fx: float = 40.0  # a 126 x 113 deg view: the whole contact patch (at 90 px the rim was lost, 26-38 % of the force)
    fy: float = 40.0
    cx: float = 79.5
    cy: float = 59.5
    fps: float = 30.0
    depth_scale_m: float = 0.0001
    device: str = ""
    reference: str = ""

    def __post_init__(self) -> None:
        _positive(self, "depth", "width", "height", "fx", "fy", "fps", "depth_scale_m")

    def camera_in_bubble(self) -> Pose:
        """T_bubble_camera ``(7,)``: at the bubble frame's origin, looking along ``axis`` (for ``-z`` the bubble
        frame turned 180 deg about its x axis, for ``+z`` the bubble frame itself)."""
        return (0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0) if self.axis == "-z" else (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)


MATERIAL_MU_MAX = 3.0
"""The largest friction coefficient a bubble's material may have (``hydrosoft-stack fit`` keeps mu below it): a
rubber membrane's mu lies near 1; a larger one is a typo."""


class MaterialConfig(Strict):
    """A bubble's material, ``[arms.material]`` (``hydrosoft-stack fit --out`` writes it): E, the normal pressure
    gradient (Pa/m); K, the shear stiffness (Pa/m); mu, the friction coefficient. Each left out keeps the task
    scene's value for that arm's bubble body."""

    E: float | None = None
    K: float | None = None
    mu: float | None = None

    def values(self) -> dict[str, float]:
        """The values given, by name (``E``, ``K``, ``mu``)."""
        return {name: getattr(self, name) for name in ("E", "K", "mu") if getattr(self, name) is not None}


class ArmConfig(Strict):
    """One arm. name: the scene body it carries (its TCP frame is that body's frame). ur_host: the UR controller's
    address (sim: a 127.0.0.N loopback address for the simulated controller). ft_port: the FT 300's serial port
    (sim: a path under run_dir that sim_world links to its pseudo-terminal). depth: the bubble's depth camera.
    nominal_tcp: the TCP's nominal orientation [qw, qx, qy, qz] in the base frame (the scene body's, turned by
    scene.task_frame; identity: the membrane faces down), from which ``limits.max_tilt_deg`` and
    ``limits.yaw_range_deg`` are measured. material: its bubble's material, which the planner and the sim plant
    give that scene body in place of the scene's (None: the scene's)."""

    name: str
    ur_host: str = "127.0.0.2"
    ft_port: str = ""
    depth: DepthConfig = DepthConfig()
    nominal_tcp: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    material: MaterialConfig | None = None

    def __post_init__(self) -> None:
        unit = abs(math.sqrt(sum(v * v for v in self.nominal_tcp)) - 1.0) <= 1e-6
        _require(all(math.isfinite(v) for v in self.nominal_tcp) and unit, f"arms.{self.name}.nominal_tcp",
                 f"must be a unit quaternion [qw, qx, qy, qz], got {self.nominal_tcp}")
        values = self.material.values() if self.material is not None else {}
        for name in ("E", "K"):
            if name in values:
                _require(math.isfinite(values[name]) and values[name] > 0, f"arms.{self.name}.material.{name}",
                         f"must be a positive, finite number of Pa/m, got {values[name]}")
        if "mu" in values:
            _require(math.isfinite(values["mu"]) and 0 <= values["mu"] <= MATERIAL_MU_MAX,
                     f"arms.{self.name}.material.mu", f"must be in [0, {MATERIAL_MU_MAX:g}], got {values['mu']}")


#: Upper bounds of the arm commander's limits, each with its reason. A config past one is a typo or a wrong unit,
#: not a choice: the commander refuses to start on it.
LIMIT_BOUNDS = {
    "max_speed_m_s": 0.25,  # ISO 10218-1's reduced speed for work beside people (250 mm/s)
    "max_angular_speed_rad_s": 3.14,  # half a turn per second: faster turns the bubble too fast to watch
    "max_force_n": 150.0,  # ISO/TS 15066's quasi-static limit for a hand (140 N), rounded up; the FT 300's range
    "servo_rate_hz": 500.0,  # an e-Series controller's cycle
    "idle_rate_hz": 500.0,  # at most servo_rate_hz (checked there)
    "heartbeat_timeout_s": 2.0,  # longer, a dead planner's last target would steer the arm for seconds
    "planner_lost_s": 10.0,  # longer, a planner silent for many seconds could still resume its goal
    "sensor_lost_s": 10.0,  # longer, a sensor back from a restart many seconds later could still resume its goal
    "state_timeout_s": 1.0,  # longer, the arm would move blind past ur_rtde's own 2.5 s read deadline
    "max_target_lead_s": 5.0,  # a target is a plan step, valid for a fraction of a second, not a program
    "max_plan_age_s": 10.0,  # a planner that solved nothing for this long is hung, not slow
    "max_tilt_deg": 90.0,  # the bubble faces sideways at most: past it the tool turns over
    "max_yaw_deg": 180.0,  # a full turn either way
}
#: Largest workspace box edge, m (a UR5e reaches 0.85 m; the box is the table's corner the task uses).
MAX_WORKSPACE_EDGE_M = 1.0


class LimitsConfig(Strict):
    """The arm commander's limits. workspace_min/max: the box (m, base frame) every TCP target, and the straight
    path to it, must lie in. max_speed_m_s, max_angular_speed_rad_s: the interpolation's speed limit (the UR
    driver's ``max_tcp_speed_m_s`` is this). max_force_n: above this contact force (N) only a target that moves
    the bubble away from the contact is servoed (a retreat); release_force_n: normal servoing resumes only once
    the force has fallen below this (N, < max_force_n; default 0.75 x max_force_n). servo_rate_hz: the rate of
    servo commands. idle_rate_hz: the commander's rate while it holds the arm at rest with no target (it checks
    the arm and publishes its state this often, and wakes at once on a target). heartbeat_timeout_s: stop when
    the planner's heartbeat is older. planner_lost_s: a heartbeat older than this, after it was fresh, ends the
    goal (a new goal must be started). sensor_lost_s: an input the motion depends on (the F/T readings for the
    commander; the object pose, TCP poses and membrane images for the planner) missing for longer than this, after
    it was fresh, ends the goal the same way. state_timeout_s: stop when the arm driver's state has not advanced for this
    long. max_target_lead_s: a target's deadline is clamped to at most this far after its arrival (s).
    max_plan_age_s: stop when the plan behind the target was completed longer ago than this (s; a hung solve).
    max_tilt_deg: the largest angle between a target's tool z axis and the arm's nominal one
    (``ArmConfig.nominal_tcp``); yaw_range_deg: the range of the turn about the nominal tool z axis, relative to
    the nominal orientation (deg). Every limit has an upper bound (``LIMIT_BOUNDS``)."""

    workspace_min: Vec3 = (-0.15, -0.15, 0.0)
    workspace_max: Vec3 = (0.15, 0.15, 0.2)
    max_speed_m_s: float = 0.1
    max_angular_speed_rad_s: float = 1.0
    max_force_n: float = 40.0
    release_force_n: float | None = None
    servo_rate_hz: float = 125.0
    idle_rate_hz: float = 25.0
    heartbeat_timeout_s: float = 0.5
    planner_lost_s: float = 1.0
    sensor_lost_s: float = 1.0
    state_timeout_s: float = 0.2
    max_target_lead_s: float = 1.0
    max_plan_age_s: float = 2.0
    max_tilt_deg: float = 30.0
    yaw_range_deg: tuple[float, float] = (-180.0, 180.0)

    def __post_init__(self) -> None:
        _positive(self, "limits", "max_speed_m_s", "max_angular_speed_rad_s", "max_force_n", "servo_rate_hz",
                  "idle_rate_hz", "heartbeat_timeout_s", "planner_lost_s", "sensor_lost_s", "state_timeout_s",
                  "max_target_lead_s", "max_plan_age_s", "max_tilt_deg")
        for name, bound in LIMIT_BOUNDS.items():
            if name != "max_yaw_deg":
                _require(getattr(self, name) <= bound, f"limits.{name}",
                         f"must be at most {bound} (LIMIT_BOUNDS gives the reason), got {getattr(self, name)}")
        _require(self.release_force_n is None or 0 <= self.release_force_n < self.max_force_n,
                 "limits.release_force_n",
                 f"must be >= 0 and below max_force_n ({self.max_force_n} N), got {self.release_force_n}")
        _require(self.planner_lost_s >= self.heartbeat_timeout_s, "limits.planner_lost_s",
                 f"must be at least heartbeat_timeout_s ({self.heartbeat_timeout_s} s), got {self.planner_lost_s}")
        _require(self.idle_rate_hz <= self.servo_rate_hz, "limits.idle_rate_hz",
                 f"must be at most servo_rate_hz ({self.servo_rate_hz} Hz), got {self.idle_rate_hz}")
        _require(all(math.isfinite(v) for v in (*self.workspace_min, *self.workspace_max)), "limits.workspace_min",
                 f"must be finite, got {self.workspace_min} and {self.workspace_max}")
        _require(all(lo < hi for lo, hi in zip(self.workspace_min, self.workspace_max)), "limits.workspace_min",
                 f"must be below workspace_max on every axis, got {self.workspace_min} and {self.workspace_max}")
        _require(all(hi - lo <= MAX_WORKSPACE_EDGE_M for lo, hi in zip(self.workspace_min, self.workspace_max)),
                 "limits.workspace_max", f"every edge of the box must be at most {MAX_WORKSPACE_EDGE_M} m (a UR5e's "
                 f"reach), got {self.workspace_min} .. {self.workspace_max}")
        low, high = self.yaw_range_deg
        bound = LIMIT_BOUNDS["max_yaw_deg"]
        _require(-bound <= low < high <= bound, "limits.yaw_range_deg",
                 f"must be [low, high] with -{bound} <= low < high <= {bound} deg, got {self.yaw_range_deg}")

    @property
    def release_level_n(self) -> float:
        """The force (N) below which normal servoing resumes after ``max_force_n`` was exceeded:
        ``release_force_n``, or three quarters of ``max_force_n`` when it is not set."""
        return 0.75 * self.max_force_n if self.release_force_n is None else self.release_force_n


#: Named planner settings (``planner.preset``): a ``[planner]`` table with ``preset = NAME`` starts from these values
#: and its own keys override them. ``paper``: the paper's planner (B = 64, K = 10, G = 2, 216 surface points),
#: float32, compiled (ready after minutes with a cold compile cache), its samples rolled out by two worker processes;
#: its targets live at least 0.3 s and longer as its measured cycle asks (``planner.target_lead``); one chunk of
#: samples per worker (``chunks = 0``: 4 chunks of 16 took 79 against 56 ms a solve alone, docs/benchmarks.md).
#: ``quick``: B = 16, K = 6, G = 1, 96 points, eager, one process: ready in seconds, replans at a few Hz on 2 cores.
PLANNER_PRESETS: dict[str, dict[str, object]] = {
    "paper": {"model": "nh", "spacing": 0.0084, "samples": 64, "elites": 8, "horizon": 10, "grad_steps": 2,
              "dtype": "float32", "sdf_solver_steps": 2, "compile": True, "object_update": "linearly_implicit",
              "threads": 1, "workers": 2, "chunks": 0, "worker_processes": True, "target_lead_s": 0.3, "nice": 10},
    "quick": {"model": "nh", "spacing": 0.0125, "samples": 16, "elites": 4, "horizon": 6, "grad_steps": 1,
              "dtype": "float32", "sdf_solver_steps": 3, "compile": False, "object_update": "linearly_implicit",
              "threads": 1, "workers": 1, "worker_processes": False, "target_lead_s": 1.0, "nice": 0},
}


def with_planner_preset(raw: object) -> object:
    """A decoded config document ``raw`` with its ``[planner]`` table filled in from ``planner.preset``
    (``PLANNER_PRESETS``): the table's own keys win. Raises ConfigError for an unknown preset."""
    planner = raw.get("planner") if isinstance(raw, dict) else None
    if not isinstance(planner, dict) or "preset" not in planner:
        return raw
    name = planner["preset"]
    _require(isinstance(name, str) and name in PLANNER_PRESETS, "planner.preset",
             f"must be one of {', '.join(sorted(PLANNER_PRESETS))}, got {name!r}")
    return {**raw, "planner": {**PLANNER_PRESETS[name], **planner}}


class PlannerConfig(Strict):
    """The MPC (``hydrosoft.tasks.evaluation.PlannerSettings`` names): contact model, surface spacing (m), samples
    B, elites, horizon K, gradient steps G, dtype, compile (compile the step during start-up), seed.
    sdf_solver_steps: None solves the bubble ellipsoid's closest point to convergence; an integer runs that many
    fixed solver steps (``hydrosoft.geometry.sdf.Ellipsoid.solver_steps``; 3 is within 1e-7 m of the converged
    distance up to 2 cm from the membrane, deeper than any press of the stack's tasks). Fixed steps make the
    compiled step loop-free, so torch's compile cache can keep it between launches (a ``torch.while_loop`` cannot
    be cached) and the solve is faster.
    max_age_s: per input topic kind, the oldest sample the planner acts on (s). heartbeat_period_s: its heartbeat
    period (must be under half the commander's heartbeat_timeout_s). target_lead_s: how long each target stays
    valid (its deadline). threads: torch intra-op threads of the solve (1 by default: with the other services on
    a small machine, two threads that wait for each other at every kernel's barrier were several times slower
    than one under load; raise it on a machine with cores to spare). workers: solver threads that each roll out a
    share of the samples (``CemGdConfig.workers``; 1 by default), at most ``samples``: on a machine with a core per
    worker to spare, two workers with one torch thread each beat one solve on two threads (``hydrosoft-stack bench
    control --rate-workers 1,2 --threads 1`` measures it). worker_processes: the ``workers`` shares in processes of
    their own instead of threads (``hydrosoft.control.WorkerProcesses``; 0.86 of the threads' cycle in the
    benchmark, ``--rate-worker-kinds``), each with its own copy of the model and step: for a machine with a core per
    worker to spare. chunks: with two workers or more, the samples are cut into this many equal chunks, and each
    worker takes the next chunk as it finishes one (``CemGdConfig.chunks``), so that a worker the machine delays
    takes fewer of them instead of holding up the solve with a fixed half; 0 (the default): one chunk per worker;
    else from ``workers`` to ``samples`` (``hydrosoft-stack bench control --rate-chunks`` measures it; a smaller
    chunk costs the compiled step's fixed time per call more often). object_update: the planner model's object update
    (``hydrosoft.dynamics.Model.object_update``): ``explicit``, sub-stepped as the scene's contacts need, or
    ``linearly_implicit``, one sub-step per control step (NH and SNH planners; ``hydrosoft-stack bench control
    --rate-object-updates`` measures the rate of each). max_reapproaches: how often one goal may bring
    the bubble back onto an object it lost (``services/arm/reapproach.py``; one-arm scenes) before it fails; 0: a lost
    object fails the goal at once. stall_s: a goal whose ADD error has made no progress (fallen 0.5 mm) for this long
    while the planner plans ends ``failed`` with the reason (``services/arm/progress.py``), instead of pressing on
    until its timeout. preset: the named settings (``PLANNER_PRESETS``) the config file's table
    started from (``with_planner_preset``, applied on load), or None. target_lead_s is the shortest lead: the
    planner lengthens it to twice its recent p90 cycle plus a margin, within ``limits.max_target_lead_s``. nice:
    the scheduling niceness, 0-19 (``os.nice``), of the planner's computing (its build, compile and solve threads and
    its worker processes; its event loop keeps its own): on cores it shares with the arm commander and the sensor
    services, a positive one lets them run first whenever they are ready, so a solve or a compile never starves the
    commander's servo loop or the controller link (and so do other programs at a lower niceness: each worker process
    is a program of its own to the scheduler, its session's group set to this niceness). device: where the
    planner's model, solver and worker processes compute, ``cpu`` (the default), ``cuda`` or ``cuda:N`` (a torch
    device); a planner whose GPU is not available says so in its status and plans nothing (no fallback to the CPU)."""

    preset: Literal["paper", "quick"] | None = None

    model: Literal["nh", "snh", "pf", "pff", "nh_pressure_normal"] = "nh"
    spacing: float = 0.0125
    samples: int = 16
    elites: int = 4
    horizon: int = 6
    grad_steps: int = 1
    dtype: Literal["float32", "float64"] = "float32"
    compile: bool = False
    seed: int = 0
    sdf_solver_steps: int | None = None
    max_age_s: dict[str, float] = msgspec.field(
        default_factory=lambda: {"object_pose": 0.5, "arm_state": 0.2, "deformation": 0.5})
    heartbeat_period_s: float = 0.1
    target_lead_s: float = 0.5
    threads: int = 1
    workers: int = 1
    chunks: int = 0
    object_update: Literal["explicit", "linearly_implicit"] = "explicit"
    max_reapproaches: int = 3
    stall_s: float = 10.0
    worker_processes: bool = False
    nice: int = 0
    device: str = "cpu"

    def __post_init__(self) -> None:
        _require(PLANNER_DEVICE.fullmatch(self.device) is not None, "planner.device",
                 f"must be cpu, cuda or cuda:N (N a GPU index), got {self.device!r}")
        _require(self.max_reapproaches >= 0, "planner.max_reapproaches",
                 f"must be >= 0, got {self.max_reapproaches}")
        _require(self.sdf_solver_steps is None or 0 <= self.sdf_solver_steps <= SDF_SOLVER_STEPS_MAX,
                 "planner.sdf_solver_steps", f"must be 0..{SDF_SOLVER_STEPS_MAX} (or left out: solve to "
                 f"convergence), got {self.sdf_solver_steps}")
        _require(0 <= self.nice <= 19, "planner.nice", f"must be 0..19, got {self.nice}")
        _positive(self, "planner", "spacing", "samples", "elites", "horizon", "heartbeat_period_s", "target_lead_s",
                  "threads", "workers", "stall_s")
        _require(self.workers <= self.samples, "planner.workers",
                 f"must be at most planner.samples ({self.samples}): each worker rolls out a share of them, got "
                 f"{self.workers}")
        _require(self.chunks == 0 or self.workers <= self.chunks <= self.samples, "planner.chunks",
                 f"must be 0 (one per worker) or from planner.workers ({self.workers}) to planner.samples "
                 f"({self.samples}), got {self.chunks}")
        for key, value in self.max_age_s.items():
            _require(value > 0, f"planner.max_age_s.{key}", f"must be > 0 s, got {value}")
        _require(self.object_update == "explicit" or self.model in ("nh", "snh", "nh_pressure_normal"),
                 "planner.object_update",
                 f"linearly_implicit needs an NH, SNH or nh_pressure_normal planner (planner.model), "
                 f"got {self.model!r}")


MAX_SIM_FT_BIAS_N = 100.0
"""The largest simulated F/T offset force, N: a third of the FT 300's +-300 N range, above any real mounting offset."""
MAX_SIM_FT_BIAS_NM = 10.0
"""The largest simulated F/T offset torque, N m (the FT 300's range is +-30 N m)."""
MAX_SIM_FT_NOISE = 10.0
"""The largest simulated F/T noise, as a multiple of the datasheet's: 1 N per frame."""


class SimConfig(Strict):
    """sim_world: physics rate (Hz of simulated time, run in real time), the plant's spacing relative to the
    planner's, camera noise (grey levels) and blur (px), depth noise (m). compile: run the plant's step compiled
    (``hydrosoft.dynamics.CompiledStep``): a tick (step and snapshot) takes a sixth of the eager
    one's CPU (1.4 against 9.2 ms, one thread, deploy/sim.toml's pushing plant: ``hydrosoft-stack bench plant``)
    for compiling before READY: minutes when its artefact is missing or stale, loaded from the compile cache after
    that (``services/bus/artefacts.py``; loop-free only with ``sdf_solver_steps``). On a small machine the
    eager plant, sharing two cores with the planner's solves, falls behind real time while the simulated arm does
    not, and the cube then lags the bubble. ur_tick_hz: the simulated UR controllers' cycle, which also caps their
    RTDE streams: a CB3's 125 Hz by default, not an e-Series' 500 Hz, as the commander servoes and reads at 125 Hz
    and each extra cycle is a Python loop turn in sim_world (at least ``limits.servo_rate_hz``). object_offset_m:
    the object starts this far (m, task frame x and y) from the scene's pose, under no bubble when it is far enough:
    a lost object for the planner to re-approach (``services/arm/reapproach.py``). ft_bias: the simulated FT 300's
    zero-load reading ``[Fx, Fy, Fz, Mx, My, Mz]`` (N, N m), which it adds to every frame as a real sensor's offset;
    sim_world stores it as the arm's tare (``services/arm/ft_bias.py``) at its start, a tare taken before the membrane
    touched anything. ft_noise: the simulated FT 300's signal noise per frame, as a multiple of the datasheet's
    (``hydrosoft.drivers.robotiq_ft300.noise``: 0.1 N, 0.005 N m for Mx and My, 0.003 N m for Mz at 1), drawn per
    frame from a generator seeded per arm; 0 (the default; deploy/sim.toml sets 1) turns it off. sdf_solver_steps: the plant's bubble closest points, as ``planner.sdf_solver_steps`` (None:
    solved to convergence, a ``torch.while_loop`` that torch's compile cache cannot keep, so a compiled plant
    compiles at every launch; 3 fixed steps: within 1e-7 m up to 2 cm deep, kept by the cache)."""

    rate_hz: float = 50.0
    ur_tick_hz: float = 125.0
    spacing_factor: float = 0.5
    compile: bool = False
    image_noise: float = 2.0
    image_blur_px: float = 0.6
    depth_noise_m: float = 0.0002
    object_offset_m: tuple[float, float] = (0.0, 0.0)
    sdf_solver_steps: int | None = None
    ft_bias: tuple[float, float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    ft_noise: float = 0.0

    def __post_init__(self) -> None:
        _require(self.sdf_solver_steps is None or 0 <= self.sdf_solver_steps <= SDF_SOLVER_STEPS_MAX,
                 "sim.sdf_solver_steps", f"must be 0..{SDF_SOLVER_STEPS_MAX} (or left out: solve to convergence), "
                 f"got {self.sdf_solver_steps}")
        _positive(self, "sim", "rate_hz", "spacing_factor", "ur_tick_hz")
        _require(all(math.isfinite(v) for v in self.ft_bias)
                 and max(abs(v) for v in self.ft_bias[:3]) <= MAX_SIM_FT_BIAS_N
                 and max(abs(v) for v in self.ft_bias[3:]) <= MAX_SIM_FT_BIAS_NM, "sim.ft_bias",
                 f"must be 6 finite numbers, forces within {MAX_SIM_FT_BIAS_N} N and torques within "
                 f"{MAX_SIM_FT_BIAS_NM} N m, got {list(self.ft_bias)}")
        _require(math.isfinite(self.ft_noise) and 0 <= self.ft_noise <= MAX_SIM_FT_NOISE, "sim.ft_noise",
                 f"must be a number from 0 (no noise) to {MAX_SIM_FT_NOISE} times the datasheet's, got {self.ft_noise}")
        _require(all(math.isfinite(v) and abs(v) <= 0.5 for v in self.object_offset_m), "sim.object_offset_m",
                 f"must be two finite numbers within 0.5 m, got {list(self.object_offset_m)}")
        _require(self.rate_hz >= 50.0, "sim.rate_hz", f"must be at least 50 Hz, got {self.rate_hz}")


class ServiceConfig(Strict):
    """Per service: restart policy (never, on-failure, always), most restarts, first backoff (s, doubling), and
    how long the launcher waits for READY (s)."""

    restart: RestartPolicy = "on-failure"
    max_restarts: int = 5
    backoff_s: float = 0.5
    ready_timeout_s: float = 120.0

    def __post_init__(self) -> None:
        _positive(self, "services", "backoff_s", "ready_timeout_s")
        _require(self.max_restarts >= 0, "services.max_restarts", f"must be >= 0, got {self.max_restarts}")


class CurveConfig(Strict):
    """CURVE keys (pyzmq zmq.auth certificate files, ``hydrosoft-stack keys generate``): this host's secret key
    file (mode 0600) and the folder of the authorised peers' public keys. Every ``tcp://`` endpoint beyond
    loopback uses them; ``loopback``: also every ``tcp://127.x`` one, so that a test on one machine runs the
    secure path (``ipc://`` never: it does not leave the host)."""

    secret_key_file: str
    authorized_keys_dir: str
    loopback: bool = False


class HostConfig(Strict):
    """One host of a stack split across hosts. address: the IP address its peers reach it at (its tcp endpoints
    bind there). services: the services it runs (each service on exactly one host). first_port: the first of its
    tcp ports (three per service of the stack, see the module docstring). public_key_file: its CURVE public key
    (``NAME.key`` of ``hydrosoft-stack keys generate``), with which clients on other hosts authenticate its
    servers; empty: the key of ``curve.secret_key_file`` (one key pair for all hosts). secret_key_file: its own
    secret key, used in place of ``curve.secret_key_file`` by the processes on it; empty: that one. run_dir: its
    own run_dir (two hosts simulated on one machine need two); None: the stack's."""

    address: str
    services: list[str]
    first_port: int = 5600
    public_key_file: str = ""
    secret_key_file: str = ""
    run_dir: str | None = None


class StackConfig(Strict):
    """The whole stack (see the module docstring)."""

    arms: list[ArmConfig]
    run_dir: str = "/tmp/hydrosoft"
    log_level: str = "INFO"
    log_dir: str | None = None
    compile_cache_dir: str | None = None
    state_dir: str = "state"
    mode: Literal["sim", "lab"] = "sim"
    scene: SceneConfig = SceneConfig()
    camera: CameraConfig = CameraConfig()
    limits: LimitsConfig = LimitsConfig()
    planner: PlannerConfig = PlannerConfig()
    sim: SimConfig = SimConfig()
    services: dict[str, ServiceConfig] = {}
    endpoints: dict[str, str] = {}
    curve: CurveConfig | None = None
    hosts: dict[str, HostConfig] = {}
    host: str | None = None

    def __post_init__(self) -> None:
        _require(len(self.arms) >= 1, "arms", "the stack needs at least one arm")
        names = [arm.name for arm in self.arms]
        _require(len(set(names)) == len(names), "arms", f"arm names must be unique, got {names}")
        _require(self.sim.ur_tick_hz >= self.limits.servo_rate_hz, "sim.ur_tick_hz",
                 f"must be at least limits.servo_rate_hz ({self.limits.servo_rate_hz} Hz), or servo commands would "
                 f"be skipped; got {self.sim.ur_tick_hz}")
        _require(2 * self.planner.heartbeat_period_s < self.limits.heartbeat_timeout_s, "planner.heartbeat_period_s",
                 f"must be under half of limits.heartbeat_timeout_s ({self.limits.heartbeat_timeout_s} s)")
        for name in self.services:
            _require(name in self.service_names(), f"services.{name}",
                     f"no such service; the services are {', '.join(self.service_names())}")
        for key, endpoint in self.endpoints.items():
            service, _, kind = key.rpartition(".")
            _require(service in self.service_names() and kind in ENDPOINT_KINDS, f"endpoints.{key}",
                     "keys are SERVICE.data, SERVICE.status or SERVICE.cmd")
            try:
                check_endpoint(endpoint, self.curve_server())
            except Exception as err:  # noqa: BLE001 - re-raised with the key named
                raise ConfigError(f"endpoints.{key}: {err}") from err
        self._check_hosts()

    def _check_hosts(self) -> None:
        """Every service on exactly one host, addresses that are IP literals, ports in range, ``host`` known."""
        _require(self.host is None or self.host in self.hosts, "host",
                 f"must be one of the [hosts] tables ({', '.join(self.hosts) or 'none'}), got {self.host!r}")
        if not self.hosts:
            return
        placed: dict[str, str] = {}
        for name, host in self.hosts.items():
            try:
                ipaddress.ip_address(host.address)
            except ValueError:
                raise ConfigError(f"hosts.{name}.address: must be an IP address, got {host.address!r}") from None
            last_port = host.first_port + len(ENDPOINT_KINDS) * len(self.service_names()) - 1
            _require(1024 <= host.first_port and last_port <= 65535, f"hosts.{name}.first_port",
                     f"its ports {host.first_port}..{last_port} must lie in 1024..65535")
            for service in host.services:
                _require(service in self.service_names(), f"hosts.{name}.services",
                         f"no service {service!r}; the services are {', '.join(self.service_names())}")
                _require(service not in placed, f"hosts.{name}.services",
                         f"{service} is also on host {placed.get(service)!r}: each service runs on one host")
                placed[service] = name
        missing = [service for service in self.service_names() if service not in placed]
        _require(not missing, "hosts", f"these services are on no host: {', '.join(missing)}")
        for service in self.service_names():
            for kind in ENDPOINT_KINDS:
                try:
                    check_endpoint(self.tcp_endpoint(service, kind), self.curve_server())
                except Exception as err:  # noqa: BLE001 - re-raised with the key named
                    raise ConfigError(f"hosts.{placed[service]}: {err}") from err

    def service_names(self) -> list[str]:
        """Every service of this stack, in start order (sim_world first, the planner last)."""
        names = ["sim_world"] if self.mode == "sim" else []
        for arm in self.arms:
            names += [f"arm_commander-{arm.name}", f"ft_reader-{arm.name}", f"bubble_camera-{arm.name}"]
        return names + ["tag_tracker", "planner"]

    def service(self, name: str) -> ServiceConfig:
        """The launcher settings of service ``name`` (defaults when its table is absent)."""
        return self.services.get(name, ServiceConfig())

    def arm(self, name: str) -> ArmConfig:
        """The arm carrying scene body ``name``."""
        for arm in self.arms:
            if arm.name == name:
                return arm
        raise ConfigError(f"arms: no arm named {name!r}; the arms are {[a.name for a in self.arms]}")

    def bubble_materials(self) -> dict[str, dict[str, float]]:
        """Per arm with an ``[arms.material]`` table, its bubble body's name and the material values it gives
        (``with_body_materials`` takes this)."""
        return {arm.name: arm.material.values() for arm in self.arms if arm.material is not None}

    def arm_service(self, module: str, name: str | None) -> tuple[str, str]:
        """``(service name, arm)`` of a per-arm service ``module`` run as ``name`` (``MODULE-ARM``; None: the
        first arm's). Raises ConfigError for another name or an unknown arm."""
        name = name or f"{module}-{self.arms[0].name}"
        prefix, _, arm = name.partition("-")
        if prefix != module or not arm:
            raise ConfigError(f"--name {name!r}: expected {module}-ARM, e.g. {module}-{self.arms[0].name}")
        self.arm(arm)
        return name, arm

    def endpoint(self, service: str, kind: str = "data") -> str:
        """Where this process reaches (or, for its own service, binds) ``service``'s ``kind`` socket (data,
        status or cmd): the ``[endpoints]`` override; else, for a service of another host (or of any host when
        this process names none), its tcp endpoint; else ipc in ``run_dir``."""
        override = self.endpoints.get(f"{service}.{kind}")
        if override is not None:
            return override
        if self.hosts and self.host_of(service) != self.host:
            return self.tcp_endpoint(service, kind)
        return f"ipc://{self.run_dir}/{service}.{kind}"

    def host_of(self, service: str) -> str | None:
        """The host that runs ``service``, or None for a stack on one host."""
        return next((name for name, host in self.hosts.items() if service in host.services), None)

    def tcp_endpoint(self, service: str, kind: str) -> str:
        """``tcp://ADDRESS:PORT`` of ``service``'s ``kind`` socket on its host (see the module docstring)."""
        host = self.hosts[self.host_of(service)]
        port = host.first_port + len(ENDPOINT_KINDS) * self.service_names().index(service) + ENDPOINT_KINDS.index(kind)
        return f"tcp://{host.address}:{port}"

    def on_host(self, host: str | None) -> StackConfig:
        """This config as read on ``host`` (None: unchanged): ``host`` set, and that host's ``run_dir`` and secret
        key file where it names its own. Raises ConfigError for a host the config does not name."""
        if host is None:
            return self
        _require(host in self.hosts, "--host", f"no host {host!r}; the config's hosts are "
                                               f"{', '.join(self.hosts) or 'none (no [hosts] tables)'}")
        own = self.hosts[host]
        curve = self.curve
        if curve is not None and own.secret_key_file:
            curve = msgspec.structs.replace(curve, secret_key_file=own.secret_key_file)
        return msgspec.structs.replace(self, host=host, run_dir=own.run_dir or self.run_dir, curve=curve)

    def local_services(self) -> list[str]:
        """The services this process's host runs, in start order (all of them on a stack without hosts)."""
        if self.host is None:
            return self.service_names()
        return [name for name in self.service_names() if self.host_of(name) == self.host]

    def local_sources(self) -> frozenset[str] | None:
        """The services that stamp with this process's clock (``Bus.local_sources``): None on a stack on one
        host (all of them), this host's services on a split stack, none where this process names no host."""
        if not self.hosts:
            return None
        return frozenset(self.local_services()) if self.host is not None else frozenset()

    def runtime(self, service: str) -> RuntimeConfig:
        """The runtime settings of ``service`` (the planner's heartbeat at ``planner.heartbeat_period_s``, its log
        file in ``service_log_dir``, its CURVE keys, and on a split stack its tcp endpoints bound beside the ipc
        ones and the services of its host, whose stamps share its clock)."""
        heartbeat = {"heartbeat_period_s": self.planner.heartbeat_period_s} if service == "planner" else {}
        also_bind = {} if not self.hosts or service not in self.service_names() else {
            f"ipc://{self.run_dir}/{service}.{kind}": self.tcp_endpoint(service, kind) for kind in ENDPOINT_KINDS}
        return RuntimeConfig(status_endpoint=self.endpoint(service, "status"), log_level=self.log_level,
                             log_file=str(self.service_log_dir() / f"{service}.log"), curve=self.curve_keys(),
                             also_bind=also_bind, local_sources=self.local_sources(), **heartbeat)

    def service_log_dir(self) -> Path:
        """Where each service writes its own log file ``NAME.log``: ``log_dir``, or ``RUN_DIR/logs``."""
        return Path(self.log_dir).expanduser() if self.log_dir is not None else Path(self.run_dir) / "logs"

    def state_path(self) -> Path:
        """The folder of what the stack keeps between launches (``state_dir``; a relative one lies under
        ``run_dir``). Keep it off a folder that a restart empties (the lab's ``/run``): a lost tare leaves the F/T
        readings untared until a person tares again."""
        return Path(self.run_dir) / Path(self.state_dir).expanduser()

    def curve_keys(self) -> CurveKeys | None:
        """The CURVE keys every process of this stack gives its bus (``Bus(curve=...)``), or None."""
        if self.curve is None:
            return None
        server_keys = {self.tcp_endpoint(service, kind): Path(host.public_key_file)
                       for host in self.hosts.values() if host.public_key_file
                       for service in host.services for kind in ENDPOINT_KINDS}
        return CurveKeys(Path(self.curve.secret_key_file), Path(self.curve.authorized_keys_dir), server_keys,
                         loopback=self.curve.loopback)

    def curve_server(self) -> CurveServer | None:
        """The CURVE server keys, or None."""
        if self.curve is None:
            return None
        return CurveServer(Path(self.curve.secret_key_file), Path(self.curve.authorized_keys_dir))


def parse_config(text: str | bytes, origin: str = "config") -> StackConfig:
    """Validate a stack config from TOML text (its planner preset applied: ``with_planner_preset``); raises
    ConfigError naming ``origin`` and the key."""
    try:
        return msgspec.convert(with_planner_preset(msgspec.toml.decode(text)), StackConfig)
    except ConfigError as err:
        raise ConfigError(f"{origin}: {err}") from err
    except msgspec.ValidationError as err:
        raise ConfigError(f"{origin}: {err}") from err
    except msgspec.DecodeError as err:
        raise ConfigError(f"{origin} is not valid TOML: {err}") from err


def load_config(path: str | Path, host: str | None = None) -> StackConfig:
    """Read and validate a stack config file as read on ``host`` (default ``$HYDROSOFT_HOST``, else the
    config's ``host``; ``StackConfig.on_host``); raises ConfigError naming the file and the key."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file {path} does not exist")
    config = parse_config(path.read_bytes(), origin=str(path))
    try:
        return config.on_host(host or os.environ.get(HOST_ENV) or None)
    except ConfigError as err:
        raise ConfigError(f"{path}: {err}") from err
