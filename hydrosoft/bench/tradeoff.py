"""``hydrosoft-stack bench tradeoff``: solve time against closed-loop error over the planner's knobs.

From a base planner (the ``bench control --quick`` one: spacing 12.5 mm, B = 16, 4 elites, K = 6, G = 1, exact
NH, float64, one integration sub-step per compiled sub-step), one knob at a time is swept:

- ``samples`` B: 8, 16, 32, 64;  ``grad_steps`` G: 0, 1, 2;  ``horizon`` K: 4, 6, 10;
- ``spacing`` (m): 0.0167, 0.0125, 0.0084;  ``dt``: the planner's integration step as a fraction of the
  compiled one, 1 or 1/2 (``substep_factor`` 1, 2);  ``dtype``: float64, float32;  ``model``: nh, snh (smoothed);
  ``sdf_solver_steps``: the bubble ellipsoid solved to convergence or in 2 fixed steps;  ``object_update``:
  explicit (sub-stepped as the scene's contacts need) or linearly implicit (one sub-step per step).

Every setting runs goals ``0 .. --goals - 1`` (default 5) of a fixed small task set closed loop on the finer NH
plant (default planar pushing and planar rotation, ``--quick``: planar rotation, goal 0, fewer values). Reported
per setting: the mean solve time (ms) and the mean and standard error of the final ADD error (mm) over all its
episodes; the Pareto front (no other setting is both faster and more accurate on the mean) is marked. One goal
per setting is too noisy to rank settings: run several, and read differences smaller than the standard errors
as ties. Tasks can run as separate processes (``--tasks pushing`` ...) to use both cores. ``--settings`` runs only
the named rows (``base``, or ``knob=value`` as the table labels them, e.g. ``model=nh_pressure_normal``). Output: a
table (or ``--json``: one JSON document ``{"points": [...], "pareto": [...]}``), a PNG ``tradeoff.png`` in
``--out``, progress on stderr. Runs single-threaded by default (``--threads``; see ``bench control``).
``--compile`` runs every setting's planner step through ``torch.compile`` (``PlannerSettings.compile``); each
setting is compiled by a one-step warm-up episode first (about a minute per setting on a CPU), so the reported solve
times are steady-state ones.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

BASE = {"spacing": 0.0125, "samples": 16, "elites": 4, "horizon": 6, "grad_steps": 1}
SWEEP = {
    "samples": [8, 16, 32, 64],
    "grad_steps": [0, 1, 2],
    "horizon": [4, 6, 10],
    "spacing": [0.0167, 0.0125, 0.0084],
    "dt": [1, 2],
    "dtype": ["float64", "float32"],
    "model": ["nh", "snh", "nh_pressure_normal"],
    "sdf_solver_steps": [None, 2],
    "object_update": ["explicit", "linearly_implicit"],
}
QUICK_SWEEP = {"samples": [8, 16], "grad_steps": [0, 1], "dtype": ["float64", "float32"],
               "model": ["nh", "snh", "nh_pressure_normal"]}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Register the benchmark's options on ``parser``."""
    parser.add_argument("--tasks", default="pushing,rotation", help="task set (default pushing,rotation)")
    parser.add_argument("--settings", type=lambda text: [t.strip() for t in text.split(",") if t.strip()],
                        default=None, metavar="S1,S2",
                        help="only these rows: 'base' or KNOB=VALUE as labelled in the table, e.g. "
                             "base,model=nh_pressure_normal (default: every row). Run time, one thread, goals 0-4 of "
                             "pushing and rotation: about 1-2 min per row and 19 min for all on the idle 2-core "
                             "machine; under heavy load the base row alone took 45 min")
    parser.add_argument("--quick", action="store_true", help="planar rotation only and fewer values (CI)")
    parser.add_argument("--json", action="store_true", help="print exactly one JSON document instead of the table")
    parser.add_argument("--out", type=Path, default=Path("out/bench-tradeoff"), help="folder for the PNG")
    parser.add_argument("--goals", type=int, default=None, help="seeded goals per task and setting (default 5, quick 1)")
    parser.add_argument("--steps", type=int, default=None, help="control steps per episode (default: the task's)")
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads (default 1)")
    parser.add_argument("--compile", action="store_true",
                        help="planner step through torch.compile, compiled by an untimed one-step warm-up per setting")


def rows(sweep: dict) -> list[tuple[str, object]]:
    """The sweep's rows as ``(knob, value)``, the base planner first as ``("base", None)``."""
    return [("base", None)] + [(knob, value) for knob, values in sweep.items() for value in values]


def label(knob: str, value) -> str:
    """A row's label in the table and for ``--settings``: ``base`` or ``knob=value``."""
    return "base" if knob == "base" else f"{knob}={value}"


