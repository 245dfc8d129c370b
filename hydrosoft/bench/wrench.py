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
import statistics
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

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
DEFAULT_SUBSTEPS = 1  # on sim recordings 1, 4 and 8 agree within 1e-4 N: the arm's path between samples is straight


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


# --- frames and errors (numpy) --------------------------------------------------------------------------------------


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix ``(3, 3)`` of a unit quaternion ``(4,)`` wxyz."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def sensor_to_tcp(wrenches: np.ndarray, tcp_in_sensor: Sequence[float]) -> np.ndarray:
    """Wrenches ``(..., 6)`` [N, N m] about the sensor's origin in its frame, moved to about the TCP's origin in the TCP
    frame; ``tcp_in_sensor (7,)`` is the TCP frame's pose in the sensor frame (m, wxyz)."""
    pose = np.asarray(tcp_in_sensor, dtype=np.float64)
    R, p = quat_to_matrix(pose[3:]), pose[:3]
    force, torque = wrenches[..., :3], wrenches[..., 3:]
    return np.concatenate([force @ R, (torque - np.cross(p, force)) @ R], axis=-1)


def rmse(errors: np.ndarray) -> float:
    """Root mean square over rows of the row norms of ``errors (K, d)``."""
    return float(np.sqrt(np.mean(np.sum(np.square(errors), axis=-1))))


def trajectory_errors(predicted: np.ndarray, measured: np.ndarray) -> dict[str, float]:
    """RMSEs of one trajectory over its rows 1..K (row 0 is the tare), wrenches ``(K + 1, 6)`` in the TCP frame:
    ``force_n`` (3-vector), ``torque_nm`` (3-vector), ``shear_n`` (the TCP-frame x, y force)."""
    error = predicted[1:] - measured[1:]
    return {"force_n": rmse(error[:, :3]), "torque_nm": rmse(error[:, 3:]), "shear_n": rmse(error[:, :2])}


def mean_and_std(values: Sequence[float]) -> tuple[float, float]:
    """Mean and sample standard deviation (0 for one value)."""
    return statistics.fmean(values), statistics.stdev(values) if len(values) > 1 else 0.0


# --- the replay (torch) -------------------------------------------------------------------------------------------


def predict_tcp_wrenches(object_name: str, object_poses: np.ndarray, bubble_poses: np.ndarray, contact: str,
                         spacing: float, substeps: int = DEFAULT_SUBSTEPS) -> np.ndarray:
    """Replay a batch of trajectories of one object through contact model ``contact``.

    Args:
        object_name: a ``wrench_scenes.BENCH_OBJECTS`` key.
        object_poses, bubble_poses: ``(B, K + 1, 7)`` world poses per trajectory and step (m, wxyz); row 0 must be
            out of contact (the replay starts there without force).
        contact: ``nh``, ``snh``, ``pf`` or ``pff``.
        spacing: the object's surface spacing (m).
        substeps: ``dynamics.advance_forces`` calls per recorded step, at equally spaced poses between the two
            recorded ones (straight line, shortest rotation).

    Returns:
        ``(B, K + 1, 6)`` float64: the predicted wrench on the bubble [N, N m] about its frame's origin, in its frame.
    """
    import torch

    from hydrosoft.bench.wrench_scenes import wrench_scene
    from hydrosoft.dynamics import advance_forces, body_wrenches, press_in
    from hydrosoft.geometry import se3
    from hydrosoft.scene import compile_scene

    if substeps < 1:
        raise ValueError(f"substeps must be at least 1, got {substeps}")
    objects = torch.as_tensor(np.asarray(object_poses), dtype=torch.float64)
    bubbles = torch.as_tensor(np.asarray(bubble_poses), dtype=torch.float64)
    scene = wrench_scene(object_name, contact, spacing, object_pose=objects[0, 0].tolist(),
                         bubble_pose=bubbles[0, 0].tolist())
    model, _, _ = compile_scene(scene)
    state = press_in(model, objects[:, 0], bubbles[:, 0:1])

    def tcp_wrench(state) -> torch.Tensor:
        w = body_wrenches(model, state)[:, 0]
        R = se3.quat_to_matrix(state.body_poses[:, 0, 3:])
        return torch.cat([(R.mT @ w[:, :3, None])[..., 0], (R.mT @ w[:, 3:, None])[..., 0]], dim=-1)

    def delta(start: torch.Tensor, end: torch.Tensor) -> torch.Tensor:
        turn = se3.quat_multiply(end[..., 3:], se3.quat_conjugate(start[..., 3:]))
        return torch.cat([end[..., :3] - start[..., :3], se3.so3_log(turn)], dim=-1)

    out = [tcp_wrench(state)]
    with torch.no_grad():
        for k in range(1, bubbles.shape[1]):
            d_object, d_bubble = delta(objects[:, k - 1], objects[:, k]), delta(bubbles[:, k - 1], bubbles[:, k])
            for j in range(1, substeps + 1):
                fraction = j / substeps
                object_pose = se3.retract(objects[:, k - 1], fraction * d_object)
                bubble_pose = se3.retract(bubbles[:, k - 1], fraction * d_bubble)
                state = advance_forces(model, state, object_pose, bubble_pose.unsqueeze(1))
            out.append(tcp_wrench(state))
    return torch.stack(out, dim=1).numpy()


def measured_tcp_wrenches(wrenches: np.ndarray, tcp_in_sensor: Sequence[float]) -> np.ndarray:
    """Measured wrenches ``(K + 1, 6)`` (sensor frame) minus the tare row 0, in the TCP frame about its origin."""
    return sensor_to_tcp(wrenches - wrenches[0], tcp_in_sensor)


