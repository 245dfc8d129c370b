"""``hydrosoft-stack bench wrench RECORDINGS...``: how well each contact model predicts the wrench the Soft Bubble
transmits to the wrist (paper V-C, Table II).

Input: recordings of ``hydrosoft-stack collect wrench`` (``wrench_recording``: per step the measured bubble (TCP)
pose, the object's pose and the F/T wrench). Each trajectory is replayed through each model (``--models``, default
nh, pf, pff): the benchmark object's scene (``wrench_scenes.wrench_scene``) at surface spacing ``--spacing``,
starting from the recorded tare pose (out of contact, no force), the bubble and the object moved kinematically to
each recorded pose (``dynamics.advance_forces``, in ``--substeps`` equal pieces per recorded step), and the predicted
wrench on the bubble about its frame's origin, in its frame (``dynamics.body_wrenches``, as sim_world's FT 300
reports it). The measurement is the recorded wrench minus the trajectory's tare sample, moved from the sensor's frame
to the TCP frame (``RecordingInfo.tcp_in_sensor``).

Per trajectory: the RMSE over its steps (the tare sample excluded) of the force error's norm (N), of the torque
error's norm (N m) and of the tangential (TCP x, y) force error's norm (N, the shear the PFF baseline cannot carry);
per object and model the mean and sample standard deviation over trajectories, printed in Table II's layout with
the paper's figures beside ours (the paper reports one "wrench RMSE [N]": we compare its figures with our force
RMSE), then whether the models rank in the paper's order per object. ``--json`` prints one JSON document instead.

On a sim recording the plant is itself an NH model (at the recording's plant spacing, the default ``--spacing``), so
NH's error is only what the replay cannot reproduce: the FT 300's resolution (0.01 N, 0.001 N m), the arm's motion
between the recorded steps (the plant followed the servo path at 50 Hz), and the plant's 50 Hz sampling. NH wins by
construction there; the comparison that means something is the lab's.

Run time: each model replays all of an object's trajectories as one batch (``advance_forces`` with ``B`` =
trajectories); 0.1 s per object and model for 3 trajectories of 20 steps on one shared core.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from hydrosoft.bench.wrench_replay import (
    DEFAULT_SUBSTEPS,
    load_recordings,
    mean_and_std,
    predict_grouped,
    recording_files,
    trajectory_errors,
)

#: Paper Table II, wrench RMSE [N], (mean, std) per object and model.
PAPER_TABLE_II = {
    "plate": {"nh": (0.43, 0.12), "pf": (2.32, 0.66), "pff": (1.25, 0.68)},
    "triangle": {"nh": (0.44, 0.22), "pf": (1.31, 0.40), "pff": (0.97, 0.38)},
    "trapezoid": {"nh": (0.80, 0.28), "pf": (1.65, 0.71), "pff": (1.64, 0.55)},
    "cube": {"nh": (0.57, 0.12), "pf": (0.87, 0.20), "pff": (0.69, 0.23)},
    "cylinder_r15": {"nh": (1.80, 0.50), "pf": (2.64, 0.72), "pff": (1.58, 0.44)},
    "cylinder_r25": {"nh": (1.69, 0.37), "pf": (3.20, 0.85), "pff": (1.75, 0.57)},
}
MODEL_TITLES = {"nh": "NH", "snh": "SNH", "pf": "PF", "pff": "PFF", "nh_pressure_normal": "NH-PN"}
DEFAULT_MODELS = ("nh", "pf", "pff")


def _csv(text: str) -> list[str]:
    return [part.strip() for part in text.split(",") if part.strip()]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``hydrosoft-stack bench wrench``."""
    parser.add_argument("recordings", nargs="+", type=Path,
                        help="wrench-<object>.mcap files of `hydrosoft-stack collect wrench`, or folders of them")
    parser.add_argument("--models", type=_csv, default=list(DEFAULT_MODELS), metavar="M1,M2",
                        help="contact models: nh,snh,pf,pff,nh_pressure_normal (default nh,pf,pff)")
    parser.add_argument("--spacing", type=float, default=None,
                        help="object surface spacing of the models, m (default: the sim plant's, recorded in the "
                             "file; 0.005 for lab recordings)")
    parser.add_argument("--substeps", type=int, default=DEFAULT_SUBSTEPS,
                        help=f"replay steps per recorded step (default {DEFAULT_SUBSTEPS})")
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads (default 1)")
    parser.add_argument("--json", action="store_true", help="print one JSON document instead of the tables")