def _settings(knob: str, value, compile: bool = False):
    """PlannerSettings with ``knob`` set to ``value`` on top of BASE (and ``compile``); knob ``base``: BASE."""
    import torch

    from hydrosoft.tasks.evaluation import PlannerSettings

    fields = dict(BASE, compile=compile)
    if knob == "base":
        pass
    elif knob == "dt":
        fields["substep_factor"] = value
    elif knob == "dtype":
        fields["dtype"] = getattr(torch, value)
    else:
        fields[knob] = value
    return PlannerSettings(**fields)


def pareto(points: list[dict]) -> list[dict]:
    """The settings no other one beats on both solve time and error (ties kept), fastest first."""
    front = [p for p in points if not any(
        q["solve_ms"] <= p["solve_ms"] and q["error_mm"] <= p["error_mm"]
        and (q["solve_ms"] < p["solve_ms"] or q["error_mm"] < p["error_mm"]) for q in points)]
    return sorted(front, key=lambda p: p["solve_ms"])


def _plot(points: list[dict], front: list[dict], out: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for p in points:
        ax.scatter(p["solve_ms"], p["error_mm"], color="tab:blue" if p in front else "tab:gray")
        ax.annotate(p["label"], (p["solve_ms"], p["error_mm"]), fontsize=7)
    ax.plot([p["solve_ms"] for p in front], [p["error_mm"] for p in front], color="tab:blue", lw=1)
    ax.set_xlabel("mean solve time [ms]")
    ax.set_ylabel("closed-loop final ADD error [mm]")
    ax.set_title("planner trade-off (Pareto front in blue)")
    fig.tight_layout()
    out.mkdir(parents=True, exist_ok=True)
    path = out / "tradeoff.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def run(args: argparse.Namespace) -> int:
    """Run the sweep; returns the process exit status (2 for an unknown task)."""
    import torch

    from hydrosoft.bench.control import mean_and_std
    from hydrosoft.tasks import TASKS, make_task
    from hydrosoft.tasks.evaluation import prepare, run_episode

    names = ["rotation"] if args.quick else [t.strip() for t in args.tasks.split(",") if t.strip()]
    if not names or any(t not in TASKS for t in names):
        print(f"bench tradeoff: unknown task in {args.tasks!r}; known: {', '.join(TASKS)}", file=sys.stderr)
        return 2
    torch.set_num_threads(args.threads)
    sweep = QUICK_SWEEP if args.quick else SWEEP
    goals = args.goals if args.goals is not None else (1 if args.quick else 5)
    runs = rows(sweep)
    if args.settings is not None:
        known = {label(knob, value): (knob, value) for knob, value in runs}
        unknown = [text for text in args.settings if text not in known]
        if unknown or not args.settings:
            print(f"bench tradeoff: unknown setting in {','.join(args.settings)!r}; known: {', '.join(known)}",
                  file=sys.stderr)
            return 2
        runs = [known[text] for text in args.settings]
    seen, points = set(), []
    for i, (knob, value) in enumerate(runs, 1):
        settings = _settings(knob, value, args.compile)
        if settings in seen:
            continue
        seen.add(settings)
        errors, solve = [], []
        for name in names:
            task = make_task(name, args.steps)
            tic = time.perf_counter()
            setup = prepare(task, settings)
            if args.compile:
                run_episode(setup, task.sample_goal(0), "closed", steps=1)
            for goal in range(goals):
                result = run_episode(setup, task.sample_goal(goal), "closed")
                errors.append(result.error_mm)
                solve.append(result.solve_s)
            print(f"[{i}/{len(runs)}] {label(knob, value)} {name}: {sum(errors[-goals:]) / goals:.2f} mm over {goals} "
                  f"goal(s), {1e3 * sum(solve[-goals:]) / goals:.0f} ms per solve, {time.perf_counter() - tic:.1f} s",
                  file=sys.stderr, flush=True)
        mean, spread = mean_and_std(errors)
        points.append({"knob": knob, "value": value, "label": label(knob, value), "episodes": len(errors),
                       "solve_ms": 1e3 * sum(solve) / len(solve), "error_mm": mean,
                       "error_mm_sem": spread / len(errors) ** 0.5})
    front = pareto(points)
    png = _plot(points, front, args.out)
    if args.json:
        print(json.dumps({"tasks": names, "goals": goals, "base": BASE, "points": points, "pareto": [p["label"] for p in front],
                          "png": str(png)}))
    else:
        print(f"tasks {', '.join(names)}, goals 0..{goals - 1}, closed loop; base {BASE}")
        print(f"{'setting':<24}{'solve ms':>10}{'error mm':>10}{'+-sem':>8}  pareto")
        for p in sorted(points, key=lambda p: p["solve_ms"]):
            print(f"{p['label']:<24}{p['solve_ms']:>10.1f}{p['error_mm']:>10.2f}{p['error_mm_sem']:>8.2f}  "
                  f"{'*' if p in front else ''}")
        print(f"figure: {png}")
    return 0