def evaluate(recordings: Sequence[Path], models: Sequence[str], spacing: float | None = None,
             substeps: int = DEFAULT_SUBSTEPS, progress=None) -> dict:
    """The benchmark's JSON document for ``recordings`` (files or folders of ``wrench-*.mcap``).

    Returns ``{"rows": [...], "trajectories": [...], "ordering": [...], "settings": {...}}``: one row per object and
    model (``force_n_mean``, ``force_n_std``, ``torque_nm_mean``, ``torque_nm_std``, ``shear_n_mean``,
    ``shear_n_std``, ``trajectories``, the paper's ``paper_force_n_mean``/``_std`` where it has them), one entry per
    trajectory and model with its three RMSEs, and per object the models ranked by mean force RMSE, ours and the
    paper's.
    """
    from hydrosoft.bench.wrench_recording import read_wrench_recording
    from hydrosoft.bench.wrench_scenes import BENCH_OBJECTS, SPACING_M

    files = _recording_files(recordings)
    by_object: dict[str, list] = {}
    infos = {}
    for path in files:
        info, trajectories = read_wrench_recording(path)
        by_object.setdefault(info.object, []).extend(trajectories)
        infos[str(path)] = info
    rows, per_trajectory, ordering = [], [], []
    spacings = {}
    names = [n for n in BENCH_OBJECTS if by_object.get(n)]
    if not names:
        raise ValueError(f"no complete trajectory in {', '.join(str(p) for p in files)}")
    for name in names:
        trajectories = by_object[name]
        info = next(i for i in infos.values() if i.object == name)
        spacing_m = spacing if spacing is not None else (info.plant_spacing_m or SPACING_M)
        spacings[name] = spacing_m
        measured = [measured_tcp_wrenches(t.wrenches, info.tcp_in_sensor) for t in trajectories]
        for model in models:
            tic = time.perf_counter()
            predicted = _predict_grouped(name, trajectories, model, spacing_m, substeps)
            errors = [trajectory_errors(p, m) for p, m in zip(predicted, measured)]
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
    modes = sorted({i.mode for i in infos.values()})
    return {"rows": rows, "trajectories": per_trajectory, "ordering": ordering,
            "settings": {"recordings": [str(p) for p in files], "models": list(models), "spacing_m": spacings,
                         "substeps": substeps, "modes": modes}}


def _recording_files(paths: Sequence[Path]) -> list[Path]:
    files = []
    for path in paths:
        if path.is_dir():
            found = sorted(path.glob("wrench-*.mcap"))
            if not found:
                raise ValueError(f"{path}: no wrench-*.mcap recording in this folder")
            files += found
        elif path.is_file():
            files.append(path)
        else:
            raise ValueError(f"{path}: no such recording")
    return files


def _predict_grouped(name: str, trajectories: list, model: str, spacing: float, substeps: int) -> list[np.ndarray]:
    """Predictions per trajectory, replayed in batches of trajectories of equal length."""
    predicted: list[np.ndarray | None] = [None] * len(trajectories)
    lengths = sorted({len(t.phases) for t in trajectories})
    for length in lengths:
        members = [i for i, t in enumerate(trajectories) if len(t.phases) == length]
        batch = predict_tcp_wrenches(name, np.stack([trajectories[i].object_poses for i in members]),
                                     np.stack([trajectories[i].bubble_poses for i in members]), model, spacing,
                                     substeps)
        for row, i in enumerate(members):
            predicted[i] = batch[row]
    return predicted


def _ordering(name: str, rows: list[dict]) -> dict:
    ours = [r["model"] for r in sorted(rows, key=lambda r: r["force_n_mean"])]
    paper_figures = PAPER_TABLE_II.get(name, {})
    paper = [m for m in sorted(paper_figures, key=lambda m: paper_figures[m][0]) if m in ours]
    comparable = len(paper) == len(ours)
    return {"object": name, "ours": ours, "paper": paper if comparable else None,
            "same": (ours == paper) if comparable else None}


# --- output -------------------------------------------------------------------------------------------------------


def format_tables(document: dict) -> str:
    """Table II's layout: per object the force RMSE (N) mean and std per model, the paper's beside it; then the
    torque and shear RMSEs; then the ranking per object."""
    from hydrosoft.bench.wrench_scenes import BENCH_OBJECTS

    rows, models = document["rows"], document["settings"]["models"]
    index = {(r["object"], r["model"]): r for r in rows}
    objects = list(dict.fromkeys(r["object"] for r in rows))

    def table(title: str, key: str, with_paper: bool, digits: int = 3) -> list[str]:
        head = f"{'Object':<14}" + "".join(f"| {MODEL_TITLES.get(m, m):^13} " for m in models)
        sub = f"{'':<14}" + "".join(f"| {'Mean':>6}{'Std':>7} " for _ in models)
        if with_paper:
            head += "|| paper " + "".join(f"| {MODEL_TITLES.get(m, m):^11} " for m in models)
            sub += "||       " + "".join(f"| {'Mean':>5}{'Std':>6} " for _ in models)
        lines = [title, head, sub, "-" * len(sub)]
        for name in objects:
            line = f"{BENCH_OBJECTS[name].title:<14}"
            for m in models:
                r = index.get((name, m))
                line += f"| {r[key + '_mean']:>6.{digits}f}{r[key + '_std']:>7.{digits}f} " if r else f"| {'-':>13} "
            if with_paper:
                line += "||       "
                for m in models:
                    paper = PAPER_TABLE_II.get(name, {}).get(m)
                    line += f"| {paper[0]:>5.2f}{paper[1]:>6.2f} " if paper else f"| {'-':>11} "
            lines.append(line)
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
