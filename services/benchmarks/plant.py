"""``hydrosoft-stack bench plant``: what one sim_world physics tick costs, eager against compiled (``sim.compile``).

The plant of a stack config (``sim_world.SimPlant``: the task scene at the plant's spacing, one step per tick of
``1 / sim.rate_hz`` s) is driven through the same scripted stroke in each mode: every arm's TCP moves ``--stroke-mm``
along base x, one ``STEP_MM`` per tick, and back. The first ``WARM_TICKS`` ticks are not timed (a compiled plant
compiles on its first tick). One torch thread, as in sim_world.

Each row (one mode): ``ms_per_tick`` (median) and ``p95_ms`` of ``SimPlant.step_to`` (the step and the snapshot
the services read), ``ticks``, ``first_tick_s`` (the compilation, for the compiled mode), ``object_travel_mm`` (how
far the stroke pushed the object) and ``max_pose_diff`` (object pose against the eager mode's, same tick; 0 for
eager). ``speedup`` is the eager median over the compiled one, measured in the same run. ``--json`` prints
``{"config": {...}, "rows": [...], "speedup": ...}``; otherwise a table. Progress goes to stderr.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time

import numpy as np
import torch

from hydrosoft.services.bus.config import load_config
from hydrosoft.services.sim_world import TORCH_THREADS, SimPlant, plant_model

STEP_MM = 1.0  # TCP travel per tick along base x, mm
WARM_TICKS = 3
MODES = ("eager", "compiled")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``hydrosoft-stack bench plant``."""
    parser.add_argument("config", nargs="?", default="deploy/sim.toml",
                        help="a sim-mode stack config (default deploy/sim.toml); its scene, spacing and rate")
    parser.add_argument("--modes", default=",".join(MODES), help="eager,compiled (default both)")
    parser.add_argument("--stroke-mm", type=float, default=20.0,
                        help=f"TCP travel out and back along base x, mm (default 20: {2 * 20 / STEP_MM:.0f} ticks)")
    parser.add_argument("--json", action="store_true", help='print one JSON document {"config", "rows", "speedup"}')


def stroke(plant: SimPlant, stroke_mm: float) -> list[dict[str, np.ndarray]]:
    """The TCP poses of every tick of the stroke: out ``stroke_mm`` along base x and back (``(7,)`` per arm)."""
    start = {arm: pose.copy() for arm, pose in plant.snapshot.tcp_poses.items()}
    out = np.arange(1, int(round(stroke_mm / STEP_MM)) + 1) * STEP_MM * 1e-3
    ticks = []
    for dx in np.concatenate([out, out[::-1][1:], [0.0]]):
        poses = {arm: pose.copy() for arm, pose in start.items()}
        for pose in poses.values():
            pose[0] += dx
        ticks.append(poses)
    return ticks


def run_mode(config, compiled: bool, stroke_mm: float) -> tuple[dict, list[np.ndarray]]:
    """One mode's row and the object pose after every tick."""
    model, state = plant_model(config)
    plant = SimPlant(model, state, [arm.name for arm in config.arms], compiled)
    start = plant.snapshot.object_pose.copy()
    times, poses = [], []
    first_tick_s = 0.0
    for k, tcp in enumerate(stroke(plant, stroke_mm)):
        tic = time.perf_counter()
        plant.step_to(tcp)
        elapsed = time.perf_counter() - tic
        if k == 0:
            first_tick_s = elapsed
        if k >= WARM_TICKS:
            times.append(elapsed)
        poses.append(plant.snapshot.object_pose.copy())
    travel = max(float(np.linalg.norm(p[:3] - start[:3])) for p in poses)
    ms = sorted(1e3 * t for t in times)
    row = {"mode": "compiled" if compiled else "eager", "ticks": len(times), "ms_per_tick": statistics.median(ms),
           "p95_ms": ms[min(len(ms) - 1, int(0.95 * len(ms)))], "first_tick_s": first_tick_s,
           "object_travel_mm": 1e3 * travel}
    if plant.compiled_step is not None and not plant.compiled_step.compiled:
        row["fallback"] = plant.compiled_step.fallback_reason
    return row, poses


def run(args: argparse.Namespace) -> int:
    """Run the benchmark described by ``args`` (see ``add_arguments``); returns the exit status."""
    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    unknown = sorted(set(modes) - set(MODES))
    if unknown or not modes:
        print(f"bench plant: unknown --modes {unknown or modes} (choose from {', '.join(MODES)})", file=sys.stderr)
        return 2
    if args.stroke_mm < 2 * STEP_MM * (WARM_TICKS + 1):
        print(f"bench plant: --stroke-mm must be at least {2 * STEP_MM * (WARM_TICKS + 1)}", file=sys.stderr)
        return 2
    config = load_config(args.config)
    torch.set_num_threads(TORCH_THREADS)
    rows, reference = [], None
    for mode in modes:
        print(f"bench plant: {mode} plant of {args.config} ({config.scene.task})", file=sys.stderr, flush=True)
        row, poses = run_mode(config, mode == "compiled", args.stroke_mm)
        if reference is None:
            reference = poses
        row["max_pose_diff"] = max(float(np.abs(a - b).max()) for a, b in zip(poses, reference))
        rows.append(row)
    by_mode = {row["mode"]: row for row in rows}
    speedup = (by_mode["eager"]["ms_per_tick"] / by_mode["compiled"]["ms_per_tick"]
               if {"eager", "compiled"} <= by_mode.keys() else None)
    summary = {"config": {"file": args.config, "task": config.scene.task, "rate_hz": config.sim.rate_hz,
                          "spacing_factor": config.sim.spacing_factor, "stroke_mm": args.stroke_mm},
               "rows": rows, "speedup": speedup}
    if args.json:
        print(json.dumps(summary))
        return 0
    print(f"{'mode':<9} {'ticks':>5} {'ms/tick':>8} {'p95 ms':>7} {'first tick s':>12} {'travel mm':>9} "
          f"{'max diff':>9}")
    for row in rows:
        print(f"{row['mode']:<9} {row['ticks']:>5} {row['ms_per_tick']:>8.2f} {row['p95_ms']:>7.2f} "
              f"{row['first_tick_s']:>12.1f} {row['object_travel_mm']:>9.2f} {row['max_pose_diff']:>9.1e}")
    if speedup is not None:
        print(f"compiled is {speedup:.1f}x faster per tick (same run)")
    return 0