def evaluate(recordings: Sequence[Path], models: Sequence[str], spacing: float | None = None,
             substeps: int = DEFAULT_SUBSTEPS, progress=None) -> dict:
    """The benchmark's JSON document for ``recordings`` (files or folders of ``wrench-*.mcap``).

    Returns ``{"rows": [...], "trajectories": [...], "ordering": [...], "settings": {...}}``: one row per object and
    model (``force_n_mean``, ``force_n_std``, ``torque_nm_mean``, ``torque_nm_std``, ``shear_n_mean``,
    ``shear_n_std``, ``trajectories``, the paper's ``paper_force_n_mean``/``_std`` where it has them), one entry per
    trajectory and model with its three RMSEs, and per object the models ranked by mean force RMSE, ours and the
    paper's.
    """
    files = recording_files(recordings)
    groups = load_recordings(files, spacing)
    rows, per_trajectory, ordering = [], [], []
    for group in groups:
        name, trajectories = group.object, group.trajectories
        for model in models:
            tic = time.perf_counter()
            predicted = predict_grouped(name, trajectories, model, group.spacing_m, substeps)
            errors = [trajectory_errors(p, m) for p, m in zip(predicted, group.measured)]
            if progress:
                progress(f"{name} {model}: {len(trajectories)} trajectories in {time.perf_counter() - tic:.2f} s")
            row = {"object": name, "model": model, "trajectories": len(errors)}
            for key in ("force_n", "torque_nm", "shear_n"):
                row[f"{key}_mean"], row[f"{key}_std"] = mean_and_std([e[key] for e in errors])
            paper = PAPER_TABLE_II.get(name, {}).get(model)
            row["paper_force_n_mean"], row["paper_force_n_std"] = paper if paper else (None, None)
            rows.append(row)
            per_trajectory += [{"object": name, "model": model, "trajectory": t.index, **e}
                               for t, e in zip(trajectories, errors)]
        ordering.append(_ordering(name, [r for r in rows if r["object"] == name]))
    spacings = {group.object: group.spacing_m for group in groups}
    modes = sorted({mode for group in groups for mode in group.modes})
    return {"rows": rows, "trajectories": per_trajectory, "ordering": ordering,
            "settings": {"recordings": [str(p) for p in files], "models": list(models), "spacing_m": spacings,
                         "substeps": substeps, "modes": modes}}


def _ordering(name: str, rows: list[dict]) -> dict:
    ours = [r["model"] for r in sorted(rows, key=lambda r: r["force_n_mean"])]
    paper_figures = PAPER_TABLE_II.get(name, {})
    paper = [m for m in sorted(paper_figures, key=lambda m: paper_figures[m][0]) if m in ours]
    comparable = len(paper) == len(ours)
    return {"object": name, "ours": ours, "paper": paper if comparable else None,
            "same": (ours == paper) if comparable else None}


# --- output -------------------------------------------------------------------------------------------------------


def rmse_table(title: str, label: str, columns: Sequence[str],
               rows: Sequence[tuple[str, Sequence[tuple[float, float] | None]]], digits: int = 3) -> list[str]:
    """Lines of one RMSE table in Table II's layout: ``title``, a header of ``columns`` (each a mean and a standard
    deviation), then per row its title and its ``(mean, std)`` cells (None prints a dash)."""
    head = f"{label:<14}" + "".join(f"| {c:^13} " for c in columns)
    sub = f"{'':<14}" + "".join(f"| {'Mean':>6}{'Std':>7} " for _ in columns)
    lines = [title, head, sub, "-" * len(sub)]
    for name, cells in rows:
        lines.append(f"{name:<14}" + "".join(f"| {c[0]:>6.{digits}f}{c[1]:>7.{digits}f} " if c else f"| {'-':>13} "
                                             for c in cells))
    return lines


