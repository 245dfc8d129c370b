"""Every message on the bus: one frozen ``msgspec.Struct`` per kind, its wire frames and its validation.

Wire format (one ZeroMQ multipart message)::

    [topic, header, array_0, array_1, ...]

- ``topic``: UTF-8, the kind's ``topic`` optionally followed by ``/instance`` (``"depth/left"``,
  ``"status/planner"``). Subscribers filter on it; the decoder picks the kind from its longest registered prefix.
- ``header``: the struct as msgpack. Each numpy array field is replaced by an ``ArrayMeta(dtype, shape)``.
- ``array_i``: the raw C-ordered bytes of each array field, in the order their ``ArrayMeta`` appear in the header.
  Sending hands the array's own buffer to ZeroMQ (no copy); receiving wraps the frame with ``np.frombuffer``
  (no copy), so **arrays of a received message are read-only views** and an array must not be modified after it
  was sent.

Every message carries a header: ``seq`` (per publisher and topic, from 1), ``stamp_ns`` (``time.monotonic_ns()``
when published; the stack runs on one host, so all processes share that clock), ``source`` (the publishing
service's name) and, for sensor data, ``hw_stamp_ns`` (the device's own clock in ns, or ``None``). The publisher
fills ``seq``, ``stamp_ns`` and ``source``; leave them at their defaults when building a message.

Conventions: poses are ``(7,)`` float64 ``[x, y, z, qw, qx, qy, qz]`` (m, unit quaternion) in the frame the field
names; wrenches ``(6,)`` float64 ``[Fx, Fy, Fz, Mx, My, Mz]`` (N, N m). Every kind declares, per array field, the
dtypes and the shape it accepts (``ARRAYS``); ``encode`` and ``decode`` both enforce them, and reject NaN or Inf
in any float scalar and in every array declared ``finite``, and non-unit quaternions in pose arrays. Each problem
raises its own ``MessageError`` subclass, whose ``kind`` names it for error counters.
"""

from __future__ import annotations

import functools
import math
import typing
from collections.abc import Iterator, Mapping, Sequence
from typing import Annotated, Any, ClassVar, Literal, NamedTuple

import msgspec
import numpy as np

#: Largest frame accepted or sent, bytes: a 2048 x 2048 float32 image (the largest image any kind allows). It
#: also caps arrays whose dimension limits alone would allow more (a plan's forces for 16 bodies x 65536 points).
MAX_FRAME_BYTES = 2048 * 2048 * 4
#: Largest msgpack header, bytes (headers carry no bulk data; a status with many topics is a few kB).
MAX_HEADER_BYTES = 64 * 1024
#: Largest topic frame, bytes.
MAX_TOPIC_BYTES = 256
#: Longest task name and instance id a Goal may carry, characters (task names are a few words, ids 32 hex digits).
MAX_TASK_CHARS = 64
#: A quaternion is a unit quaternion when ``| ||q|| - 1 | <= QUATERNION_NORM_TOLERANCE`` (float32 rounding of a
#: normalised quaternion stays below 1e-6).
QUATERNION_NORM_TOLERANCE = 1e-5
#: Longest side of any image, px.
MAX_IMAGE_SIDE_PX = 2048
#: Most AprilTags in one detection message.
MAX_TAGS = 64
#: Most planning steps, compliant bodies and object surface points in a plan or a truth message.
MAX_HORIZON = 512
MAX_BODIES = 16
MAX_POINTS = 65536

# Dtypes an array frame may declare at all (little-endian numeric); each field narrows this further.
_WIRE_DTYPES = frozenset(
    np.dtype(name)
    for name in ("bool", "int8", "int16", "int32", "int64", "uint8", "uint16", "uint32", "uint64",
                 "float16", "float32", "float64")
)


class BusError(Exception):
    """Root of every failure of the bus layer (messages, sockets, staleness)."""


class MessageError(BusError):
    """A message that cannot be accepted. ``kind`` is the short name error counters use."""

    kind: ClassVar[str] = "message"


class UnknownTopic(MessageError):
    """The topic frame names no registered message kind, or a kind was sent on another kind's topic."""

    kind = "unknown_topic"


class FrameCountError(MessageError):
    """The multipart message has fewer frames than a header needs, or not one frame per array."""

    kind = "frame_count"


class GarbageBytes(MessageError):
    """The header frame is not msgpack (or the topic is not UTF-8)."""

    kind = "garbage"


class SchemaError(MessageError):
    """The header is msgpack but not the kind's schema: missing, unknown or mistyped fields."""

    kind = "schema"


class DtypeError(MessageError):
    """An array's dtype is not one its field accepts."""

    kind = "dtype"


class ShapeError(MessageError):
    """An array's shape breaks its field's rule (fixed sizes, maxima, sizes shared between fields)."""

    kind = "shape"


class LengthMismatch(MessageError):
    """An array frame's byte length differs from ``prod(shape) * itemsize`` of its ``ArrayMeta``."""

    kind = "length"


