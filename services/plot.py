"""``hydrosoft-stack plot PATH.mcap``: PNG plots of one recorded run.

Written to ``--out`` (default: next to the file, ``STEM-plots/``), time in seconds from the first message:

- ``object_error.png``: the planner's error of the tracked object against its goal (``StatusReply.error_mm``, ADD,
  mm) and, against the goal's target pose, the position error of the tracked (``object_pose``) and, in sim, the true
  object (``eval/object_pose``), mm;
- ``contact_forces.png``: per compliant body, the magnitude of the total contact force the plan predicts
  (``Plan.predicted_forces``), the simulation's true one (``eval/contact_forces``), and each F/T sensor's
  measured force (``wrench/ARM``), N;
- ``planner.png``: each plan's solve time (ms) and the plan rate (plans per second, each from the spacing of two
  plans' stamps);
- ``events.png``: per service, its error counts by kind over time (from ``status/SERVICE``) with the times it
  went degraded or stopping, and each arm's watchdog stops (``ArmState.servo_active`` turning false, with the
  reason).

The series are plain functions of the recorded messages (``series``), tested without plotting. A file cut short by
a crash is plotted up to its last complete chunk.
"""

from __future__ import annotations

import argparse
import sys
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hydrosoft.services import messages as msg
from hydrosoft.services.recording import RecordedMessage, RecordingError, read_recording


@dataclass
class Series:
    """Time series of one run, each a list of ``(t_s, value)`` (t from the first message's stamp, s).

    error_mm: planner's ADD error; tracked_mm, true_mm: position error of the tracked and true object against the
    goal; forces: per label (``predicted BODY``, ``true BODY``, ``F/T ARM``) the force magnitude, N; solve_ms, plan_hz:
    per plan; errors: per ``SERVICE: KIND`` the error count; states: ``(t_s, service, state)`` for every change to
    degraded or stopping; stops: ``(t_s, arm, reason)`` for every watchdog stop."""

    error_mm: list[tuple[float, float]] = field(default_factory=list)
    tracked_mm: list[tuple[float, float]] = field(default_factory=list)
    true_mm: list[tuple[float, float]] = field(default_factory=list)
    forces: dict[str, list[tuple[float, float]]] = field(default_factory=lambda: defaultdict(list))
    solve_ms: list[tuple[float, float]] = field(default_factory=list)
    plan_hz: list[tuple[float, float]] = field(default_factory=list)
    errors: dict[str, list[tuple[float, int]]] = field(default_factory=lambda: defaultdict(list))
    states: list[tuple[float, str, str]] = field(default_factory=list)
    stops: list[tuple[float, str, str]] = field(default_factory=list)


def series(messages: Sequence[RecordedMessage]) -> Series:
    """The plotted series of a run's raw messages (in file order)."""
    out = Series()
    if not messages:
        return out
    start_ns = min(item.message.stamp_ns for item in messages)
    goal: np.ndarray | None = None
    bodies: tuple[str, ...] = ()
    last_plan_ns: int | None = None
    last_state: dict[str, str] = {}
    servoing: dict[str, bool] = {}
    for item in sorted(messages, key=lambda i: i.message.stamp_ns):
        m = item.message
        t = (m.stamp_ns - start_ns) * 1e-9
        match m:
            case msg.StatusReply():
                if m.goal is not None and m.goal.target_pose is not None:
                    goal = np.asarray(m.goal.target_pose)
                if m.running:
                    out.error_mm.append((t, m.error_mm))
            case msg.ObjectPose() if goal is not None:
                out.tracked_mm.append((t, 1e3 * float(np.linalg.norm(m.pose[:3] - goal[:3]))))
            case msg.EvalObjectPose() if goal is not None:
                out.true_mm.append((t, 1e3 * float(np.linalg.norm(m.pose[:3] - goal[:3]))))
            case msg.EvalContactForces():
                bodies = m.bodies
                for body, force in zip(m.bodies, m.forces):
                    out.forces[f"true {body}"].append((t, float(np.linalg.norm(force.sum(axis=0)))))
            case msg.Plan():
                for index, force in enumerate(np.asarray(m.predicted_forces, dtype=np.float64)):
                    name = bodies[index] if len(bodies) == len(m.predicted_forces) else f"body {index}"
                    out.forces[f"predicted {name}"].append((t, float(np.linalg.norm(force.sum(axis=0)))))
                out.solve_ms.append((t, m.solve_ms))
                if last_plan_ns is not None and m.stamp_ns > last_plan_ns:
                    out.plan_hz.append((t, 1e9 / (m.stamp_ns - last_plan_ns)))
                last_plan_ns = m.stamp_ns
            case msg.Wrench():
                out.forces[f"F/T {m.sensor}"].append((t, float(np.linalg.norm(m.wrench[:3]))))
            case msg.ServiceStatus():
                service = item.topic.partition("/")[2]
                for kind, count in m.errors.items():
                    out.errors[f"{service}: {kind}"].append((t, count))
                if m.state != last_state.get(service) and m.state in ("degraded", "stopping"):
                    out.states.append((t, service, m.state))
                last_state[service] = m.state
            case msg.ArmState():
                if servoing.get(m.arm, False) and not m.servo_active:
                    out.stops.append((t, m.arm, m.stop_reason))
                servoing[m.arm] = m.servo_active
    return out


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

    figure, axis = plt.subplots(figsize=(8, 4))
    for label, points in run.errors.items():
        t, v = zip(*points)
        axis.step(t, v, where="post", label=label, linewidth=1)
    for t, service, state in run.states:
        axis.axvline(t, color="orange" if state == "degraded" else "grey", linewidth=0.8, linestyle="--")
        axis.annotate(f"{service} {state}", (t, 0), rotation=90, fontsize=6, va="bottom")
    for t, arm, reason in run.stops:
        axis.axvline(t, color="red", linewidth=1)
        axis.annotate(f"{arm} stop: {reason}", (t, 0), rotation=90, fontsize=6, va="bottom", color="red")
    axis.set_ylabel("errors so far")
    axis.set_xlabel("t, s")
    axis.grid(alpha=0.3)
    if run.errors:
        axis.legend(fontsize=7, loc="upper left")
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
        messages, reader = read_recording(args.recording)
    except RecordingError as error:
        print(f"hydrosoft-stack plot: {error}", file=sys.stderr)
        return 2
    out_dir = args.out or args.recording.with_name(f"{args.recording.stem}-plots")
    for path in write_plots(series(messages), out_dir, args.recording.name):
        print(path)
    if reader.truncated:
        print(f"the file ends early (a crashed recorder?): plotted up to its last complete chunk ({reader.error})")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m hydrosoft.services.plot", description=__doc__.split("\n")[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
