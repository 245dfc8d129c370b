"""``hydrosoft-stack fit RECORDINGS... --model nh|pf|nh_pressure_normal --params E,K,mu``: the Soft Bubble's
material identified from ``collect wrench`` recordings.

The recordings' trajectories are split into a fit set and a held-out set (``--holdout``, ``--seed``); the material is
fitted on the first (``material_fit.fit_material``: L-BFGS through the differentiable replay, uncertainty from the
Gauss-Newton covariance at the optimum, with ``--uncertainty bootstrap`` from a parametric bootstrap, ``fit_bootstrap``,
or with ``--uncertainty profile`` its intervals from the profile likelihood, ``fit_profile``); then the force, torque
and tangential RMSE of both sets are printed before (start material) and after, in ``bench wrench``'s layout, with the
fitted values, their uncertainty and which are not identified. ``--out PARAMS.toml`` writes the fitted material as an
``[arms.material]`` table for an arm of a stack config (``deploy/*.toml``); its E, K and mu lines also fit a scene's
bubble ``[[bodies]]`` table. The recordings are only read. ``--pose-offset`` fits a constant object position offset (m,
base frame) jointly with the material, a nuisance parameter for a tracker's constant error (``material_fit`` module
docstring): one offset for all the recordings given, so fit one recording at a time when each has its own.

Run time: about 5 s for 6 trajectories of 12 steps on one shared core (each cost evaluation replays the fit set
forward and backward; L-BFGS needs 20 to 70 of them); the bootstrap adds one refit per draw (7 to 30 evaluations
each); the profile adds 2 to 8 refits of the other parameters per fitted parameter (1.7 to 3.6 times the fit's
evaluations, docs/fit.md); ``--pose-offset`` takes 2 to 5 times the evaluations of the material alone. Progress goes
to stderr.
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from hydrosoft.bench.material_parameters import DEFAULT_DRAWS, FIT_MODELS, PARAMETERS, UNCERTAINTY_METHODS, UNITS
from hydrosoft.bench.wrench_replay import mean_and_std

SETS = ("fit", "held_out")
UNCERTAINTY_TEXT = {
    "hessian": "gauss-newton: covariance s2 (J^T J)^-1 of the residuals' Jacobian at the optimum, scaled by the "
               "reduced chi-square; sigma by the delta method, interval95 in the log (E, K) or logit (mu) "
               "coordinates",
    "bootstrap": "parametric bootstrap: refits on the fit set replayed at the fitted material with fresh FT 300 noise "
                 "at the level the residuals show; sigma the draws' standard deviation, interval95 the {interval} "
                 "interval of the draws (bootstrap.intervals95 has both kinds); parameters the data do not "
                 "determine keep the Gauss-Newton verdict",
    "profile": "profile likelihood: interval95 where the cost, minimised over the other parameters, rises by at most "
               "1.96^2 times the reduced chi-square; sigma and the identified verdict are Gauss-Newton's; parameters "
               "the data do not determine keep the Gauss-Newton verdict",
}
UNCERTAINTY_TITLE = {"hessian": "Gauss-Newton at the optimum", "bootstrap": "parametric bootstrap",
                     "profile": "profile-likelihood intervals, Gauss-Newton sigma"}
SET_TITLES = {"fit": "fit", "held_out": "held-out"}


def _csv(text: str) -> list[str]:
    return [part.strip() for part in text.split(",") if part.strip()]


def _axes(text: str) -> str:
    if not text or not set(text) <= set("xyz"):
        raise argparse.ArgumentTypeError(f"expected base axes, some of xyz (e.g. z), got {text!r}")
    return text


def _floats(text: str) -> tuple[float, ...]:
    values = tuple(float(part) for part in _csv(text))
    if len(values) != 7 or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"expected 7 finite numbers X,Y,Z,QW,QX,QY,QZ, got {text!r}")
    return values


def stack_options(args: argparse.Namespace) -> dict:
    """``read_stack_recording``'s keyword arguments, and ``contact_force_n`` and ``start_pressed``
    (``split_at_free_samples``'s), from the stack recording options that were given."""
    options = {"object_name": args.object, "arm": args.arm, "clamped": args.clamped,
               "tcp_in_sensor": args.tcp_in_sensor, "max_gap_s": args.max_gap, "period_s": args.period,
               "contact_force_n": args.contact_force, "start_pressed": args.start_pressed or None,
               "true_object": args.true_object or None}
    return {key: value for key, value in options.items() if value is not None}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``hydrosoft-stack fit``."""
    parser.add_argument("recordings", nargs="+", type=Path,
                        help="wrench-<object>.mcap files of `hydrosoft-stack collect wrench`, or folders of them, "
                             "or stack recordings of `launch --record` (told apart by content; only read)")
    parser.add_argument("--model", default="nh", help=f"contact model to fit: {'|'.join(FIT_MODELS)} (default nh)")
    parser.add_argument("--params", type=_csv, default=list(PARAMETERS), metavar="E,K,mu",
                        help="parameters to fit, the others held at the scenes' Soft Bubble values "
                             "(default E,K,mu)")
    parser.add_argument("--pose-offset", nargs="?", type=_axes, const="xyz", default=None, metavar="AXES",
                        help="fit a constant offset (m, base frame; prior 2 mm per axis) added to every recorded "
                             "object pose, jointly with the material, along AXES (some of xyz; default all three; z: "
                             "the press normal of a horizontal face): a tracker's constant error then widens the "
                             "material's intervals instead of biasing it (one offset for all recordings given; with "
                             "--uncertainty hessian or profile; the profile refits the offset at each point)")
    parser.add_argument("--holdout", type=float, default=0.2,
                        help="fraction of the trajectories held out of the fit and scored after it (default 0.2)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the fit/held-out split (default 0)")
    parser.add_argument("--spacing", type=float, default=None,
                        help="object surface spacing of the model, m (default: the sim plant's, recorded in the "
                             "file; 0.005 for lab recordings)")
    parser.add_argument("--substeps", type=int, default=None,
                        help="replay steps per recorded step (default: chosen, from 1 doubled while a replay twice as "
                             "fine would move a fitted value by more than 0.1 sigma, at most 8)")
    parser.add_argument("--uncertainty", choices=UNCERTAINTY_METHODS, default="hessian",
                        help="how to report each value's uncertainty: hessian (the Gauss-Newton covariance at the "
                             "optimum; adds a few seconds) or bootstrap (--draws refits on data simulated at the fitted "
                             "values with fresh FT 300 noise; each refit 0.5 to 9 s of CPU, so 100 draws add 1 to 15 "
                             "min on one core) or profile (intervals where the cost, refitted over the other "
                             "parameters, rises by the chi-square's 95 %% quantile: right where stick/slip makes "
                             "the residuals non-linear in K and mu; 2 to 4 times the fit's CPU) (default hessian)")
    parser.add_argument("--draws", type=int, default=DEFAULT_DRAWS,
                        help=f"bootstrap refits with --uncertainty bootstrap (default {DEFAULT_DRAWS})")
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads (default 1)")
    parser.add_argument("--out", type=Path, default=None, metavar="PARAMS.toml",
                        help="write the fitted material as an [arms.material] table for an arm of a stack config "
                             "(its lines also fit a scene's bubble [[bodies]] table)")
    parser.add_argument("--json", action="store_true", help="print one JSON document instead of the tables")
    stack = parser.add_argument_group("stack recordings (`launch --record` MCAP files)")
    stack.add_argument("--arm", default=None, help="arm whose wrench and TCP pose to fit (default: the only one)")
    stack.add_argument("--object", default=None,
                       help="benchmark object to replay (default: the tracked pose's object name)")
    stack.add_argument("--clamped", action="store_true",
                       help="the object is clamped: use its first tracked pose throughout")
    stack.add_argument("--tcp-in-sensor", type=_floats, default=None, metavar="X,Y,Z,QW,QX,QY,QZ",
                       help="the TCP (bubble) frame's pose in the F/T sensor's frame, m and wxyz (default identity)")
    stack.add_argument("--max-gap", type=float, default=None, metavar="S",
                       help="interpolate the poses to each wrench sample between poses at most 2 S apart, else take "
                            "the nearest within S, else drop the sample (default 0.02)")
    stack.add_argument("--contact-force", type=float, default=None, metavar="N",
                       help="cut the recording into one trajectory per contact, where the force exceeds N newtons, "
                            "each with its own tare before it; 0 keeps it whole, its first sample the tare "
                            "(default 0.5)")
    stack.add_argument("--start-pressed", action="store_true",
                       help="the recording starts at rest with the bubble pressed straight into the object (the sim "
                            "scenes' start): fit that first contact too, its wrenches as the F/T reader tared them and "
                            "its first sample replayed pressed in (default: a contact from the start is skipped)")
    stack.add_argument("--true-object", action="store_true",
                       help="sim recordings: replay the sim's true object pose (eval/object_pose, 10 Hz: give "
                            "--max-gap 0.05) instead of the tracked one, to see the tracker's share of the error")
    stack.add_argument("--period", type=float, default=None, metavar="S",
                       help="keep at most one wrench sample per this many seconds (default 0.05)")


def check_recording(path: Path, read=None) -> None:
    """ValueError naming ``path`` (and the trajectory) when it lacks what the fit needs: a readable wrench
    recording (its samples decode, so their numbers are finite: JSON has no NaN) whose every trajectory has its
    tare and at least one step after it. ``read``: as ``wrench_replay.load_recordings`` takes it."""
    from hydrosoft.bench.wrench_recording import read_wrench_recording

    _, trajectories = (read or read_wrench_recording)(path)
    if not trajectories:
        raise ValueError(f"{path}: no trajectory in this recording")
    for t in trajectories:
        if len(t.phases) < 2:
            raise ValueError(f"{path}: trajectory {t.index} has only its tare sample, no step to fit")


class RecordingReaders:
    """Reads each file in its format: a stack recording (``stack_recording.read_stack_recording`` with
    ``stack_options``) cut into one trajectory per contact (``split_at_free_samples`` at ``contact_force_n``; 0 or
    less keeps it whole), numbered from ``STACK_INDEX_BASE`` in the order read, or a ``collect wrench`` file.
    ``stack`` holds what each stack recording gave (arm, object, kept and dropped samples, trajectories and contacts
    skipped for want of a tare before them)."""

    STACK_INDEX_BASE = 1000

    def __init__(self, stack_options: dict | None = None) -> None:
        self.stack_options = stack_options or {}
        self.stack: dict[str, dict] = {}
        self._read: dict[str, tuple] = {}  # each stack recording is read once (check, then load)

    def __call__(self, path: Path):
        from dataclasses import replace

        from hydrosoft.bench.stack_recording import (DEFAULT_CONTACT_FORCE_N, is_stack_recording,
                                                     read_stack_recording, split_at_free_samples)
        from hydrosoft.bench.wrench_recording import read_wrench_recording

        if not is_stack_recording(path):
            return read_wrench_recording(path)
        if str(path) not in self._read:
            options = dict(self.stack_options)
            contact_force = options.pop("contact_force_n", DEFAULT_CONTACT_FORCE_N)
            start_pressed = options.pop("start_pressed", False)
            read = read_stack_recording(path, **options)
            if start_pressed and not read.tared:
                raise ValueError(f"{path}: --start-pressed needs wrenches tared by the F/T reader, and some samples "
                                 "are raw (tared=False): tare the sensor out of contact first")
            pieces, skipped = ([read.trajectory], 0) if contact_force <= 0 else \
                split_at_free_samples(read.trajectory, contact_force, start_pressed)
            if not pieces:
                raise ValueError(f"{path}: no contact with an out-of-contact sample before it (force over "
                                 f"{contact_force} N; {skipped} contact(s) from the start"
                                 + ("" if start_pressed else ": --start-pressed fits one the recording starts "
                                    "pressed in, as the sim scenes do") + "): nothing to fit")
            first = self.STACK_INDEX_BASE + sum(len(s["indices"]) for s in self.stack.values())
            indices = list(range(first, first + len(pieces)))
            self.stack[str(path)] = {"indices": indices, "arm": read.arm, "object": read.info.object,
                                     "clamped": bool(self.stack_options.get("clamped", False)),
                                     "true_object": bool(self.stack_options.get("true_object", False)),
                                     "kept": read.kept,
                                     "dropped": read.dropped, "trajectories": len(pieces),
                                     "skipped_in_contact": skipped, "tared": read.tared,
                                     "at_exposure": read.at_exposure,
                                     "start_pressed": sum(p.pretared for p in pieces)}
            self._read[str(path)] = read.info, [replace(t, index=i) for t, i in zip(pieces, indices)]
        return self._read[str(path)]


def run_fit(recordings: Sequence[Path], model: str, params: Sequence[str], holdout: float = 0.2, seed: int = 0,
            spacing: float | None = None, substeps: int | None = None, progress=None,
            stack_options: dict | None = None, uncertainty: str = "hessian", draws: int = DEFAULT_DRAWS,
            pose_offset: str = "") -> dict:
    """The fit's JSON document for ``recordings`` (files or folders of ``wrench-*.mcap``, or stack recordings:
    ``stack_options`` are ``stack_recording.read_stack_recording``'s keyword arguments for them).

    Returns ``{"model", "parameters": {name: {start, value, sigma, interval95, unit, fitted, identified}},
    "uncertainty", "bootstrap", "rows": [...], "trajectories": [...], "split", "fit": {...}, "settings"}``:
    ``uncertainty`` says how ``sigma`` and ``interval95`` were found (``uncertainty``: ``hessian``, ``bootstrap``
    with ``draws`` refits seeded by ``seed``: then ``bootstrap`` holds its draws, noise scale and both interval
    kinds per parameter, else None; or ``profile``: then ``profile`` holds its cost evaluations, seconds, open sides
    and the Gauss-Newton intervals it replaced, else None);
    ``pose_offset``: with ``pose_offset`` (axes, some of ``"xyz"``) the fitted
    object position offset per axis (``offset_x``, ``offset_y``, ``offset_z``: value, sigma, interval95 in m, fitted,
    identified; an axis not fitted is 0), added to the recorded poses of both sets for the ``after`` rows; else
    None; ``rows`` per set
    (``fit``, ``held_out``) and material (``before``, ``after``) the mean and sample standard deviation over
    trajectories of the force, torque and shear RMSEs, as ``bench wrench``'s rows. ValueError for a bad option or
    a recording the fit cannot use (naming it).
    """
    from hydrosoft.bench import material_fit
    from hydrosoft.bench.material_fit import START
    from hydrosoft.bench.wrench_replay import load_recordings, recording_files

    if uncertainty not in UNCERTAINTY_METHODS:
        raise ValueError(f"unknown uncertainty {uncertainty!r}; known: {', '.join(UNCERTAINTY_METHODS)}")
    if not set(pose_offset) <= set("xyz"):
        raise ValueError(f"--pose-offset takes axes, some of xyz, got {pose_offset!r}")
    if pose_offset and uncertainty == "bootstrap":
        raise ValueError("--pose-offset works with --uncertainty hessian or profile only (the bootstrap refits the "
                         "material alone)")
    if uncertainty == "bootstrap" and draws < 2:
        raise ValueError(f"--draws must be at least 2, got {draws}")
    if model not in FIT_MODELS:
        raise ValueError(f"unknown contact model {model!r}; the fit knows {', '.join(FIT_MODELS)}")
    bad = [p for p in params if p not in PARAMETERS]
    if bad or not params:
        raise ValueError(f"unknown parameter(s) {bad}; --params takes some of {','.join(PARAMETERS)}")
    files = recording_files(recordings)
    read = RecordingReaders(stack_options)
    for path in files:
        check_recording(path, read)
    groups = load_recordings(files, spacing, read)
    labels = [(g.object, t.index) for g in groups for t in g.trajectories]
    fit_labels, held_labels = material_fit.split_trajectories(labels, holdout, seed)
    batches = {"fit": material_fit.replay_batches(groups, set(fit_labels)),
               "held_out": material_fit.replay_batches(groups, set(held_labels))}
    tic = time.perf_counter()

    def report(evaluation: int, cost: float, values: dict[str, float]) -> None:
        if progress:
            shown = ", ".join([f"{n} {values[n]:.4g}" for n in params]
                              + [f"{n} {1e3 * values[n]:+.4f} mm" for n in material_fit.OFFSET_AXES if n in values])
            progress(f"evaluation {evaluation}: cost {cost:.5g} ({shown}) at {time.perf_counter() - tic:.1f} s")

    result = material_fit.fit_material(batches["fit"], model, params, START, substeps, progress=report,
                                       pose_offset=pose_offset)
    substeps = result.substeps
    estimates, boot_document, profile_document = result.estimates, None, None
    if uncertainty == "bootstrap":
        from hydrosoft.bench.fit_bootstrap import BOOTSTRAP_INTERVAL, bootstrap

        def report_draw(draw: int, total: int, seconds: float) -> None:
            if progress:
                progress(f"bootstrap refit {draw}/{total} at {seconds:.1f} s")

        boot = bootstrap(result, batches["fit"], model, params, draws, seed, START, progress=report_draw)
        estimates = boot.estimates
        boot_document = {"draws": len(boot.draws), "failed": boot.failed, "noise_scale": boot.noise_scale,
                         "interval": BOOTSTRAP_INTERVAL, "evaluations": boot.evaluations, "seconds": boot.seconds,
                         "intervals95": {kind: {name: list(v) for name, v in kinds.items()}
                                         for kind, kinds in boot.intervals.items()}}
    if uncertainty == "profile":
        from hydrosoft.bench.fit_profile import profile_intervals

        def report_parameter(name: str, points: int, seconds: float) -> None:
            if progress:
                progress(f"profile of {name}: {points} points at {seconds:.1f} s")

        profile = profile_intervals(result, batches["fit"], model, params, START, progress=report_parameter)
        estimates = profile.estimates
        profile_document = {"evaluations": profile.evaluations, "seconds": profile.seconds,
                            "open": [list(side) for side in profile.open],
                            "hessian_interval95": {e.name: [_finite_or_none(v) for v in e.interval95]
                                                   for e in result.estimates if e.fitted}}
    rows, per_trajectory = [], []
    for name in SETS:
        for when, values, offset in (("before", START, None), ("after", result.values, result.offset_m)):
            errors = material_fit.trajectory_rmses(values, batches[name], model, START, substeps, offset)
            per_trajectory += [{"set": name, "when": when, **e} for e in errors]
            row = {"set": name, "when": when, "trajectories": len(errors)}
            for key in ("force_n", "torque_nm", "shear_n"):
                row[f"{key}_mean"], row[f"{key}_std"] = mean_and_std([e[key] for e in errors]) if errors \
                    else (None, None)
            rows.append(row)
    return {
        "model": model,
        "parameters": {e.name: {"start": e.start, "value": e.value, "sigma": _finite_or_none(e.sigma),
                                "interval95": [_finite_or_none(v) for v in e.interval95], "unit": UNITS[e.name],
                                "fitted": e.fitted, "identified": e.identified} for e in estimates},
        "pose_offset": {e.name: {"value": e.value, "sigma": _finite_or_none(e.sigma),
                                 "interval95": [_finite_or_none(v) for v in e.interval95], "unit": "m",
                                 "fitted": e.fitted, "identified": e.identified} for e in result.pose_offset} or None,
        "uncertainty": UNCERTAINTY_TEXT[uncertainty].format(interval=(boot_document or {}).get("interval")),
        "uncertainty_method": uncertainty,
        "bootstrap": boot_document,
        "profile": profile_document,
        "rows": rows,
        "trajectories": per_trajectory,
        "split": {"fit": [list(x) for x in fit_labels], "held_out": [list(x) for x in held_labels]},
        "fit": {"cost_start": result.cost_start, "cost": result.cost, "reduced_chi2": result.reduced_chi2,
                "residuals": result.residual_count, "evaluations": result.iterations,
                "substeps": result.substeps, "replay_shift_sigma": result.replay_shift_sigma,
                "seconds": time.perf_counter() - tic},
        "settings": {"recordings": [str(p) for p in files], "objects": [g.object for g in groups],
                     "params": list(params), "pose_offset": pose_offset, "holdout": holdout, "seed": seed,
                     "substeps": substeps,
                     "spacing_m": {g.object: g.spacing_m for g in groups},
                     "modes": sorted({m for g in groups for m in g.modes}), "stack_recordings": read.stack},
    }


def _finite_or_none(value: float) -> float | None:
    return value if math.isfinite(value) else None


def estimates_of(document: dict) -> list[dict]:
    """The document's parameters as a list of dicts with their ``name``, in ``PARAMETERS`` order."""
    return [{"name": name, **document["parameters"][name]} for name in PARAMETERS]


def _value_text(p: dict) -> str:
    unit = f" {p['unit']}" if p["unit"] else ""
    if not p["fitted"]:
        return f"{p['value']:.4g}{unit} (held, not fitted)"
    low, high = p["interval95"]
    high_text = "inf" if high is None else f"{high:.4g}"
    sigma = "inf" if p["sigma"] is None else f"{p['sigma']:.3g}"
    verdict = "" if p["identified"] else "  NOT IDENTIFIED by these recordings"
    return (f"{p['value']:.4g}{unit} +- {sigma} (1 sigma), 95 % [{low:.4g}, {high_text}], "
            f"start {p['start']:.4g}{verdict}")


def _draws_text(document: dict) -> str:
    boot = document["bootstrap"]
    return "" if boot is None else f" of {boot['draws']} draws, {boot['interval']} intervals"


def format_tables(document: dict) -> str:
    """The fitted values with their uncertainty, then the RMSE tables in ``bench wrench``'s layout: rows the fit
    and held-out sets, columns the start material (before) and the fitted one (after)."""
    from hydrosoft.bench.wrench import rmse_table

    lines = [f"Fitted material, model {document['model'].upper()} (uncertainty: "
             f"{UNCERTAINTY_TITLE[document['uncertainty_method']]}{_draws_text(document)}, "
             f"reduced chi-square {document['fit']['reduced_chi2']:.3g}, replay {document['fit']['substeps']} "
             f"sub-steps per recorded step):"]
    lines += [f"  {p['name']:<3} {_value_text(p)}" for p in estimates_of(document)]
    for name, p in (document.get("pose_offset") or {}).items():
        if not p["fitted"]:
            lines.append(f"  {name} 0 mm (held, not fitted)")
            continue
        low, high = p["interval95"]
        verdict = "" if p["identified"] else "  NOT identified: its 2 mm prior, not the data, sets it"
        lines.append(f"  {name} {p['value'] * 1e3:+.4f} mm +- {p['sigma'] * 1e3:.3g} mm (1 sigma), 95 % "
                     f"[{low * 1e3:+.4f}, {high * 1e3:+.4f}] mm (added to the recorded object poses){verdict}")
    for path, stack in document["settings"]["stack_recordings"].items():
        poses = (" (clamped)" if stack["clamped"] else " (true pose)" if stack.get("true_object")
                 else " (tracked, at the images' exposures)" if stack.get("at_exposure") else " (tracked)")
        lines.append(f"  stack recording {path}: arm {stack['arm']}, object {stack['object']}{poses}, "
                     f"{stack['kept']} samples kept, "
                     f"{stack['dropped']} dropped (no pose within the max gap), {stack['trajectories']} "
                     f"trajectories ({stack['start_pressed']} started pressed in), {stack['skipped_in_contact']} "
                     "contacts skipped (in contact from the start)")
    index = {(r["set"], r["when"]): r for r in document["rows"]}

    def table(title: str, key: str, digits: int = 3) -> list[str]:
        cells = []
        for name in SETS:
            row_cells = []
            for when in ("before", "after"):
                r = index[(name, when)]
                row_cells.append((r[key + "_mean"], r[key + "_std"]) if r["trajectories"] else None)
            cells.append((f"{SET_TITLES[name]} ({index[(name, 'before')]['trajectories']})", row_cells))
        return rmse_table(title, "Trajectories", ["before", "after"], cells, digits)

    lines += [""] + table("Wrench RMSE, force [N] (lower is better), start material (before) and fitted (after)",
                          "force_n")
    lines += [""] + table("Wrench RMSE, torque [N m]", "torque_nm", digits=4)
    lines += [""] + table("Wrench RMSE, tangential force (TCP x, y) [N]", "shear_n")
    return "\n".join(lines)


def params_toml(document: dict, today: datetime.date | None = None) -> str:
    """An ``[arms.material]`` table of the fitted, identified parameters (``E``, ``K`` in Pa/m, ``mu``), as a stack
    config's arm takes it (``ArmConfig.material``), with comments saying where they came from and how to use them;
    a parameter not identified is left as a comment (the arm then keeps the scene's value)."""
    today = today or datetime.date.today()
    settings = document["settings"]
    held = next(r for r in document["rows"] if r["set"] == "held_out" and r["when"] == "after")
    lines = [f"# Soft Bubble material fitted by `hydrosoft-stack fit` on {today.isoformat()}: model "
             f"{document['model']}, objects {', '.join(settings['objects'])}, "
             f"{len(document['split']['fit'])} trajectories fitted, {held['trajectories']} held out"
             + (f" (held-out force RMSE {held['force_n_mean']:.3g} N)" if held["trajectories"] else "") + ".",
             "# Use: paste this table into the stack config (deploy/*.toml) directly below the keys of the",
             "# [[arms]] table of the arm whose bubble was recorded; the planner and the sim plant then use it",
             "# for that arm's bubble. For a scene file, its E, K and mu lines go in the bubble's [[bodies]] table.",
             f"# The comments give 1 sigma and the 95 % interval ({UNCERTAINTY_TITLE[document['uncertainty_method']]}"
             f"{_draws_text(document)}).",
             *(["# Fitted jointly with a constant object pose offset (m, base frame): " + ", ".join(
                 f"{name} {p['value']:.3g}" for name, p in document["pose_offset"].items())]
               if document.get("pose_offset") else []),
             "[arms.material]"]
    for p in estimates_of(document):
        if not p["fitted"]:
            continue
        if not p["identified"]:
            lines.append(f"# {p['name']}: NOT identified by these recordings (95 % interval {p['interval95']}); "
                         "keep the scene's value and record trajectories that exercise it")
            continue
        low, high = p["interval95"]
        lines.append(f"{p['name']} = {p['value']:.6g}  # {p['unit'] or 'friction coefficient'}, 1 sigma "
                     f"{p['sigma']:.3g}, 95 % [{low:.6g}, {high:.6g}]")
    return "\n".join(lines) + "\n"


def run(args: argparse.Namespace) -> int:
    """Run the fit; 0, or 2 for a bad option or a recording the fit cannot use."""
    import torch

    if args.spacing is not None and not (math.isfinite(args.spacing) and args.spacing > 0):
        print(f"fit: --spacing must be a positive number of metres, got {args.spacing}", file=sys.stderr)
        return 2
    if args.substeps is not None and args.substeps < 1:
        print(f"fit: --substeps must be at least 1, got {args.substeps}", file=sys.stderr)
        return 2
    for name, value in (("--max-gap", args.max_gap), ("--period", args.period)):
        if value is not None and not (math.isfinite(value) and value > 0):
            print(f"fit: {name} must be a positive number of seconds, got {value}", file=sys.stderr)
            return 2
    if args.contact_force is not None and not (math.isfinite(args.contact_force) and args.contact_force >= 0):
        print(f"fit: --contact-force must be a number of newtons, 0 or more, got {args.contact_force}",
              file=sys.stderr)
        return 2
    if args.uncertainty == "bootstrap" and args.draws < 2:
        print(f"fit: --draws must be at least 2, got {args.draws}", file=sys.stderr)
        return 2
    if args.out is not None and args.out.suffix != ".toml":
        print(f"fit: --out must name a .toml file (the recordings are never written), got {args.out}",
              file=sys.stderr)
        return 2
    torch.set_num_threads(args.threads)
    try:
        document = run_fit(args.recordings, args.model, args.params, args.holdout, args.seed, args.spacing,
                           args.substeps, progress=lambda text: print(f"[fit] {text}", file=sys.stderr, flush=True),
                           stack_options=stack_options(args), uncertainty=args.uncertainty, draws=args.draws,
                           pose_offset=args.pose_offset or "")
    except ValueError as error:
        print(f"fit: {error}", file=sys.stderr)
        return 2
    print(json.dumps(document) if args.json else format_tables(document))
    if args.out is not None:
        args.out.write_text(params_toml(document))
        print(f"[fit] wrote {args.out}: paste its [arms.material] table below the arm's [[arms]] keys in the "
              "stack config (deploy/*.toml)", file=sys.stderr)
    return 0
