"""``hydrosoft-stack bench fit``: does the material fit recover a known material, and does its reported uncertainty
hold under the FT 300's noise?

For each seed a synthetic recording (``synthetic_wrench``) of the NH plant with a non-default material (``TRUTH``:
E x1.7, K x0.6, mu 0.35 of the scenes' Soft Bubble) on the cube: ``len(KINDS)`` press-and-shear trajectories of
``STEPS`` steps, each sample the mean of 5 FT 300 frames with the datasheet's noise, quantised. All trajectories are
fitted (``material_fit.fit_material``, E, K and mu from the scenes' values); a parameter is covered when the truth
lies in its reported 95 % interval. First the same without noise (the FT 300's resolution only): the recovery.

With ``--draws N`` each seed's fit is also bootstrapped (``fit_bootstrap``, N refits), and the coverage of the
bootstrap's percentile and basic intervals is counted beside Gauss-Newton's. With ``--profile`` the same for the
profile-likelihood intervals (``fit_profile``), each parameter's by its profile z-score at the truth
(``fit_profile.signed_roots``; the interval holds the truth exactly where it is within ``Z95``). With ``--pose-noise
MM,DEG`` the recorded object poses carry tracker noise (``synthetic_wrench.tracked_poses``) and the mean relative error
over the seeds shows the bias it causes. ``--plant-substeps N --substeps N`` makes the fit's replay the plant exactly
(the plant otherwise takes ``synthetic_wrench.PLANT_SUBSTEPS`` and the replay is chosen by the fit's resolution rule),
to tell their mismatch from the noise; ``--no-recovery`` skips the noise-free run (for many seeds in chunks).

Each row also gives per parameter ``z_linear``: the error the seed's noise alone gives through the fit's
linearisation at the truth (``linear_error``). Its mean square over many seeds tells a wrong noise model or
weighting (away from 1) from chance in a few seeds, and the fitted ``z`` less it is the non-linearity's share.

Prints one row per run (the recovered values, their relative error, 1 sigma and whether covered) and per
parameter and method the count of seeds that cover it; ``--json`` prints one JSON document instead.

Run time: about 9 s of CPU per seed on one core (recording, fit, the replay-resolution check and the Gauss-Newton
Jacobian): 101 s for the default 10 seeds and the noise-free run, 11 min 45 s of wall time on the loaded 2-core dev
VM (2026-11-27). ``z_linear`` adds one Jacobian at the truth per noisy seed: 0.8 s of CPU at 1 sub-step, 4.2 s at 8
(about 17 s for seeds 0-9). ``--draws 100`` adds 1 to 15 min of CPU per seed (6 to 21 cost evaluations per refit; more
sub-steps cost more). ``--profile`` adds one refit of the two others per parameter, at the truth (the interval itself,
``fit --uncertainty profile``, takes 2 to 8 such refits per parameter).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path

from hydrosoft.bench.material_parameters import BOOTSTRAP_INTERVALS, DEFAULT_DRAWS

TRUTH = {"E": 3e5 * 1.7, "K": 1e5 * 0.6, "mu": 0.35}
OBJECT = "cube"
KINDS = ("shear", "twist", "shear_twist", "shear", "shear_twist", "twist", "shear", "shear_twist")
STEPS = 12
METHODS = ("hessian",) + BOOTSTRAP_INTERVALS + ("profile",)  # Gauss-Newton, the bootstrap's two, the profile's


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``hydrosoft-stack bench fit``."""
    parser.add_argument("--seeds", type=int, default=10, help="noisy recordings to fit (default 10)")
    parser.add_argument("--first-seed", type=int, default=0, help="seed of the first one (default 0)")
    parser.add_argument("--draws", type=int, default=0,
                        help="parametric bootstrap draws per seed, beside the Gauss-Newton interval, e.g. "
                             f"{DEFAULT_DRAWS}: each is one refit, 0.5 to 9 s of CPU, so 100 add 1 to 15 min per seed "
                             "(default 0: Gauss-Newton only)")
    parser.add_argument("--profile", action="store_true",
                        help="also whether each seed's profile-likelihood interval holds the truth, beside "
                             "Gauss-Newton's (one refit per parameter at the truth)")
    parser.add_argument("--pose-noise", type=_pose_noise, default=(0.0, 0.0), metavar="MM,DEG",
                        help="tracker noise on the recorded object poses, standard deviation per axis of position (mm) "
                             "and rotation (deg); the plant pressed the true pose (default none)")
    parser.add_argument("--plant-substeps", type=int, default=None,
                        help="the synthetic plant's steps per recorded step (default: the plant's own, "
                             "synthetic_wrench.PLANT_SUBSTEPS); the same as --substeps makes the replay the plant "
                             "exactly")
    parser.add_argument("--substeps", type=int, default=None,
                        help="the fit's replay steps per recorded step (default: chosen by the fit's resolution rule)")
    parser.add_argument("--no-recovery", action="store_true", help="skip the noise-free recovery run")
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads (default 1)")
    parser.add_argument("--json", action="store_true", help="print one JSON document instead of the table")


