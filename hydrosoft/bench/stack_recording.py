"""A stack recording (``hydrosoft-stack launch --record``, an MCAP file of the recorder) read as one trajectory of the
material fit (``wrench_recording.RecordedTrajectory``), beside the ``collect wrench`` format.

The fit needs three raw topics (``services/recording/mcap_format.py``): ``wrench/ARM`` (the F/T wrench, sensor frame,
tared), ``arm_state/ARM`` (the TCP pose, base frame) and ``object_pose/object`` (the tracked object pose, base frame).
The bubble frame is the stack's TCP frame (sim_world puts the arm's bubble body at the TCP pose), so the bubble pose is
the TCP pose. Samples are taken on the wrench's stamps (``stamp_ns``), at most one per ``period_s``; each takes the
arm's TCP pose and the object pose at that stamp (``pose_at``; a tracked pose stands at its image's exposure when
that is on the host's clock, ``MAX_EXPOSURE_AGE_NS``): interpolated between the poses recorded just before
and just after it (linear in position, slerp in orientation) when those are at most ``2 max_gap_s`` apart, else the
nearest pose when it is within ``max_gap_s``. A sample with no such arm pose (or, unless the object is clamped, no
object pose) is dropped and counted. With ``clamped``, every sample takes the first tracked object pose (the object
does not move; tracker noise stays out of the replay).

``read_stack_recording`` gives the whole recording as one trajectory, its first kept sample the tare row
(``wrench_replay.measured_tcp_wrenches`` subtracts it). ``split_at_free_samples`` cuts it into one trajectory per
contact: a run of samples whose force exceeds ``contact_force_n``, after up to ``APPROACH_SAMPLES`` out-of-contact
ones, the first of which is its tare; a contact the recording starts in is kept only when it started pressed straight
in and the stream was tared (``start_pressed``, ``pretared``: the sim scenes start so). The file is only read, in one pass, one message at a time (images and other
topics are never decoded); only these topics' stamps, poses and wrenches are held.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from hydrosoft.bench.wrench_recording import RecordedTrajectory, RecordingInfo

IDENTITY = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
OBJECT_TOPIC = "object_pose/object"
TRUE_OBJECT_TOPIC = "eval/object_pose"  # the sim's true object pose (10 Hz), beside the tracked one
DEFAULT_MAX_GAP_S = 0.02  # the arm state comes at 125 Hz (8 ms) or faster, the tracked pose at the camera's 30 Hz
DEFAULT_PERIOD_S = 0.05  # collect wrench's sample spacing
#: A sample whose force (the tared wrench's force norm, N) exceeds this is in contact: 5 times the FT 300's noise per
#: axis and frame (0.1 N), about 3 times its norm over three axes (0.17 N), well under a press's few newtons.
DEFAULT_CONTACT_FORCE_N = 0.5
#: Out-of-contact samples kept before each contact, the first of them its tare (0.5 s at the default period): the
#: tare is taken before the approach rather than at the touch, where light contact may already load the sensor.
APPROACH_SAMPLES = 10
#: A tracked pose is placed at its image's exposure (``ObjectPose.hw_stamp_ns``) when every tracked pose's exposure
#: is on the host's monotonic clock, as the sim camera's is: at most this long before the pose was published. The
#: tracker publishes a pose 30-60 ms after its exposure (the image's render or grab, then the tracker): placed at
#: its publishing, a pushed cube's replayed pose lagged the wrench by that (measured on a sim push: 0.49 mm behind
#: along the push, 0.10 mm at the exposure). A lab camera's own clock (``CAP_PROP_POS_MSEC``) is not the host's:
#: its poses keep their publishing stamps.
MAX_EXPOSURE_AGE_NS = 1_000_000_000

@dataclass(frozen=True)
class StackTrajectory:
    """A stack recording read for the fit: ``info`` (as a ``collect wrench`` file's, ``mode`` "stack"), its one
    ``trajectory``, the ``arm`` read, ``kept`` samples and ``dropped`` ones (no fresh pose within the max gap);
    ``tared``: every kept wrench was tared by the F/T reader (``Wrench.tared``); ``at_exposure``: the object poses
    were placed at their images' exposures (``MAX_EXPOSURE_AGE_NS``), not at their publishing."""

    info: RecordingInfo
    trajectory: RecordedTrajectory
    arm: str
    kept: int
    dropped: int
    tared: bool = False
    at_exposure: bool = False


def is_stack_recording(path: str | Path) -> bool:
    """Whether ``path`` is a stack recording: an MCAP file whose first channel is not the ``collect wrench``
    sample channel (read up to that channel only; a file that is not MCAP, or has no channel, is not one)."""
    from mcap.exceptions import McapError
    from mcap.records import Channel
    from mcap.stream_reader import StreamReader

    from hydrosoft.bench.wrench_recording import TOPIC

    try:
        with open(path, "rb") as stream:
            for record in StreamReader(stream).records:
                if isinstance(record, Channel):
                    return record.topic != TOPIC
    except (McapError, EOFError, ValueError, OSError):
        return False
    return False


def pose_at(stamps: np.ndarray, poses: np.ndarray, at: int, max_gap_ns: int) -> np.ndarray | None:
    """The pose ``(7,)`` (m, wxyz) at stamp ``at`` (ns) of poses ``(N, 7)`` at sorted ``stamps (N,)``: interpolated
    between the poses just before and just after ``at`` (linear position, slerp orientation) when they are at most
    ``2 max_gap_ns`` apart, else the nearest one when it is within ``max_gap_ns``; None when there is none."""
    from scipy.spatial.transform import Rotation, Slerp

    i = int(np.searchsorted(stamps, at, side="right"))  # stamps[i - 1] <= at < stamps[i]
    if i > 0 and stamps[i - 1] == at:
        return poses[i - 1]
    if 0 < i < len(stamps) and stamps[i] - stamps[i - 1] <= 2 * max_gap_ns:
        t0, t1 = int(stamps[i - 1]), int(stamps[i])
        fraction = (at - t0) / (t1 - t0)
        position = (1 - fraction) * poses[i - 1, :3] + fraction * poses[i, :3]
        turns = Rotation.from_quat(poses[i - 1:i + 1, 3:], scalar_first=True)
        quaternion = Slerp([0.0, 1.0], turns)(fraction).as_quat(scalar_first=True)
        if np.dot(quaternion, poses[i - 1, 3:]) < 0:  # keep the recorded hemisphere
            quaternion = -quaternion
        return np.concatenate([position, quaternion])
    candidates = [j for j in (i - 1, i) if 0 <= j < len(stamps)]
    best = min(candidates, key=lambda j: abs(int(stamps[j]) - at))
    return poses[best] if abs(int(stamps[best]) - at) <= max_gap_ns else None


def split_at_free_samples(trajectory: RecordedTrajectory, contact_force_n: float = DEFAULT_CONTACT_FORCE_N,
                          start_pressed: bool = False) -> tuple[list[RecordedTrajectory], int]:
    """One trajectory per contact of ``trajectory`` (a whole stack recording, ``read_stack_recording``), and the
    count of contacts left out because no out-of-contact sample precedes them (the recording starts in contact).

    A sample is in contact when its force norm (N) exceeds ``contact_force_n``. Each maximal run of such samples
    becomes a trajectory: up to ``APPROACH_SAMPLES`` out-of-contact samples before it (the first is its tare row),
    then the run. A contact the recording starts in has no such sample, so it is left out, unless ``start_pressed``
    (the caller knows the recording starts at rest with the bubble pressed straight in, as the sim scenes start, and
    that the F/T reader tared the stream out of contact): then it becomes a ``pretared`` trajectory, its wrenches
    taken as they are and its first row replayed pressed in. Trajectories keep ``trajectory.index``; the caller
    numbers them."""
    force = np.linalg.norm(trajectory.wrenches[:, :3], axis=-1)
    touching = force > contact_force_n
    pieces, skipped, k = [], 0, 0
    while k < len(touching):
        if not touching[k]:
            k += 1
            continue
        end = k
        while end < len(touching) and touching[end]:
            end += 1
        free = k
        while free > 0 and not touching[free - 1] and k - free < APPROACH_SAMPLES:
            free -= 1
        pretared = free == k == 0 and start_pressed and end > 1
        if free == k and not pretared:
            skipped += 1
        else:
            rows = slice(free, end)
            pieces.append(replace(trajectory, bubble_poses=trajectory.bubble_poses[rows],
                                  target_poses=trajectory.target_poses[rows],
                                  object_poses=trajectory.object_poses[rows], wrenches=trajectory.wrenches[rows],
                                  phases=("start",) + ("stack",) * (end - free - 1), pretared=pretared))
        k = end
    return pieces, skipped


def read_stack_recording(path: str | Path, object_name: str | None = None, arm: str | None = None,
                         clamped: bool = False, tcp_in_sensor=IDENTITY, max_gap_s: float = DEFAULT_MAX_GAP_S,
                         period_s: float = DEFAULT_PERIOD_S, true_object: bool = False) -> StackTrajectory:
    """The fit's trajectory of the stack recording ``path`` (module docstring). ``object_name``: the benchmark object
    to replay (default: the tracked pose's ``object`` when that is one); ``arm``: whose wrench and TCP (default: the
    only one recorded); ``tcp_in_sensor``: ``(7,)`` the TCP frame in the F/T sensor's frame (m, wxyz);
    ``true_object``: take the sim's true object pose (``TRUE_OBJECT_TOPIC``) instead of the tracked one, to tell
    the tracker's share of a sim fit's error. ValueError
    naming the file and the missing topic, or when no sample is left."""
    from hydrosoft.bench.wrench_scenes import BENCH_OBJECTS
    from hydrosoft.services.bus import messages as msg
    from hydrosoft.services.recording.mcap_format import RecordingError, RecordingReader, bus_topic

    path = Path(path)
    stamps: dict[str, list[int]] = {}
    values: dict[str, list[np.ndarray]] = {}
    names: dict[str, str] = {}
    tared: dict[str, list[bool]] = {}  # per wrench topic and message: tared by the F/T reader
    exposures: dict[str, list[int | None]] = {}  # per object pose topic: the tracked poses' hw_stamp_ns
    object_topic = TRUE_OBJECT_TOPIC if true_object else OBJECT_TOPIC
    reader = RecordingReader(path, ["wrench", "arm_state", object_topic])
    try:
        for item in reader:  # one pass, one message at a time; only these topics' poses and wrenches are kept
            message = item.message
            stamps.setdefault(item.topic, []).append(message.stamp_ns)
            if isinstance(message, (msg.ObjectPose, msg.EvalObjectPose)):
                values.setdefault(item.topic, []).append(np.array(message.pose))
                names.setdefault(item.topic, message.object)
                if isinstance(message, msg.ObjectPose):
                    exposures.setdefault(item.topic, []).append(message.hw_stamp_ns)
            elif isinstance(message, msg.Wrench):
                values.setdefault(item.topic, []).append(np.array(message.wrench))
                tared.setdefault(item.topic, []).append(message.tared)
            elif isinstance(message, msg.ArmState):
                values.setdefault(item.topic, []).append(np.array(message.tcp_pose))
    except RecordingError as error:
        raise ValueError(f"{path}: {error}") from None
    topics = {bus_topic(c) for c in reader.channels.values()} | set(stamps)
    arms = sorted({t.split("/", 1)[1] for t in topics if t.startswith(("wrench/", "arm_state/"))})
    if arm is None:
        if len(arms) > 1:
            raise ValueError(f"{path}: recording of several arms ({', '.join(arms)}); name one with --arm")
        arm = arms[0] if arms else "ARM"
    needed = [f"wrench/{arm}", f"arm_state/{arm}", object_topic]
    missing = [t for t in needed if t not in topics]
    if missing:
        raise ValueError(f"{path}: recording has no topic {', '.join(missing)}, which the fit needs")
    missing = [t for t in needed if not stamps.get(t)]
    if missing:
        raise ValueError(f"{path}: recording has no message on {', '.join(missing)}, which the fit needs")
    object_name = object_name or names[object_topic]
    if object_name not in BENCH_OBJECTS:
        raise ValueError(f"{path}: object {object_name!r} is not a benchmark object the fit can replay "
                         f"({', '.join(BENCH_OBJECTS)}); name one with --object")
    wrench_t, state_t, object_t = needed
    at_exposure = exposures_on_host_clock(stamps[object_t], exposures.get(object_t, []))
    if at_exposure:
        stamps[object_t] = exposures[object_t]
    order = {t: np.argsort(np.array(stamps[t], dtype=np.int64), kind="stable") for t in needed}
    sorted_stamps = {t: np.array(stamps[t], dtype=np.int64)[order[t]] for t in needed}
    sorted_poses = {t: np.stack(values[t])[order[t]] for t in (state_t, object_t)}
    max_gap_ns, period_ns = int(max_gap_s * 1e9), int(period_s * 1e9)
    rows: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # (TCP pose, object pose, wrench)
    all_tared = True
    dropped, last = 0, None
    for w in order[wrench_t]:
        at = int(stamps[wrench_t][w])
        if last is not None and at - last < period_ns:
            continue
        tcp = pose_at(sorted_stamps[state_t], sorted_poses[state_t], at, max_gap_ns)
        tracked = sorted_poses[object_t][0] if clamped else pose_at(sorted_stamps[object_t],
                                                                   sorted_poses[object_t], at, max_gap_ns)
        if tcp is None or tracked is None:
            dropped += 1
            continue
        rows.append((tcp, tracked, values[wrench_t][w]))
        all_tared = all_tared and tared[wrench_t][w]
        last = at
    if len(rows) < 2:
        raise ValueError(f"{path}: {len(rows)} sample(s) with a pose within {max_gap_s} s of the wrench "
                         f"({dropped} dropped): nothing to fit")
    bubbles, objects, wrenches = (np.stack(column) for column in zip(*rows))
    info = RecordingInfo(object=object_name, config=str(path), mode="stack", tcp_in_sensor=tuple(tcp_in_sensor),
                         plant_spacing_m=None, seed=0, epoch_offset_ns=reader.epoch_offset_ns)
    trajectory = RecordedTrajectory(object=object_name, index=0, bubble_poses=bubbles, target_poses=bubbles,
                                    object_poses=objects, wrenches=wrenches,
                                    phases=("start",) + ("stack",) * (len(rows) - 1))
    return StackTrajectory(info, trajectory, arm, len(rows), dropped, all_tared, at_exposure)


def exposures_on_host_clock(stamps: list[int], exposures: list[int | None]) -> bool:
    """Whether the exposures ``hw_stamp_ns`` (ns) of poses published at ``stamps`` (ns, the host's
    ``time.monotonic_ns``) are on the host's clock too: each one given and at most ``MAX_EXPOSURE_AGE_NS`` before its
    pose's publishing."""
    return len(exposures) == len(stamps) > 0 and all(
        exposure is not None and 0 <= stamp - exposure <= MAX_EXPOSURE_AGE_NS
        for stamp, exposure in zip(stamps, exposures))