class OversizedFrame(MessageError):
    """A frame is larger than its limit (``MAX_TOPIC_BYTES``, ``MAX_HEADER_BYTES``, ``MAX_FRAME_BYTES``)."""

    kind = "oversized"


class NonFinite(MessageError):
    """A float scalar, or an array declared finite, holds NaN or Inf."""

    kind = "non_finite"


class NonUnitQuaternion(MessageError):
    """A pose's quaternion ``[qw, qx, qy, qz]`` is not unit length within ``QUATERNION_NORM_TOLERANCE``."""

    kind = "quaternion"


class OutOfRange(MessageError):
    """A scalar lies outside its documented range (a non-positive scale, focal length or timeout, ...)."""

    kind = "range"


class Dim(NamedTuple):
    """A named array dimension: every field of one message using ``name`` must have the same size, at most
    ``max``."""

    name: str
    max: int


class ArraySpec(NamedTuple):
    """What one array field accepts.

    dtypes: numpy dtype names (``"float64"``); shape: per axis a fixed size or a ``Dim``; finite: reject NaN/Inf;
    unit_quaternion: the last axis is a pose ``[x, y, z, qw, qx, qy, qz]`` whose quaternion must be unit length;
    optional: the field may be ``None``.
    """

    dtypes: tuple[str, ...]
    shape: tuple[int | Dim, ...]
    finite: bool = True
    unit_quaternion: bool = False
    optional: bool = False


class ArrayMeta(msgspec.Struct, frozen=True, array_like=True, forbid_unknown_fields=True):
    """How an array travels in the header: numpy dtype string (``"<u2"``) and shape; its bytes are a frame."""

    dtype: str
    shape: tuple[Annotated[int, msgspec.Meta(ge=0)], ...]


_F64 = ("float64",)
_FLOAT = ("float32", "float64")
_IMAGE = (Dim("H", MAX_IMAGE_SIDE_PX), Dim("W", MAX_IMAGE_SIDE_PX))
POSE = ArraySpec(_F64, (7,), unit_quaternion=True)
"""A pose ``(7,)`` float64 ``[x, y, z, qw, qx, qy, qz]``, m and unit quaternion."""
TWIST = ArraySpec(_F64, (6,))
"""A velocity ``(6,)`` float64 ``[vx, vy, vz, wx, wy, wz]``, m/s and rad/s."""
WRENCH = ArraySpec(_F64, (6,))
"""A wrench ``(6,)`` float64 ``[Fx, Fy, Fz, Mx, My, Mz]``, N and N m."""