def _pose_noise(text: str) -> tuple[float, float]:
    parts = text.split(",")
    try:
        mm, deg = (float(part) for part in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected MM,DEG (two numbers), got {text!r}") from None
    if not (math.isfinite(mm) and math.isfinite(deg) and mm >= 0 and deg >= 0):
        raise argparse.ArgumentTypeError(f"expected two numbers 0 or more, got {text!r}")
    return mm, deg


def _covered(interval, truth: float) -> bool:
    return interval[0] <= truth <= interval[1]


def fit_one(folder: Path, seed: int, noise_scale: float, draws: int = 0,
            pose_noise: tuple[float, float] = (0.0, 0.0), plant_substeps: int | None = None,
            substeps: int | None = None, profile: bool = False) -> dict:
    """Record and fit one synthetic recording, with ``draws`` bootstrap refits (none for 0), with ``profile`` the
    profile's z-score at the truth, and ``pose_noise`` ``(mm, deg)`` of tracker noise on its object poses, the plant at
    ``plant_substeps`` (None: its default) and the fit's replay at ``substeps`` (None: chosen by the fit); its row of
    the benchmark's document: per parameter the fit's value, error, Gauss-Newton sigma, interval, ``z`` (the error in
    Gauss-Newton standard deviations, in the fit's log and logit coordinates) and ``z_linear`` (``linear_error`` in the
    same standard deviations; None without noise, where the standard deviations are the resolution's), and, with draws,
    ``bootstrap``: its sigma and its ``percentile`` and ``basic`` intervals, each with whether it covers the truth; with
    ``profile``, ``profile``: ``z`` (``fit_profile.signed_roots`` at the truth, with the sign of the fit less the truth,
    as ``z``'s) and whether the profile interval covers the truth (``|z| <= Z95``), and the row's ``profile``: cost
    evaluations and seconds. ``evaluations`` and ``fit_seconds``: the fit's own."""
    import numpy as np

    from hydrosoft.bench import material_fit
    from hydrosoft.bench.fit_bootstrap import bootstrap
    from hydrosoft.bench.fit_profile import signed_roots
    from hydrosoft.bench.synthetic_wrench import PLANT_SUBSTEPS, write_synthetic_recording
    from hydrosoft.bench.wrench_replay import load_recordings

    path = folder / f"wrench-{OBJECT}-{seed}-{noise_scale:g}.mcap"
    tic = time.perf_counter()
    write_synthetic_recording(path, OBJECT, TRUTH, KINDS, STEPS, seed, noise_scale,
                              pose_noise=(pose_noise[0] / 1000, math.radians(pose_noise[1])),
                              plant_substeps=plant_substeps or PLANT_SUBSTEPS)
    groups = load_recordings([path])
    labels = {(g.object, t.index) for g in groups for t in g.trajectories}
    batches = material_fit.replay_batches(groups, labels)
    result = material_fit.fit_material(batches, "nh", list(TRUTH), substeps=substeps)
    row = {"seed": seed, "noise_scale": noise_scale, "reduced_chi2": result.reduced_chi2, "substeps": result.substeps,
           "replay_shift_sigma": result.replay_shift_sigma}
    truth = material_fit.to_theta(TRUTH, material_fit.START)
    errors = result.theta - truth.numpy()
    sigmas = np.sqrt(np.diag(result.covariance))
    z_linears = linear_error(batches, truth, result.substeps) / sigmas if noise_scale > 0 else [None] * len(sigmas)
    for e, error, sigma, z_linear in zip(result.estimates, errors, sigmas, z_linears):
        row[e.name] = {"value": e.value, "relative_error": e.value / TRUTH[e.name] - 1, "sigma": e.sigma,
                       "interval95": list(e.interval95), "identified": e.identified,
                       "covered": _covered(e.interval95, TRUTH[e.name]), "z": float(error / sigma),
                       "z_linear": None if z_linear is None else float(z_linear)}
    row["seconds"] = row["fit_seconds"] = time.perf_counter() - tic
    row["evaluations"] = result.iterations
    if profile:
        roots, evaluations = signed_roots(result, batches, "nh", list(TRUTH), TRUTH)
        row["profile"] = {"evaluations": evaluations, "seconds": time.perf_counter() - tic - row["fit_seconds"]}
        for name, root in roots.items():  # z: the fit less the truth, as the fitted z's sign
            row[name]["profile"] = {"z": -root, "covered": abs(root) <= material_fit.Z95}
        row["seconds"] = time.perf_counter() - tic
    if draws:
        boot = bootstrap(result, batches, "nh", list(TRUTH), draws, seed)
        row["bootstrap"] = {"draws": len(boot.draws), "failed": boot.failed, "noise_scale": boot.noise_scale,
                            "evaluations": boot.evaluations, "seconds": boot.seconds}
        for e in boot.estimates:
            row[e.name]["bootstrap"] = {"sigma": e.sigma, **{
                kind: {"interval95": list(boot.intervals[kind][e.name]),
                       "covered": _covered(boot.intervals[kind][e.name], TRUTH[e.name])} for kind in BOOTSTRAP_INTERVALS}}
        row["seconds"] = time.perf_counter() - tic
    return row


def linear_error(batches, truth, substeps: int):
    """The fit's error ``(3,)`` in the unconstrained coordinates if the residuals were linear in them: the
    Gauss-Newton step ``-(J^T J)^-1 J^T r`` from the ``truth``'s coordinates ``(3,)`` (``material_fit.to_theta``), with
    the whitened residuals ``r`` of ``batches`` and their Jacobian ``J`` there, at the fit's ``substeps``. With the
    replay the plant exactly, ``r`` is the whitened noise, so under a right noise model this error over the fit's
    standard deviations is exactly normal with variance 1: the fitted ``z`` less this ``z_linear`` is the
    non-linearity's share."""
    import numpy as np
    import torch

    from hydrosoft.bench import material_fit

    r, J = material_fit.residuals_and_jacobian(truth, torch.ones(3, dtype=torch.bool), batches, "nh",
                                               material_fit.START, substeps)
    return -np.linalg.lstsq(J, r, rcond=None)[0]


def covered_of(row: dict, name: str, method: str) -> bool:
    """Whether ``method`` (``METHODS``) covered parameter ``name``'s truth in a row of ``fit_one``."""
    if method == "hessian":
        return row[name]["covered"]
    return row[name]["profile"]["covered"] if method == "profile" else row[name]["bootstrap"][method]["covered"]


def evaluate(seeds: int, progress=None, draws: int = 0, first_seed: int = 0,
             pose_noise: tuple[float, float] = (0.0, 0.0), plant_substeps: int | None = None,
             substeps: int | None = None, recovery: bool = True, profile: bool = False) -> dict:
    """The benchmark's document: ``recovery`` (the noise-free row, no bootstrap), ``noisy`` (one row per seed,
    ``first_seed`` on), ``covered`` (per parameter the count of noisy seeds whose Gauss-Newton 95 % interval holds
    the truth), ``all_covered`` (seeds covering all three), and ``covered_by`` and ``all_covered_by``: the same per
    method (``hessian``, and with ``draws`` the bootstrap's ``percentile`` and ``basic``); ``mean_relative_error``
    per parameter over the noisy seeds (the bias, with its standard error); ``pose_noise`` ``(mm, deg)``;
    ``coverage_interval95``: per method and parameter the exact (Clopper-Pearson) 95 % confidence interval of the
    coverage fraction; ``mean_square_z``: per parameter the mean squared ``z`` (1 for right intervals);
    ``mean_square_z_linear`` and ``covered_linear``: the same of ``z_linear`` (``linear_error``), the noise's share
    alone, and how many of its ``|z_linear|`` are within the 95 % interval's ``Z95``; with ``profile`` (method
    ``profile`` too) ``mean_square_z_profile``: the same of the profile's z at the truth; ``seconds``: per part
    (``fit``, ``profile``, the noisy seeds' wall time summed) and ``evaluations`` (the same, cost evaluations).
    ``plant_substeps`` and ``substeps``: as ``fit_one``'s; ``recovery``: whether to run the noise-free row (else
    None)."""
    from scipy.stats import binomtest

    from hydrosoft.bench.material_fit import Z95

    with tempfile.TemporaryDirectory(prefix="hydrosoft-fit-bench-") as folder:
        recovery_row = None
        if recovery:
            recovery_row = fit_one(Path(folder), 0, 0.0, pose_noise=pose_noise, plant_substeps=plant_substeps,
                                   substeps=substeps)
            if progress:
                progress(f"noise-free recovery in {recovery_row['seconds']:.1f} s")
        noisy = []
        for seed in range(first_seed, first_seed + seeds):
            noisy.append(fit_one(Path(folder), seed, 1.0, draws, pose_noise, plant_substeps, substeps, profile))
            if progress:
                progress(f"seed {seed} in {noisy[-1]['seconds']:.1f} s")
    methods = [m for m in METHODS if m == "hessian" or (m == "profile" and profile)
               or (m in BOOTSTRAP_INTERVALS and draws)]
    parts = ["fit"] + (["profile"] if profile else [])
    extra = {"seconds": {part: sum(r[f"{part}_seconds"] if part == "fit" else r[part]["seconds"] for r in noisy)
                         for part in parts},
             "evaluations": {part: sum(r["evaluations"] if part == "fit" else r[part]["evaluations"] for r in noisy)
                             for part in parts}}
    if profile:
        extra["mean_square_z_profile"] = {name: sum(r[name]["profile"]["z"] ** 2 for r in noisy) / seeds
                                          for name in TRUTH}
    covered_by = {m: {name: sum(covered_of(r, name, m) for r in noisy) for name in TRUTH} for m in methods}
    all_covered_by = {m: sum(all(covered_of(r, name, m) for name in TRUTH) for r in noisy) for m in methods}
    coverage_interval95 = {m: {name: list(binomtest(count, seeds).proportion_ci(0.95)) for name, count in c.items()}
                           for m, c in covered_by.items()}
    return {"truth": TRUTH, "object": OBJECT, "trajectories": len(KINDS), "steps": STEPS, "recovery": recovery_row,
            "plant_substeps": plant_substeps, "substeps": substeps, "coverage_interval95": coverage_interval95,
            "mean_square_z": {name: sum(r[name]["z"] ** 2 for r in noisy) / seeds for name in TRUTH},
            "mean_square_z_linear": {name: sum(r[name]["z_linear"] ** 2 for r in noisy) / seeds for name in TRUTH},
            "covered_linear": {name: sum(abs(r[name]["z_linear"]) <= Z95 for r in noisy) for name in TRUTH},
            "noisy": noisy, "covered": covered_by["hessian"], "all_covered": all_covered_by["hessian"],
            "covered_by": covered_by, "all_covered_by": all_covered_by, "seeds": seeds,
            "first_seed": first_seed, "draws": draws, "pose_noise": list(pose_noise),
            "mean_relative_error": {name: _mean_and_error([r[name]["relative_error"] for r in noisy])
                                    for name in TRUTH}, **extra}


def _mean_and_error(values: list[float]) -> list[float]:
    """Mean and its standard error (0 for one value)."""
    mean = sum(values) / len(values)
    spread = math.sqrt(sum((v - mean) ** 2 for v in values) / (len(values) - 1)) if len(values) > 1 else 0.0
    return [mean, spread / math.sqrt(len(values))]


def format_table(document: dict) -> str:
    """One line per run: per parameter the value, its relative error, the Gauss-Newton 1 sigma and whether its 95 %
    interval holds the truth, then with draws whether the bootstrap's percentile (p) and basic (b) intervals do,
    and with the profile whether its interval (l) does; then the coverage counts per method, the mean squared z
    and, with the profile, the cost evaluations of the fits and of the profiles."""
    names = list(TRUTH)
    boot = bool(document["draws"])
    profile = "profile" in document["covered_by"]
    width = 34 + (8 if boot else 0) + (6 if profile else 0)
    head = f"{'run':<12}" + "".join(f"| {name:^{width}} " for name in names) + "| chi2/dof | sub-steps"
    lines = [f"Material fit on synthetic {document['object']} recordings ({document['trajectories']} trajectories of "
             f"{document['steps']} steps), truth " + ", ".join(f"{n} {v:.4g}" for n, v in TRUTH.items())
             + (", object poses with tracker noise {:g} mm, {:g} deg".format(*document["pose_noise"])
                if any(document["pose_noise"]) else "")
             + (f"; bootstrap of {document['draws']} draws: p percentile, b basic interval" if boot else "")
             + ("; l profile-likelihood interval" if profile else ""),
             head, "-" * len(head)]

    def mark(covered: bool) -> str:
        return "in" if covered else "OUT"

    def line(title: str, row: dict) -> str:
        cells = ""
        for n in names:
            cells += (f"| {row[n]['value']:>10.4g} {100 * row[n]['relative_error']:>+6.2f}% "
                      f"s {row[n]['sigma']:>8.3g} {mark(row[n]['covered']):>3} ")
            if boot:
                cells += "".join(f"{kind[0]} {mark(covered_of(row, n, kind)) if 'bootstrap' in row else '-':>3} "
                                 for kind in BOOTSTRAP_INTERVALS)
            if profile:
                cells += f"l {mark(covered_of(row, n, 'profile')) if 'profile' in row else '-':>3} "
        return f"{title:<12}{cells}| {row['reduced_chi2']:<8.3g} | {row['substeps']}"

    if document["recovery"] is not None:
        lines.append(line("no noise", document["recovery"]))
    lines += [line(f"noise s{r['seed']}", r) for r in document["noisy"]]
    lines.append("")
    seeds = f"seeds {document['first_seed']}-{document['first_seed'] + document['seeds'] - 1}"
    lines.append(f"Mean relative error ({seeds}, +- standard error): " + ", ".join(
        f"{n} {100 * m:+.2f} +- {100 * e:.2f} %" for n, (m, e) in document["mean_relative_error"].items()))
    for method, covered in document["covered_by"].items():
        lines.append(f"Truth inside the 95 % interval ({method}, {seeds}): " + ", ".join(
            f"{n} {covered[n]}/{document['seeds']} [{100 * low:.0f}, {100 * high:.0f}] %"
            for n in names for low, high in [document["coverage_interval95"][method][n]])
            + f"; all three {document['all_covered_by'][method]}/{document['seeds']}")
    lines.append("Mean squared z (1 for right intervals): " + ", ".join(
        f"{n} {z:.2f}" for n, z in document["mean_square_z"].items())
        + ("; the profile's z at the truth: " + ", ".join(
            f"{n} {z:.2f}" for n, z in document["mean_square_z_profile"].items()) if profile else ""))
    lines.append("Linearised at the truth (the noise alone): mean squared z " + ", ".join(
        f"{n} {z:.2f}" for n, z in document["mean_square_z_linear"].items()) + "; inside 95 %: " + ", ".join(
        f"{n} {c}/{document['seeds']}" for n, c in document["covered_linear"].items()))
    if profile:
        fit, prof = document["evaluations"]["fit"], document["evaluations"]["profile"]
        seconds = document["seconds"]
        lines.append(f"Cost evaluations over the noisy seeds: fits {fit}, profiles at the truth {prof} "
                     f"({prof / fit:.2f} times); CPU-bound wall time {seconds['fit']:.0f} s and "
                     f"{seconds['profile']:.0f} s")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    """Run the benchmark; 0, or 2 for a bad option."""
    import torch

    if args.seeds < 1:
        print(f"bench fit: --seeds must be at least 1, got {args.seeds}", file=sys.stderr)
        return 2
    if args.draws < 0 or args.draws == 1:
        print(f"bench fit: --draws must be 0 (no bootstrap) or at least 2, got {args.draws}", file=sys.stderr)
        return 2
    for option in ("plant_substeps", "substeps"):
        if getattr(args, option) is not None and getattr(args, option) < 1:
            print(f"bench fit: --{option.replace('_', '-')} must be at least 1, got {getattr(args, option)}",
                  file=sys.stderr)
            return 2
    torch.set_num_threads(args.threads)
    document = evaluate(args.seeds, lambda text: print(f"[bench fit] {text}", file=sys.stderr, flush=True),
                        args.draws, args.first_seed, args.pose_noise, args.plant_substeps, args.substeps,
                        not args.no_recovery, args.profile)
    print(json.dumps(document) if args.json else format_table(document))
    return 0
