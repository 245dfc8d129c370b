"""``hydrosoft-stack bench fit``: does the material fit recover a known material, and does its reported uncertainty
hold under the FT 300's noise?

For each seed a synthetic recording (``synthetic_wrench``) of the NH plant with a non-default material (``TRUTH``:
E x1.7, K x0.6, mu 0.35 of the scenes' Soft Bubble) on the cube: ``len(KINDS)`` press-and-shear trajectories of
``STEPS`` steps, each sample the mean of 5 FT 300 frames with the datasheet's noise, quantised. All trajectories are
fitted (``material_fit.fit_material``, E, K and mu from the scenes' values); a parameter is covered when the truth
lies in its reported 95 % interval. First the same without noise (the FT 300's resolution only): the recovery.

Prints one row per run (the recovered values, their relative error, 1 sigma and whether covered) and per
parameter the count of seeds that cover it; ``--json`` prints one JSON document instead.

Run time: about 9 s of CPU per seed on one core (recording, fit, the replay-resolution check and the Gauss-Newton
Jacobian): 101 s for the default 10 seeds and the noise-free run, 11 min 45 s of wall time on the loaded 2-core dev
VM (2026-11-27).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

TRUTH = {"E": 3e5 * 1.7, "K": 1e5 * 0.6, "mu": 0.35}
OBJECT = "cube"
KINDS = ("shear", "twist", "shear_twist", "shear", "shear_twist", "twist", "shear", "shear_twist")
STEPS = 12


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``hydrosoft-stack bench fit``."""
    parser.add_argument("--seeds", type=int, default=10, help="noisy recordings to fit, seeds 0..N-1 (default 10)")
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads (default 1)")
    parser.add_argument("--json", action="store_true", help="print one JSON document instead of the table")


def fit_one(folder: Path, seed: int, noise_scale: float) -> dict:
    """Record and fit one synthetic recording; its row of the benchmark's document."""
    from hydrosoft.bench import material_fit
    from hydrosoft.bench.synthetic_wrench import write_synthetic_recording
    from hydrosoft.bench.wrench_replay import load_recordings

    path = folder / f"wrench-{OBJECT}-{seed}-{noise_scale:g}.mcap"
    tic = time.perf_counter()
    write_synthetic_recording(path, OBJECT, TRUTH, KINDS, STEPS, seed, noise_scale)
    groups = load_recordings([path])
    labels = {(g.object, t.index) for g in groups for t in g.trajectories}
    result = material_fit.fit_material(material_fit.replay_batches(groups, labels), "nh", list(TRUTH))
    row = {"seed": seed, "noise_scale": noise_scale, "reduced_chi2": result.reduced_chi2, "substeps": result.substeps,
           "seconds": time.perf_counter() - tic}
    for e in result.estimates:
        row[e.name] = {"value": e.value, "relative_error": e.value / TRUTH[e.name] - 1, "sigma": e.sigma,
                       "interval95": list(e.interval95), "identified": e.identified,
                       "covered": e.interval95[0] <= TRUTH[e.name] <= e.interval95[1]}
    return row


def evaluate(seeds: int, progress=None) -> dict:
    """The benchmark's document: ``recovery`` (the noise-free row), ``noisy`` (one row per seed), ``covered`` (per
    parameter the count of noisy seeds whose 95 % interval holds the truth) and ``all_covered`` (seeds covering all
    three)."""
    with tempfile.TemporaryDirectory(prefix="hydrosoft-fit-bench-") as folder:
        recovery = fit_one(Path(folder), 0, 0.0)
        if progress:
            progress(f"noise-free recovery in {recovery['seconds']:.1f} s")
        noisy = []
        for seed in range(seeds):
            noisy.append(fit_one(Path(folder), seed, 1.0))
            if progress:
                progress(f"seed {seed} in {noisy[-1]['seconds']:.1f} s")
    return {"truth": TRUTH, "object": OBJECT, "trajectories": len(KINDS), "steps": STEPS, "recovery": recovery,
            "noisy": noisy, "covered": {name: sum(r[name]["covered"] for r in noisy) for name in TRUTH},
            "all_covered": sum(all(r[name]["covered"] for name in TRUTH) for r in noisy), "seeds": seeds}


def format_table(document: dict) -> str:
    """One line per run: per parameter the value, its relative error, 1 sigma and whether the 95 % interval holds
    the truth; then the coverage counts."""
    names = list(TRUTH)
    head = f"{'run':<12}" + "".join(f"| {name:^34} " for name in names) + "| chi2/dof | sub-steps"
    lines = [f"Material fit on synthetic {document['object']} recordings ({document['trajectories']} trajectories of "
             f"{document['steps']} steps), truth " + ", ".join(f"{n} {v:.4g}" for n, v in TRUTH.items()),
             head, "-" * len(head)]

    def line(title: str, row: dict) -> str:
        cells = "".join(f"| {row[n]['value']:>10.4g} {100 * row[n]['relative_error']:>+6.2f}% "
                        f"s {row[n]['sigma']:>8.3g} {'in' if row[n]['covered'] else 'OUT':>3} " for n in names)
        return f"{title:<12}{cells}| {row['reduced_chi2']:<8.3g} | {row['substeps']}"

    lines.append(line("no noise", document["recovery"]))
    lines += [line(f"noise s{r['seed']}", r) for r in document["noisy"]]
    lines.append("")
    lines.append("Truth inside the reported 95 % interval: " + ", ".join(
        f"{n} {document['covered'][n]}/{document['seeds']}" for n in names)
        + f"; all three {document['all_covered']}/{document['seeds']}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    """Run the benchmark; 0, or 2 for a bad option."""
    import torch

    if args.seeds < 1:
        print(f"bench fit: --seeds must be at least 1, got {args.seeds}", file=sys.stderr)
        return 2
    torch.set_num_threads(args.threads)
    document = evaluate(args.seeds, progress=lambda text: print(f"[bench fit] {text}", file=sys.stderr, flush=True))
    print(json.dumps(document) if args.json else format_table(document))
    return 0