def _mean_std(row: dict | None, key: str) -> tuple[float, float] | None:
    return (row[key + "_mean"], row[key + "_std"]) if row else None



def format_tables(document: dict) -> str:
    """Table II's layout: per object the force RMSE (N) mean and std per model, the paper's beside it; then the
    torque and shear RMSEs; then the ranking per object."""
    from hydrosoft.bench.wrench_scenes import BENCH_OBJECTS

    rows, models = document["rows"], document["settings"]["models"]
    index = {(r["object"], r["model"]): r for r in rows}
    objects = list(dict.fromkeys(r["object"] for r in rows))

    def table(title: str, key: str, with_paper: bool, digits: int = 3) -> list[str]:
        cells = [(BENCH_OBJECTS[name].title, [_mean_std(index.get((name, m)), key) for m in models])
                 for name in objects]
        lines = rmse_table(title, "Object", [MODEL_TITLES.get(m, m) for m in models], cells, digits)
        if with_paper:
            lines[1] += "|| paper " + "".join(f"| {MODEL_TITLES.get(m, m):^11} " for m in models)
            lines[2] += "||       " + "".join(f"| {'Mean':>5}{'Std':>6} " for _ in models)
            lines[3] = "-" * len(lines[2])
            for row, name in enumerate(objects, start=4):
                lines[row] += "||       "
                for m in models:
                    paper = PAPER_TABLE_II.get(name, {}).get(m)
                    lines[row] += f"| {paper[0]:>5.2f}{paper[1]:>6.2f} " if paper else f"| {'-':>11} "
        return lines

    count = max((r["trajectories"] for r in rows), default=0)
    lines = table(f"Wrench RMSE, force [N] (lower is better; up to {count} trajectories per object), "
                  "ours and the paper's Table II", "force_n", True)
    lines += [""] + table("Wrench RMSE, torque [N m]", "torque_nm", False, digits=4)
    lines += [""] + table("Wrench RMSE, tangential force (TCP x, y) [N]", "shear_n", False)
    lines += ["", "Ranking by mean force RMSE (best first):"]
    for entry in document["ordering"]:
        ours = " < ".join(MODEL_TITLES.get(m, m) for m in entry["ours"])
        if entry["paper"] is None:
            lines.append(f"  {BENCH_OBJECTS[entry['object']].title:<14} ours {ours}")
            continue
        paper = " < ".join(MODEL_TITLES.get(m, m) for m in entry["paper"])
        verdict = "same order" if entry["same"] else "DIFFERS"
        lines.append(f"  {BENCH_OBJECTS[entry['object']].title:<14} ours {ours:<16} paper {paper:<16} {verdict}")
    if "sim" in document["settings"]["modes"]:
        lines += ["", "Sim recording: the plant is itself an NH model, so NH wins by construction; its error is the "
                      "FT 300's resolution and what the replay cannot reproduce of the plant's 50 Hz path."]
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    """Run the benchmark; 0, or 2 for a bad option or an unreadable recording."""
    import torch

    bad = [m for m in args.models if m not in MODEL_TITLES]
    if bad or not args.models:
        print(f"bench wrench: unknown contact model(s) {bad}; known: {', '.join(MODEL_TITLES)}", file=sys.stderr)
        return 2
    if args.spacing is not None and not (math.isfinite(args.spacing) and args.spacing > 0):
        print(f"bench wrench: --spacing must be a positive number of metres, got {args.spacing}", file=sys.stderr)
        return 2
    if args.substeps < 1:
        print(f"bench wrench: --substeps must be at least 1, got {args.substeps}", file=sys.stderr)
        return 2
    torch.set_num_threads(args.threads)
    try:
        document = evaluate(args.recordings, args.models, args.spacing, args.substeps,
                            progress=lambda text: print(f"[bench wrench] {text}", file=sys.stderr, flush=True))
    except ValueError as error:
        print(f"bench wrench: {error}", file=sys.stderr)
        return 2
    print(json.dumps(document) if args.json else format_tables(document))
    return 0
