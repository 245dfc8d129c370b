"""The ``hydrosoft-stack`` command line.

Subcommands import their implementation lazily, so ``--help`` is fast and ``demo`` needs no benchmark code.
"""

from __future__ import annotations

import argparse
import importlib
import sys

# subcommand -> (module with add_arguments(parser) and run(args) -> int, one-line help)
BENCHES = {
    "model": ("hydrosoft.bench.model", "contact-model step time, throughput, memory and force accuracy per model, dtype, batch and point count"),
    "control": ("hydrosoft.bench.control", "closed/open-loop MPC error per task and model (paper Table III, simulation)"),
    "tradeoff": ("hydrosoft.bench.tradeoff", "solve time against closed-loop error over the planner's knobs"),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="hydrosoft-stack",
        description="ROS-free control stack for compliant tactile manipulation with non-holonomic hydroelastic "
        "contact models (Hydrosoft).",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    demo = sub.add_parser(
        "demo",
        help="run a short simulated planar-pushing rollout and print what happened",
        description="Compile the planar pushing scene, drag the cube with the bubble for a few steps and print the "
        "object's motion and the contact forces at each step. Needs no hardware.",
    )
    demo.add_argument("--steps", type=int, default=20, help="control steps to simulate (default 20)")
    demo.add_argument("--model", default="nh", choices=["nh", "snh", "pf", "pff"], help="contact model (default nh)")
    demo.add_argument("--speed", type=float, default=2.0, help="bubble speed along x in mm per step (default 2)")
    bench = sub.add_parser("bench", help="benchmarks that print figures (see `bench COMMAND --help`)")
    bench_sub = bench.add_subparsers(dest="bench", metavar="BENCH", required=True)
    for name, (module, text) in BENCHES.items():
        p = bench_sub.add_parser(name, help=text, description=text)
        p.set_defaults(bench_module=module)
        importlib.import_module(module).add_arguments(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 0
    if args.command == "demo":
        from hydrosoft.services.demo import run_demo

        return run_demo(steps=args.steps, model=args.model, speed_mm=args.speed)
    return importlib.import_module(args.bench_module).run(args)


if __name__ == "__main__":
    sys.exit(main())