class Payload(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Base of every struct on the wire. ``ARRAYS`` maps each numpy array field to its ``ArraySpec``;
    ``check`` tests relations and ranges beyond types and raises a ``MessageError``."""

    ARRAYS: ClassVar[Mapping[str, ArraySpec]] = {}

    def check(self) -> None:
        """Raise a ``MessageError`` when a value is out of its range; the default accepts everything."""


class Message(Payload, frozen=True, kw_only=True):
    """A message with its header. ``topic`` is the kind's topic (see the module docstring).

    seq: number of this message on its topic from its publisher, from 1. stamp_ns: ``time.monotonic_ns()`` at
    publish. source: name of the publishing service.
    """

    topic: ClassVar[str]

    seq: int = 0
    stamp_ns: int = 0
    source: str = ""


class SensorMessage(Message, frozen=True, kw_only=True):
    """A message carrying a device reading. hw_stamp_ns: the device's own stamp in ns (its clock, not the host's),
    or None when the device has none."""

    hw_stamp_ns: int | None = None


def _positive(owner: Payload, **values: float) -> None:
    for name, value in values.items():
        if not value > 0:
            raise OutOfRange(f"{type(owner).__name__}.{name} must be > 0, got {value!r}")


# --- sensor streams ----------------------------------------------------------------------------------------------


class DepthFrame(SensorMessage, frozen=True, kw_only=True):
    """A Soft Bubble's raw depth image. depth: ``(H, W)`` uint16, H, W <= 2048; metres = value x ``depth_scale_m``,
    0 = no return. fx_px, fy_px, cx_px, cy_px: pinhole intrinsics of the depth camera, px."""

    topic = "depth"
    ARRAYS = {"depth": ArraySpec(("uint16",), _IMAGE, finite=False)}

    bubble: str
    depth: np.ndarray
    depth_scale_m: float
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float

    def check(self) -> None:
        _positive(self, depth_scale_m=self.depth_scale_m, fx_px=self.fx_px, fy_px=self.fy_px)


class CameraImage(SensorMessage, frozen=True, kw_only=True):
    """One image of an RGB camera (sim_world's rendered tag camera, or a real one). camera: the camera's name.
    image: ``(H, W, C)`` uint8, H, W <= 2048: ``C = 3`` BGR, or ``C = 1`` grey (an ``(H, W)`` grey image travels
    with one channel: build it with ``of``). hw_stamp_ns: the image's exposure time."""

    topic = "image"
    ARRAYS = {"image": ArraySpec(("uint8",), (*_IMAGE, Dim("C", 3)), finite=False)}

    camera: str
    image: np.ndarray

    @classmethod
    def of(cls, camera: str, image: np.ndarray, hw_stamp_ns: int | None = None) -> CameraImage:
        """The message of ``image`` ``(H, W, 3)`` BGR or ``(H, W)`` grey (given one channel axis, no copy)."""
        return cls(camera=camera, image=image[..., np.newaxis] if image.ndim == 2 else image, hw_stamp_ns=hw_stamp_ns)

    @property
    def frame(self) -> np.ndarray:
        """The image as cameras give it: ``(H, W, 3)`` BGR or ``(H, W)`` grey (a view)."""
        return self.image[..., 0] if self.image.shape[2] == 1 else self.image

    def check(self) -> None:
        if self.image.shape[2] not in (1, 3):
            raise ShapeError(f"CameraImage.image must have 1 (grey) or 3 (BGR) channels, got {self.image.shape[2]}")


class MembraneDeformation(SensorMessage, frozen=True, kw_only=True):
    """A Soft Bubble membrane's deformation from its reference shape. deformation: ``(H, W)`` float32, m along the
    depth camera's optical axis, positive = pressed towards the camera, NaN = no depth return.
    reference_stamp_ns: ``time.monotonic_ns()`` when the undeformed reference image was captured."""

    topic = "deformation"
    ARRAYS = {"deformation": ArraySpec(("float32",), _IMAGE, finite=False)}

    bubble: str
    deformation: np.ndarray
    reference_stamp_ns: int


class TagDetections(SensorMessage, frozen=True, kw_only=True):
    """AprilTags seen in one camera image, T <= 64 of them (row t describes one tag).

    ids: ``(T,)`` int32 tag ids. corners_px: ``(T, 4, 2)`` float64 image corners (x, y) in px, in the detector's
    order. poses: ``(T, 7)`` float64 tag poses in the camera frame (m, wxyz). reprojection_error_px: ``(T,)``
    float64 RMS corner reprojection error of each pose, px. ambiguity: ``(T,)`` float64 ratio of the best to the
    second-best pose solution's error (0..1; near 1 = the pose may be flipped).
    """

    topic = "tags"
    ARRAYS = {
        "ids": ArraySpec(("int32",), (Dim("T", MAX_TAGS),)),
        "corners_px": ArraySpec(_F64, (Dim("T", MAX_TAGS), 4, 2)),
        "poses": ArraySpec(_F64, (Dim("T", MAX_TAGS), 7), unit_quaternion=True),
        "reprojection_error_px": ArraySpec(_F64, (Dim("T", MAX_TAGS),)),
        "ambiguity": ArraySpec(_F64, (Dim("T", MAX_TAGS),)),
    }

    camera: str
    ids: np.ndarray
    corners_px: np.ndarray
    poses: np.ndarray
    reprojection_error_px: np.ndarray
    ambiguity: np.ndarray


class ObjectPose(SensorMessage, frozen=True, kw_only=True):
    """The tracked object's pose. pose: ``(7,)`` float64 in the robot base frame (m, wxyz). tags_used: ids of the
    tags the estimate rests on. quality: 0 (unusable) .. 1 (best), the tracker's confidence. hw_stamp_ns is the
    image's stamp."""

    topic = "object_pose"
    ARRAYS = {"pose": POSE}

    object: str
    pose: np.ndarray
    tags_used: tuple[int, ...]
    quality: float

    def check(self) -> None:
        if not 0.0 <= self.quality <= 1.0:
            raise OutOfRange(f"ObjectPose.quality must be in [0, 1], got {self.quality!r}")


class Wrench(SensorMessage, frozen=True, kw_only=True):
    """A force/torque reading. wrench: ``(6,)`` float64 ``[Fx, Fy, Fz, Mx, My, Mz]`` in N and N m, sensor frame.
    tared: the sensor's bias was removed (True) or the reading is raw (False)."""

    topic = "wrench"
    ARRAYS = {"wrench": WRENCH}

    sensor: str
    wrench: np.ndarray
    tared: bool


StopOwner = Literal["", "stack", "external"]


class ArmState(SensorMessage, frozen=True, kw_only=True):
    """An arm's state as its commander sees it. tcp_pose: ``(7,)`` float64, base frame (m, wxyz). tcp_speed:
    ``(6,)`` float64 (m/s, rad/s), base frame. running: the controller executes our program. protective_stop,
    emergency_stop: the controller's stop flags. servo_active: the commander is servoing towards targets (False:
    stopped). holding: the stop is a hold: the target's deadline passed while it servoed and no other rule
    stopped it (the planner's next target is late; the next fresh target resumes; not a fault). stop_reason: why
    it stopped ("" while servoing). stop_owner: who stopped it: "stack" (the commander's
    own rules), "external" (a person or the controller: pendant, dashboard, safety system; latched until ``arm
    enable``) or "" while servoing. controller_stop: the controller's own named stop ("" when it runs our program
    normally; e.g. "safeguard stop", "program paused"). safety_flags: every safety stop the controller reports.
    latched: an external stop holds the arm until a person re-enables it (``hydrosoft-stack arm enable ARM``).
    goal_floor_ns: the commander acts only on targets of goals started after this (``time.monotonic_ns()``; its
    start, its last reconnect, ``arm enable``, refused goal or loss of the planner), named by goal_floor_cause."""

    topic = "arm_state"
    ARRAYS = {"tcp_pose": POSE, "tcp_speed": TWIST}

    arm: str
    tcp_pose: np.ndarray
    tcp_speed: np.ndarray
    running: bool
    protective_stop: bool
    emergency_stop: bool
    servo_active: bool
    holding: bool = False
    stop_reason: str = ""
    stop_owner: StopOwner = ""
    controller_stop: str = ""
    safety_flags: tuple[str, ...] = ()
    latched: bool = False
    goal_floor_ns: int = 0
    goal_floor_cause: str = ""


# --- planner outputs ---------------------------------------------------------------------------------------------


#: How a goal ended, for the halt target the planner sends then (``ArmTarget.goal_end``; "" for a plan's target).
GoalEnd = Literal["", "reached", "failed", "timeout", "stopped", "interrupted"]


class ArmTarget(Message, frozen=True, kw_only=True):
    """The pose the arm should servo towards. tcp_pose: ``(7,)`` float64, base frame (m, wxyz). deadline_ns:
    ``time.monotonic_ns()`` after which the target is void and the arm stops (the commander caps how far ahead it
    may lie: ``limits.max_target_lead_s``). plan_seq: ``seq`` of the plan it came from. goal_started_ns: when the
    goal it serves was started (the planner's ``time.monotonic_ns()``; 0: no goal): a commander servoes only on
    goals started after its own start, its last reconnect and its last ``arm enable``. plan_done_ns: when the plan
    it comes from was completed (the end of its solve, or when a waypoint or halt was computed); the commander stops
    when it is older than ``limits.max_plan_age_s``. goal_end: "" for a plan's target; the goal's outcome
    (``GoalEnd``) for the halt the planner sends when the goal ends: the commander stops the arm and names that
    outcome as the cause ("goal reached")."""

    topic = "arm_target"
    ARRAYS = {"tcp_pose": POSE}

    arm: str
    tcp_pose: np.ndarray
    deadline_ns: int
    plan_seq: int
    goal_started_ns: int = 0
    plan_done_ns: int = 0
    goal_end: GoalEnd = ""

    def check(self) -> None:
        _positive(self, deadline_ns=self.deadline_ns)
        for name in ("goal_started_ns", "plan_done_ns"):
            if getattr(self, name) < 0:
                raise OutOfRange(f"ArmTarget.{name} must be >= 0, got {getattr(self, name)}")


class Plan(Message, frozen=True, kw_only=True):
    """One MPC solution (K steps, M compliant bodies, N object surface points), float32 or float64.

    actions: ``(K, M, 6)`` per step and body a base-frame translation increment (m) and rotation-vector increment
    (rad), as ``hydrosoft.dynamics`` takes them (``se3.retract``). predicted_object_poses: ``(K, 7)`` object pose
    after each step, base frame (m, wxyz). predicted_forces: ``(M, N, 3)`` force each body applies to each surface
    point after the first step, base frame, N. cost: the plan's cost (task units). solve_ms: wall time of the solve,
    ms. (The planner plans in the task frame, ``scene.task_frame``, and converts.)

    Where the time went from the camera image to the arm targets (``time.monotonic_ns()`` of the planner's host, 0
    when unknown): image_stamp_ns, the tag image's stamp behind the object pose used (its ``hw_stamp_ns``: the
    exposure in sim; in the lab the camera's own clock); pose_stamp_ns, when the tracker published that pose;
    inputs_ns, when the planner took its inputs; solve_start_ns, when the solve began (after the state estimate);
    targets_ns, when the targets of this plan were sent.
    """

    topic = "plan"
    ARRAYS = {
        "actions": ArraySpec(_FLOAT, (Dim("K", MAX_HORIZON), Dim("M", MAX_BODIES), 6)),
        "predicted_object_poses": ArraySpec(_FLOAT, (Dim("K", MAX_HORIZON), 7), unit_quaternion=True),
        "predicted_forces": ArraySpec(_FLOAT, (Dim("M", MAX_BODIES), Dim("N", MAX_POINTS), 3)),
    }

    task: str
    actions: np.ndarray
    predicted_object_poses: np.ndarray
    predicted_forces: np.ndarray
    cost: float
    solve_ms: float
    image_stamp_ns: int = 0
    pose_stamp_ns: int = 0
    inputs_ns: int = 0
    solve_start_ns: int = 0
    targets_ns: int = 0


# --- health ------------------------------------------------------------------------------------------------------

ServiceState = Literal["starting", "ready", "degraded", "stopping"]


class Heartbeat(Message, frozen=True, kw_only=True):
    """A sign of life. period_s: the sender's heartbeat period, s (a receiver's timeout should exceed 2x it)."""

    topic = "heartbeat"

    period_s: float

    def check(self) -> None:
        _positive(self, period_s=self.period_s)


class ServiceStatus(Message, frozen=True, kw_only=True):
    """A service's health. state: starting, ready, degraded or stopping. pid: its process id. uptime_s: s since it
    started. published_hz, received_hz: per topic, messages per second over the last status period. errors:
    count per error kind since start. last_error: text of the newest error ("" if none). restarts: how often the
    launcher restarted it. note: the service's own one-line account of a state worth knowing ("" if none; the F/T
    reader's bias and its age, or why it publishes untared readings). instance: the id of the stack launch it
    belongs to (the launcher's, passed to all its services; a service started alone makes its own). compilation:
    a service with a compiled part (the planner, sim_world): ``compiling: ...`` (loading its artefact, or building
    a missing or stale one), ``compiled (artefact KEY)`` or ``eager...`` with the reason; "" for the others
    (``services/bus/artefacts.py``)."""

    topic = "status"

    state: ServiceState
    pid: int
    uptime_s: float
    published_hz: dict[str, float] = {}
    received_hz: dict[str, float] = {}
    errors: dict[str, int] = {}
    last_error: str = ""
    restarts: int = 0
    note: str = ""
    instance: str = ""
    compilation: str = ""


# --- client API: requests and replies ----------------------------------------------------------------------------


class Goal(Payload, frozen=True, kw_only=True):
    """What the planner should achieve. task: a task name of ``hydrosoft.tasks`` ("pushing", "rotation", ...).
    Either target_pose: ``(7,)`` float64 object pose in the robot base frame (m, wxyz), or (target_pose None) a
    displacement of the object from its pose at Start: dx_m, dy_m (m, base frame), dyaw_rad (rad, about base z),
    droll_rad (rad, about base x: in-hand rotation's grasp axis) and dpitch_rad (rad, about base y: a cylinder
    rolled by d along x turns d / radius), all turns about the object's centre. tolerance_mm, tolerance_deg: position
    and yaw tolerance for success. timeout_s: give up after this long.
    instance: the stack launch (``ServiceStatus.instance``) the goal is meant for; a planner of another launch
    refuses it. "" = any (a script that sets goals on whatever stack runs)."""

    ARRAYS = {"target_pose": POSE._replace(optional=True)}

    task: str
    target_pose: np.ndarray | None = None
    dx_m: float = 0.0
    dy_m: float = 0.0
    dyaw_rad: float = 0.0
    droll_rad: float = 0.0
    dpitch_rad: float = 0.0
    tolerance_mm: float
    tolerance_deg: float = 5.0
    timeout_s: float
    instance: str = ""

    def check(self) -> None:
        if self.target_pose is not None and (self.dx_m, self.dy_m, self.dyaw_rad, self.droll_rad,
                                             self.dpitch_rad) != (0.0,) * 5:
            raise OutOfRange("Goal takes either target_pose or dx_m/dy_m/dyaw_rad/droll_rad/dpitch_rad, not both")
        _positive(self, tolerance_mm=self.tolerance_mm, tolerance_deg=self.tolerance_deg, timeout_s=self.timeout_s)
        for name in ("task", "instance"):
            if len(getattr(self, name)) > MAX_TASK_CHARS:
                raise OutOfRange(f"Goal.{name} has {len(getattr(self, name))} characters, more than {MAX_TASK_CHARS}")


class Reply(Message, frozen=True, kw_only=True):
    """Base of the replies. ok: the request was accepted and done; error: why not ("" when ok)."""

    ok: bool
    error: str = ""


NO_FRESH_INPUT = "no fresh input to start from"
"""How a planner's refusal of Start begins when its inputs are stale or not received yet (a restarted planner's
first moments): a client may try again shortly."""


class CommandReply(Reply, frozen=True, kw_only=True):
    """The reply to SetGoal, Start and Stop, and to any request the server could not read."""

    topic = "reply/command"


Outcome = Literal["", "running", "reached", "failed", "timeout", "stopped", "interrupted"]


class StatusReply(Reply, frozen=True, kw_only=True):
    """The reply to GetStatus. running: a goal is being pursued. goal: the current goal, if any, with
    target_pose resolved once started (the object pose it must reach, base frame). status: the server's own
    ServiceStatus. outcome: "" (never started), running, reached, failed (reason in outcome_reason), timeout,
    stopped or interrupted (the client's verdict on a goal whose planner restarted: it is not resumed unless
    asked). error_mm: the latest ADD error of the object (its tracked pose) against the target, mm. elapsed_s:
    since Start, s. solves: MPC solves since Start. mean_solve_ms: their mean wall time, ms. reapproaches: how often
    the bubble was brought back onto a lost object since Start."""

    topic = "reply/status"

    running: bool = False
    goal: Goal | None = None
    status: ServiceStatus | None = None
    outcome: Outcome = ""
    outcome_reason: str = ""
    error_mm: float = 0.0
    elapsed_s: float = 0.0
    solves: int = 0
    mean_solve_ms: float = 0.0
    reapproaches: int = 0


class Request(Message, frozen=True, kw_only=True):
    """Base of the client's requests; ``reply`` is the kind a server answers it with. deadline_ns:
    ``time.monotonic_ns()`` after which the server must refuse the request (the client has given up on it);
    0 = none. The client fills it."""

    reply: ClassVar[type[Reply]] = CommandReply

    deadline_ns: int = 0


class SetGoal(Request, frozen=True, kw_only=True):
    """Replace the planner's goal (does not start it)."""

    topic = "cmd/set_goal"

    goal: Goal


class Start(Request, frozen=True, kw_only=True):
    """Start pursuing the current goal."""

    topic = "cmd/start"


class Stop(Request, frozen=True, kw_only=True):
    """Stop pursuing the goal and hold the arm. reason: free text for the logs."""

    topic = "cmd/stop"

    reason: str = ""


class GetStatus(Request, frozen=True, kw_only=True):
    """Ask for a StatusReply."""

    topic = "cmd/get_status"
    reply = StatusReply


class TareReply(Reply, frozen=True, kw_only=True):
    """The reply to Tare. bias: ``(6,)`` float64 the stored bias ``[Fx, Fy, Fz, Mx, My, Mz]`` (N, N m, sensor
    frame) now subtracted from every reading, None when refused. taken_unix_ns: when it was taken (wall clock, ns
    since the Unix epoch: it is kept across restarts; 0 when refused)."""

    topic = "reply/tare"
    ARRAYS = {"bias": WRENCH._replace(optional=True)}

    bias: np.ndarray | None = None
    taken_unix_ns: int = 0


class Tare(Request, frozen=True, kw_only=True):
    """Ask an F/T reader (``ft_reader-ARM``'s cmd endpoint) to tare its sensor: take the mean reading as the new
    bias and store it. Refused (``ok`` False, the reason in ``error``) unless the arm is at rest and its bubble
    shows no contact (``services/arm/tare_rules.py``)."""

    topic = "cmd/tare"
    reply = TareReply
class ArmEnableReply(Reply, frozen=True, kw_only=True):
    """The reply to EnableArm. cleared: the external stop that was cleared ("" when none was latched)."""

    topic = "reply/arm_enable"

    cleared: str = ""


class EnableArm(Request, frozen=True, kw_only=True):
    """A person re-enables an arm after an external stop (to its commander's ``cmd`` endpoint). arm: the arm's
    name. by: who asks (free text for the log)."""

    topic = "cmd/enable_arm"
    reply = ArmEnableReply

    arm: str
    by: str = ""


# --- ground truth (simulation only; the planner never subscribes to eval/) ---------------------------------------


class EvalObjectPose(Message, frozen=True, kw_only=True):
    """The simulated object's true pose. pose: ``(7,)`` float64, world frame = robot base frame (m, wxyz)."""

    topic = "eval/object_pose"
    ARRAYS = {"pose": POSE}

    object: str
    pose: np.ndarray


class EvalContactForces(Message, frozen=True, kw_only=True):
    """The simulated contact forces. bodies: the M compliant bodies' names. points: ``(N, 3)`` float64 object-frame
    surface points, m. forces: ``(M, N, 3)`` float64 force each body applies to each point, world frame, N."""

    topic = "eval/contact_forces"
    ARRAYS = {
        "points": ArraySpec(_F64, (Dim("N", MAX_POINTS), 3)),
        "forces": ArraySpec(_F64, (Dim("M", MAX_BODIES), Dim("N", MAX_POINTS), 3)),
    }

    bodies: tuple[str, ...]
    points: np.ndarray
    forces: np.ndarray

    def check(self) -> None:
        if len(self.bodies) != self.forces.shape[0]:
            raise ShapeError(f"EvalContactForces has {len(self.bodies)} bodies but forces for {self.forces.shape[0]}")


# --- registry ----------------------------------------------------------------------------------------------------


def _array_fields(cls: type[Payload]) -> set[str]:
    """Names of the fields of ``cls`` whose type is (or may be) a numpy array."""
    hints = typing.get_type_hints(cls)
    return {
        name for name in cls.__struct_fields__
        if hints[name] is np.ndarray or np.ndarray in typing.get_args(hints[name])
    }


def _register(*kinds: type[Message]) -> dict[str, type[Message]]:
    """Map each kind's topic to it, after checking that topics do not shadow each other and that ``ARRAYS``
    describes exactly the array fields (of the kind and of the payloads nested in it)."""
    registry: dict[str, type[Message]] = {}
    for kind in kinds:
        for other in registry:
            if kind.topic == other or kind.topic.startswith(other + "/") or other.startswith(kind.topic + "/"):
                raise RuntimeError(f"topic {kind.topic!r} of {kind.__name__} overlaps {other!r}")
        registry[kind.topic] = kind
    for cls in (*kinds, Goal):
        if _array_fields(cls) != set(cls.ARRAYS):
            raise RuntimeError(f"{cls.__name__}.ARRAYS {sorted(cls.ARRAYS)} != array fields {_array_fields(cls)}")
    return registry


KINDS: dict[str, type[Message]] = _register(
    DepthFrame, CameraImage, MembraneDeformation, TagDetections, ObjectPose, Wrench, ArmState, ArmTarget, Plan,
    Heartbeat, ServiceStatus, CommandReply, StatusReply, SetGoal, Start, Stop, GetStatus, EnableArm, ArmEnableReply,
    Tare, TareReply, EvalObjectPose, EvalContactForces,
)
"""Every message kind by its topic."""


def topic_for(kind: type[Message], instance: str | None = None) -> str:
    """The topic of ``kind`` for one instance (``topic_for(DepthFrame, "left") == "depth/left"``)."""
    return kind.topic if instance is None else f"{kind.topic}/{instance}"


def kind_for_topic(topic: str) -> type[Message]:
    """The kind whose topic is ``topic`` or its longest ``/``-prefix. Raises UnknownTopic."""
    prefix = topic
    while True:
        kind = KINDS.get(prefix)
        if kind is not None:
            return kind
        prefix, sep, _ = prefix.rpartition("/")
        if not sep:
            raise UnknownTopic(f"no message kind has topic {topic!r} (known: {', '.join(sorted(KINDS))})")


# --- validation --------------------------------------------------------------------------------------------------


def _check_array(where: str, value: Any, spec: ArraySpec, dims: dict[str, int]) -> None:
    if not isinstance(value, np.ndarray):
        raise SchemaError(f"{where} must be a numpy array, got {type(value).__name__}")
    if value.dtype not in _dtypes(spec.dtypes):
        raise DtypeError(f"{where} must have dtype {' or '.join(spec.dtypes)}, got {value.dtype.name}")
    if value.ndim != len(spec.shape):
        raise ShapeError(f"{where} must have {len(spec.shape)} axes {_shape_text(spec)}, got shape {value.shape}")
    for axis, (size, rule) in enumerate(zip(value.shape, spec.shape)):
        if isinstance(rule, Dim):
            if size > rule.max:
                raise ShapeError(f"{where} axis {axis} ({rule.name}) is {size}, more than {rule.max}")
            if dims.setdefault(rule.name, size) != size:
                raise ShapeError(f"{where} axis {axis} ({rule.name}) is {size}, but another field has "
                                 f"{rule.name} = {dims[rule.name]}")
        elif size != rule:
            raise ShapeError(f"{where} must have shape {_shape_text(spec)}, got {value.shape}")
    if spec.finite and value.dtype.kind == "f" and not np.isfinite(value).all():
        raise NonFinite(f"{where} holds NaN or Inf")
    if spec.unit_quaternion:
        norm = np.linalg.norm(value[..., 3:7].astype(np.float64), axis=-1)
        worst = float(np.max(np.abs(norm - 1.0), initial=0.0))
        if worst > QUATERNION_NORM_TOLERANCE:
            raise NonUnitQuaternion(f"{where} has a quaternion of norm off 1 by {worst:.3g} "
                                    f"(tolerance {QUATERNION_NORM_TOLERANCE:g})")


@functools.cache
def _dtypes(names: tuple[str, ...]) -> frozenset[np.dtype]:
    return frozenset(np.dtype(name) for name in names)


def _shape_text(spec: ArraySpec) -> str:
    return "(" + ", ".join(f"{r.name}<={r.max}" if isinstance(r, Dim) else str(r) for r in spec.shape) + ")"


@functools.cache
def _fields(cls: type[Payload]) -> tuple[tuple[str, str, ArraySpec | None], ...]:
    """Each field of ``cls``: its name, its name in error texts and its ``ArraySpec`` (None: not an array). Made
    once per kind, as ``validate`` runs twice per message (encode and decode)."""
    return tuple((name, f"{cls.__name__}.{name}", cls.ARRAYS.get(name)) for name in cls.__struct_fields__)


def validate(payload: Payload) -> None:
    """Check ``payload`` (and the payloads nested in it) against its kind's rules; raise a ``MessageError``."""
    dims: dict[str, int] = {}
    for name, where, spec in _fields(type(payload)):
        value = getattr(payload, name)
        if spec is not None:
            if value is None and spec.optional:
                continue
            _check_array(where, value, spec, dims)
        elif isinstance(value, float) and not math.isfinite(value):
            raise NonFinite(f"{where} is {value}")
        elif isinstance(value, Payload):
            validate(value)
    payload.check()


# --- wire frames -------------------------------------------------------------------------------------------------


def encode(msg: Message, topic: str | None = None) -> list[bytes | np.ndarray]:
    """The frames of ``msg`` on ``topic`` (default ``msg.topic``): ``[topic, header, arrays...]``.

    The array frames are the message's own arrays (made C-contiguous if they were not), not copies. Raises
    UnknownTopic when ``topic`` does not belong to ``msg``'s kind, and the ``MessageError`` of any broken rule.
    """
    topic = msg.topic if topic is None else topic
    if kind_for_topic(topic) is not type(msg):
        raise UnknownTopic(f"topic {topic!r} belongs to {kind_for_topic(topic).__name__}, not {type(msg).__name__}")
    validate(msg)
    arrays: list[np.ndarray] = []

    def array_to_meta(value: Any) -> ArrayMeta:
        if not isinstance(value, np.ndarray):
            raise TypeError(f"cannot encode {type(value).__name__}")
        array = np.ascontiguousarray(value)
        if array.nbytes > MAX_FRAME_BYTES:
            raise OversizedFrame(f"an array of {type(msg).__name__} has {array.nbytes} bytes, "
                                 f"more than {MAX_FRAME_BYTES}")
        arrays.append(array)
        return ArrayMeta(array.dtype.str, array.shape)

    header = msgspec.msgpack.encode(msg, enc_hook=array_to_meta)
    if len(header) > MAX_HEADER_BYTES:
        raise OversizedFrame(f"the header of {type(msg).__name__} has {len(header)} bytes, "
                             f"more than {MAX_HEADER_BYTES}")
    return [topic.encode(), header, *arrays]


def decode(frames: Sequence[Any]) -> tuple[str, Message]:
    """The topic and the message of one received multipart message.

    frames: ``[topic, header, arrays...]`` as bytes or any buffer (``zmq.Frame``). Arrays are read-only views of
    their frames. Raises the ``MessageError`` subclass that names the problem: UnknownTopic, FrameCountError,
    GarbageBytes, SchemaError, DtypeError, ShapeError, LengthMismatch, OversizedFrame, NonFinite,
    NonUnitQuaternion or OutOfRange.
    """
    if len(frames) < 2:
        raise FrameCountError(f"a message needs a topic and a header frame, got {len(frames)} frame(s)")
    views = [_byte_view(frame) for frame in frames]
    for index, (view, limit) in enumerate(zip(views, (MAX_TOPIC_BYTES, MAX_HEADER_BYTES))):
        if view.nbytes > limit:
            raise OversizedFrame(f"frame {index} ({('topic', 'header')[index]}) has {view.nbytes} bytes, "
                                 f"more than {limit}")
    for index, view in enumerate(views[2:], start=2):
        if view.nbytes > MAX_FRAME_BYTES:
            raise OversizedFrame(f"array frame {index} has {view.nbytes} bytes, more than {MAX_FRAME_BYTES}")
    try:
        topic = bytes(views[0]).decode()
    except UnicodeDecodeError as error:
        raise GarbageBytes(f"the topic frame is not UTF-8: {error}") from None
    kind = kind_for_topic(topic)
    array_frames = iter(views[2:])
    msg = _decode_header(kind, views[1], lambda meta: _frame_to_array(kind, meta, array_frames))
    left = sum(1 for _ in array_frames)
    if left:
        raise FrameCountError(f"{kind.__name__} on {topic!r} came with {left} array frame(s) more than its header "
                              "describes")
    validate(msg)
    return topic, msg


def _byte_view(frame: Any) -> memoryview:
    """A flat byte view of one frame (bytes, ``zmq.Frame`` or a C-contiguous array)."""
    view = memoryview(frame)
    if view.ndim == 1 and view.format == "B":
        return view
    return view.cast("B") if view.nbytes else memoryview(b"")


def _decode_header(kind: type[Message], header: memoryview, to_array: Any) -> Message:
    def meta_to_array(type_: type, obj: Any) -> Any:
        if type_ is not np.ndarray:
            raise TypeError(f"unexpected type {type_}")
        try:
            meta = msgspec.convert(obj, ArrayMeta)
        except msgspec.ValidationError as error:
            raise SchemaError(f"{kind.__name__}: bad array description {obj!r}: {error}") from None
        return to_array(meta)

    try:
        return msgspec.msgpack.decode(header, type=kind, dec_hook=meta_to_array)
    except msgspec.ValidationError as error:
        raise SchemaError(f"{kind.__name__}: {error}") from None
    except msgspec.DecodeError as error:
        raise GarbageBytes(f"{kind.__name__}: the header is not msgpack: {error}") from None


def _frame_to_array(kind: type[Message], meta: ArrayMeta, frames: Iterator[memoryview]) -> np.ndarray:
    try:
        dtype = np.dtype(meta.dtype)
    except TypeError:
        raise DtypeError(f"{kind.__name__}: {meta.dtype!r} is not a numpy dtype") from None
    if dtype not in _WIRE_DTYPES or dtype.byteorder == ">":
        raise DtypeError(f"{kind.__name__}: dtype {meta.dtype!r} is not a little-endian numeric dtype")
    frame = next(frames, None)
    if frame is None:
        raise FrameCountError(f"{kind.__name__}: the header describes more arrays than there are frames")
    expected = math.prod(meta.shape) * dtype.itemsize
    if frame.nbytes != expected:
        raise LengthMismatch(f"{kind.__name__}: an array of shape {meta.shape} {dtype.name} needs {expected} bytes, "
                             f"its frame has {frame.nbytes}")
    return np.frombuffer(frame, dtype=dtype).reshape(meta.shape)
