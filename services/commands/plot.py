"""``hydrosoft-stack plot PATH.mcap``: PNG plots of one recorded run.

Written to ``--out`` (default: next to the file, ``STEM-plots/``), time in seconds from the first message's stamp:

- ``object_error.png``: the planner's error of the tracked object against its goal (``StatusReply.error_mm``, ADD,
  mm) and, against the goal's target pose, the position error of the tracked (``object_pose``) and, in sim, the true
  object (``eval/object_pose``), mm;
- ``contact_forces.png``: per compliant body, the magnitude of the total contact force the plan predicts
  (``Plan.predicted_forces``), the simulation's true one (``eval/contact_forces``), and each F/T sensor's
  measured force (``wrench/ARM``), N;
- ``planner.png``: each plan's solve time (ms) and the plan rate (plans per second, each from the spacing of two
  plans' stamps);
- ``events.png``: above, per service, its error counts by kind over time (from ``status/SERVICE``); below, a
  timeline with one lane per cause: each arm's watchdog stops by reason (``ArmState.servo_active`` turning false;
  the holds, ``ArmState.holding``, in one lane of their own: a late target, not a fault)
  and each service's turns to degraded or stopping, a tick per event (darker: several in one time bucket) and the
  lane's total in its label. Hundreds of stops stay readable: they add ticks and counts, not labels.

The file is read as a stream, only the plotted topics decoded, and each series keeps at most ``MAX_BUCKETS`` time
buckets (a series' lowest and highest point in each, which draws the same line at the figure's resolution): memory
stays bounded whatever the file's length. The series are plain functions of the recorded messages (``series``),
tested without plotting. A file cut short by a crash is plotted up to its last complete chunk.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections import defaultdict
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hydrosoft.services.bus import messages as msg
from hydrosoft.services.recording.mcap_format import RecordedMessage, RecordingError, RecordingReader

#: The bus topics the plots read (and their sub-topics); the rest of the file is not decoded.
PLOTTED_TOPICS = ("reply/status", "object_pose", "eval", "plan", "wrench", "status", "arm_state")
#: Most time buckets a series keeps (each holds up to two points): a plot 800 px wide shows no more.
MAX_BUCKETS = 2000
#: Narrowest time bucket, s (widths are this times a power of two, so buckets merge in pairs).
MIN_BUCKET_S = 1e-3
#: Most lanes of the events timeline; further causes share the lane ``OTHER_LANE``.
MAX_LANES = 12
#: The lane of an arm's holds (``ArmState.holding``: the target's deadline passed, every other rule met), whatever
#: how late each target was.
HOLD_LANE = "target deadline passed"
OTHER_LANE = "other causes"


class TimeBuckets:
    """Values over time in at most ``max_buckets`` buckets of equal width: every point while there are at most twice
    as many points as buckets, then the points of each bucket merged (``merge``); the width doubles, and neighbouring
    buckets merge, whenever the buckets run out. A bucket is a tuple whose first item is its first time (s)."""

    def __init__(self, merge, max_buckets: int = MAX_BUCKETS) -> None:
        self.merge = merge
        self.max_buckets = max_buckets
        self.width_s = 0.0  # 0: every point kept as it came
        self._points: list[tuple] = []
        self._buckets: dict[int, tuple] = {}

    def add(self, point: tuple) -> None:
        """Add ``point`` (a bucket of one point: its time first)."""
        if self.width_s:
            self._put(point)
        else:
            self._points.append(point)
            if len(self._points) <= 2 * self.max_buckets:
                return
            times = [p[0] for p in self._points]
            self.width_s = MIN_BUCKET_S * 2.0 ** max(0, math.ceil(math.log2(
                max(max(times) - min(times), MIN_BUCKET_S) / MIN_BUCKET_S / self.max_buckets)))
            points, self._points = self._points, []
            for old in points:
                self._put(old)
        while len(self._buckets) > self.max_buckets:
            self.width_s *= 2
            buckets, self._buckets = self._buckets, {}
            for key, bucket in buckets.items():
                self._merge_into(key // 2, bucket)

    def _put(self, point: tuple) -> None:
        self._merge_into(math.floor(point[0] / self.width_s), point)

    def _merge_into(self, key: int, bucket: tuple) -> None:
        held = self._buckets.get(key)
        self._buckets[key] = bucket if held is None else self.merge(held, bucket)

    def buckets(self) -> list[tuple]:
        """The points (while every point is kept, in the order added) or the buckets in time order."""
        return list(self._points) if not self.width_s else [self._buckets[k] for k in sorted(self._buckets)]


def _envelope_merge(a: tuple, b: tuple) -> tuple:
    low = a[:2] if a[1] <= b[1] else b[:2]
    high = a[2:] if a[3] >= b[3] else b[2:]
    return (*low, *high)


class Envelope:
    """A time series ``(t_s, value)`` kept in ``TimeBuckets``: per bucket its lowest and highest point, as
    ``(t_low, low, t_high, high)``."""

    def __init__(self, max_buckets: int = MAX_BUCKETS) -> None:
        self._buckets = TimeBuckets(_envelope_merge, max_buckets)

    def add(self, t_s: float, value: float) -> None:
        self._buckets.add((t_s, value, t_s, value))

    def points(self) -> list[tuple[float, float]]:
        """The kept points in time order (every point while few)."""
        out: list[tuple[float, float]] = []
        for t_low, low, t_high, high in self._buckets.buckets():
            out.extend(sorted({(t_low, low), (t_high, high)}))
        return out


class Tally:
    """Events over time kept in ``TimeBuckets``: per bucket its first time and how many events fell in it."""

    def __init__(self, max_buckets: int = MAX_BUCKETS) -> None:
        self._buckets = TimeBuckets(lambda a, b: (min(a[0], b[0]), a[1] + b[1]), max_buckets)
        self.total = 0

    def add(self, t_s: float) -> None:
        self._buckets.add((t_s, 1))
        self.total += 1

    def counts(self) -> list[tuple[float, int]]:
        """``(t_s, events)`` per kept bucket (one per event while few)."""
        return self._buckets.buckets()


@dataclass
class Series:
    """Time series of one run, each a list of ``(t_s, value)`` (t from the first message's stamp, s; at most
    ``MAX_BUCKETS`` buckets' lowest and highest points each).

    error_mm: planner's ADD error; tracked_mm, true_mm: position error of the tracked and true object against the
    goal; forces: per label (``predicted BODY``, ``true BODY``, ``F/T ARM``) the force magnitude, N; solve_ms, plan_hz:
    per plan; errors: per ``SERVICE: KIND`` the error count; events: per lane (``ARM stop: REASON``, ``SERVICE
    degraded``, ``SERVICE stopping``) ``(t_s, count)`` of its events (one per event while few), and event_totals:
    each lane's number of events."""

    error_mm: list[tuple[float, float]] = field(default_factory=list)
    tracked_mm: list[tuple[float, float]] = field(default_factory=list)
    true_mm: list[tuple[float, float]] = field(default_factory=list)
    forces: dict[str, list[tuple[float, float]]] = field(default_factory=dict)
    solve_ms: list[tuple[float, float]] = field(default_factory=list)
    plan_hz: list[tuple[float, float]] = field(default_factory=list)
    errors: dict[str, list[tuple[float, float]]] = field(default_factory=dict)
    events: dict[str, list[tuple[float, int]]] = field(default_factory=dict)
    event_totals: dict[str, int] = field(default_factory=dict)


class SeriesBuilder:
    """The plotted series of a run, built one raw message at a time (in file order) in bounded memory."""

    def __init__(self, max_buckets: int = MAX_BUCKETS) -> None:
        def envelopes() -> defaultdict[str, Envelope]:
            return defaultdict(lambda: Envelope(max_buckets))

        self._lines = envelopes()  # error_mm, tracked_mm, true_mm, solve_ms, plan_hz
        self._forces = envelopes()
        self._errors = envelopes()
        self._events: defaultdict[str, Tally] = defaultdict(lambda: Tally(max_buckets))
        self._start_ns: int | None = None
        self._goal: np.ndarray | None = None
        self._bodies: tuple[str, ...] = ()
        self._last_plan_ns: int | None = None
        self._last_state: dict[str, str] = {}
        self._servoing: dict[str, bool] = {}

    def add(self, item: RecordedMessage) -> None:
        """Take one raw message into the series."""
        m = item.message
        if self._start_ns is None:
            self._start_ns = m.stamp_ns
        t = (m.stamp_ns - self._start_ns) * 1e-9
        match m:
            case msg.StatusReply():
                if m.goal is not None and m.goal.target_pose is not None:
                    self._goal = np.asarray(m.goal.target_pose)
                if m.running:
                    self._lines["error_mm"].add(t, m.error_mm)
            case msg.ObjectPose() if self._goal is not None:
                self._lines["tracked_mm"].add(t, 1e3 * float(np.linalg.norm(m.pose[:3] - self._goal[:3])))
            case msg.EvalObjectPose() if self._goal is not None:
                self._lines["true_mm"].add(t, 1e3 * float(np.linalg.norm(m.pose[:3] - self._goal[:3])))
            case msg.EvalContactForces():
                self._bodies = m.bodies
                for body, force in zip(m.bodies, m.forces):
                    self._forces[f"true {body}"].add(t, float(np.linalg.norm(force.sum(axis=0))))
            case msg.Plan():
                for index, force in enumerate(np.asarray(m.predicted_forces, dtype=np.float64)):
                    name = self._bodies[index] if len(self._bodies) == len(m.predicted_forces) else f"body {index}"
                    self._forces[f"predicted {name}"].add(t, float(np.linalg.norm(force.sum(axis=0))))
                self._lines["solve_ms"].add(t, m.solve_ms)
                if self._last_plan_ns is not None and m.stamp_ns > self._last_plan_ns:
                    self._lines["plan_hz"].add(t, 1e9 / (m.stamp_ns - self._last_plan_ns))
                self._last_plan_ns = m.stamp_ns
            case msg.Wrench():
                self._forces[f"F/T {m.sensor}"].add(t, float(np.linalg.norm(m.wrench[:3])))
            case msg.ServiceStatus():
                service = item.topic.partition("/")[2]
                for kind, count in m.errors.items():
                    self._errors[f"{service}: {kind}"].add(t, count)
                if m.state != self._last_state.get(service) and m.state in ("degraded", "stopping"):
                    self._event(f"{service} {m.state}", t)
                self._last_state[service] = m.state
            case msg.ArmState():
                if self._servoing.get(m.arm, False) and not m.servo_active:
                    self._event(f"{m.arm} hold: {HOLD_LANE}" if m.holding else f"{m.arm} stop: {m.stop_reason}", t)
                self._servoing[m.arm] = m.servo_active

    def _event(self, lane: str, t: float) -> None:
        if lane not in self._events and len(self._events) >= MAX_LANES - 1:
            lane = OTHER_LANE
        self._events[lane].add(t)

    def result(self) -> Series:
        """The series so far."""
        return Series(
            **{name: self._lines[name].points() for name in ("error_mm", "tracked_mm", "true_mm", "solve_ms",
                                                              "plan_hz")},
            forces={label: line.points() for label, line in self._forces.items()},
            errors={label: line.points() for label, line in self._errors.items()},
            events={lane: tally.counts() for lane, tally in self._events.items()},
            event_totals={lane: tally.total for lane, tally in self._events.items()})


def series(messages: Iterable[RecordedMessage], max_buckets: int = MAX_BUCKETS) -> Series:
    """The plotted series of a run's raw messages (in file order), read one at a time."""
    builder = SeriesBuilder(max_buckets)
    for item in messages:
        builder.add(item)
    return builder.result()


def _plot_lines(axis, lines: dict[str, list[tuple[float, float]]], ylabel: str) -> None:
    for label, points in lines.items():
        if points:
            t, v = zip(*points)
            axis.plot(t, v, label=label, linewidth=1)
    axis.set_ylabel(ylabel)
    axis.grid(alpha=0.3)
    if any(lines.values()):
        axis.legend(fontsize=7, loc="best")


def write_plots(run: Series, out_dir: Path, title: str) -> list[Path]:
    """The four PNGs of ``run`` in ``out_dir`` (created); their paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    written = []

    def save(figure, name: str) -> None:
        figure.suptitle(f"{title}: {name.removesuffix('.png').replace('_', ' ')}", fontsize=9)
        figure.tight_layout()
        figure.savefig(out_dir / name, dpi=100)
        plt.close(figure)
        written.append(out_dir / name)

    figure, axis = plt.subplots(figsize=(8, 4))
    _plot_lines(axis, {"planner ADD error (tracked)": run.error_mm, "tracked position error": run.tracked_mm,
                       "true position error (sim)": run.true_mm}, "error to goal, mm")
    axis.set_xlabel("t, s")
    save(figure, "object_error.png")

    figure, axis = plt.subplots(figsize=(8, 4))
    _plot_lines(axis, dict(run.forces), "total contact force, N")
    axis.set_xlabel("t, s")
    save(figure, "contact_forces.png")

    figure, (solve, rate) = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
    _plot_lines(solve, {"solve time": run.solve_ms}, "ms")
    _plot_lines(rate, {"plan rate": run.plan_hz}, "plans/s")
    rate.set_xlabel("t, s")
    save(figure, "planner.png")

    lanes = sorted(run.events, key=lambda lane: -run.event_totals[lane])
    figure, (errors, timeline) = plt.subplots(2, 1, figsize=(8, 3 + 0.3 * max(len(lanes), 2)), sharex=True,
                                              height_ratios=(2, max(len(lanes), 1) * 0.4 + 0.6))
    for label, points in run.errors.items():
        t, v = zip(*points)
        errors.step(t, v, where="post", label=label, linewidth=1)
    errors.set_ylabel("errors so far")
    errors.grid(alpha=0.3)
    if run.errors:
        errors.legend(fontsize=7, loc="upper left")
    most = max((count for lane in lanes for _, count in run.events[lane]), default=1)
    for row, lane in enumerate(lanes):
        t, counts = zip(*run.events[lane])
        color = "red" if " stop: " in lane else "orange" if lane.endswith("degraded") else "grey"
        timeline.scatter(t, [row] * len(t), marker="|", s=120, color=color,
                         alpha=[0.35 + 0.65 * count / most for count in counts], linewidths=1)
    timeline.set_yticks(range(len(lanes)), [f"{lane} ({run.event_totals[lane]})" for lane in lanes], fontsize=7)
    timeline.set_ylim(-0.7, max(len(lanes), 1) - 0.3)
    timeline.invert_yaxis()
    timeline.set_xlabel("t, s")
    timeline.grid(alpha=0.3, axis="x")
    if not lanes:
        timeline.text(0.5, 0.5, "no stops", transform=timeline.transAxes, ha="center", va="center", fontsize=8)
    save(figure, "events.png")
    return written


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments: PATH.mcap [--out DIR]."""
    parser.add_argument("recording", type=Path, help="an MCAP file written by the recorder")
    parser.add_argument("--out", type=Path, default=None, help="folder for the PNGs (default STEM-plots/ beside it)")


def run(args: argparse.Namespace) -> int:
    """Run ``hydrosoft-stack plot``; the exit code (2: an unreadable file)."""
    try:
        if not args.recording.is_file():
            raise RecordingError(f"{args.recording} does not exist")
        reader = RecordingReader(args.recording, PLOTTED_TOPICS)
        run_series = series(reader)
    except RecordingError as error:
        print(f"hydrosoft-stack plot: {error}", file=sys.stderr)
        return 2
    out_dir = args.out or args.recording.with_name(f"{args.recording.stem}-plots")
    for path in write_plots(run_series, out_dir, args.recording.name):
        print(path)
    if reader.truncated:
        print(f"the file ends early (a crashed recorder?): plotted up to its last complete chunk ({reader.error})")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m hydrosoft.services.commands.plot", description=__doc__.split("\n")[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
