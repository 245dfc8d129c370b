"""A stack recording (``hydrosoft-stack launch --record``, an MCAP file of the recorder) read as one trajectory of the
material fit (``wrench_recording.RecordedTrajectory``), beside the ``collect wrench`` format.

The fit needs three raw topics (``services/recording/mcap_format.py``): ``wrench/ARM`` (the F/T wrench, sensor frame,
tared), ``arm_state/ARM`` (the TCP pose, base frame) and ``object_pose/object`` (the tracked object pose, base frame).
The bubble frame is the stack's TCP frame (sim_world puts the arm's bubble body at the TCP pose), so the bubble pose is
the TCP pose. Samples are taken on the wrench's stamps (``stamp_ns``), at most one per ``period_s``; each takes the
arm state and the object pose whose stamps are nearest to it. A sample with no arm state (or, unless the object is
clamped, no object pose) within ``max_gap_s`` of it is dropped and counted. With ``clamped``, every sample takes the
first tracked object pose (the object does not move; tracker noise stays out of the replay).

The first kept sample is the trajectory's tare row (``wrench_replay.measured_tcp_wrenches`` subtracts it): the
recording must start with the bubble out of contact. The file is only read, in one pass, one message at a time
(images and other topics are never decoded); only these topics' stamps, poses and wrenches are held.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hydrosoft.bench.wrench_recording import RecordedTrajectory, RecordingInfo

IDENTITY = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
OBJECT_TOPIC = "object_pose/object"
DEFAULT_MAX_GAP_S = 0.02  # the arm state comes at 125 Hz (8 ms) or faster, the tracked pose at the camera's 30 Hz
DEFAULT_PERIOD_S = 0.05  # collect wrench's sample spacing


@dataclass(frozen=True)
class StackTrajectory:
    """A stack recording read for the fit: ``info`` (as a ``collect wrench`` file's, ``mode`` "stack"), its one
    ``trajectory``, the ``arm`` read, ``kept`` samples and ``dropped`` ones (no fresh pose within the max gap)."""

    info: RecordingInfo
    trajectory: RecordedTrajectory
    arm: str
    kept: int
    dropped: int


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


def _nearest(stamps: np.ndarray, at: int) -> tuple[int, int]:
    """Index of the stamp nearest ``at`` in sorted ``stamps`` and its distance (ns)."""
    i = int(np.searchsorted(stamps, at))
    candidates = [j for j in (i - 1, i) if 0 <= j < len(stamps)]
    best = min(candidates, key=lambda j: abs(int(stamps[j]) - at))
    return best, abs(int(stamps[best]) - at)


def read_stack_recording(path: str | Path, object_name: str | None = None, arm: str | None = None,
                         clamped: bool = False, tcp_in_sensor=IDENTITY, max_gap_s: float = DEFAULT_MAX_GAP_S,
                         period_s: float = DEFAULT_PERIOD_S) -> StackTrajectory:
    """The fit's trajectory of the stack recording ``path`` (module docstring). ``object_name``: the benchmark object
    to replay (default: the tracked pose's ``object`` when that is one); ``arm``: whose wrench and TCP (default: the
    only one recorded); ``tcp_in_sensor``: ``(7,)`` the TCP frame in the F/T sensor's frame (m, wxyz). ValueError
    naming the file and the missing topic, or when no sample is left."""
    from hydrosoft.bench.wrench_scenes import BENCH_OBJECTS
    from hydrosoft.services.bus import messages as msg
    from hydrosoft.services.recording.mcap_format import RecordingError, RecordingReader, bus_topic

    path = Path(path)
    stamps: dict[str, list[int]] = {}
    values: dict[str, list[np.ndarray]] = {}
    names: dict[str, str] = {}
    reader = RecordingReader(path, ["wrench", "arm_state", "object_pose"])
    try:
        for item in reader:  # one pass, one message at a time; only these topics' poses and wrenches are kept
            message = item.message
            stamps.setdefault(item.topic, []).append(message.stamp_ns)
            if isinstance(message, msg.ObjectPose):
                values.setdefault(item.topic, []).append(np.array(message.pose))
                names.setdefault(item.topic, message.object)
            elif isinstance(message, msg.Wrench):
                values.setdefault(item.topic, []).append(np.array(message.wrench))
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
    needed = [f"wrench/{arm}", f"arm_state/{arm}", OBJECT_TOPIC]
    missing = [t for t in needed if t not in topics]
    if missing:
        raise ValueError(f"{path}: recording has no topic {', '.join(missing)}, which the fit needs")
    missing = [t for t in needed if not stamps.get(t)]
    if missing:
        raise ValueError(f"{path}: recording has no message on {', '.join(missing)}, which the fit needs")
    object_name = object_name or names[OBJECT_TOPIC]
    if object_name not in BENCH_OBJECTS:
        raise ValueError(f"{path}: object {object_name!r} is not a benchmark object the fit can replay "
                         f"({', '.join(BENCH_OBJECTS)}); name one with --object")
    wrench_t, state_t, object_t = needed
    order = {t: np.argsort(np.array(stamps[t], dtype=np.int64), kind="stable") for t in needed}
    sorted_stamps = {t: np.array(stamps[t], dtype=np.int64)[order[t]] for t in needed}
    max_gap_ns, period_ns = int(max_gap_s * 1e9), int(period_s * 1e9)
    rows: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # (TCP pose, object pose, wrench)
    dropped, last = 0, None
    for w in order[wrench_t]:
        at = int(stamps[wrench_t][w])
        if last is not None and at - last < period_ns:
            continue
        s, s_gap = _nearest(sorted_stamps[state_t], at)
        o, o_gap = _nearest(sorted_stamps[object_t], at)
        if s_gap > max_gap_ns or (not clamped and o_gap > max_gap_ns):
            dropped += 1
            continue
        object_pose = values[object_t][order[object_t][0] if clamped else order[object_t][o]]
        rows.append((values[state_t][order[state_t][s]], object_pose, values[wrench_t][w]))
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
    return StackTrajectory(info, trajectory, arm, len(rows), dropped)
