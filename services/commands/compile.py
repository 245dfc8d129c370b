"""``hydrosoft-stack compile CONFIG``: fill torch's compile cache with the config's compiled planner step and costs,
so that the stack's first launch reports ready in seconds instead of minutes.

With ``planner.compile`` the planner compiles its step before it reports ready: 2.5-6.5 minutes on a 2-core
machine the first time, 6-15 s once torch's compile cache (``compile_cache_dir``, or ``TORCHINDUCTOR_CACHE_DIR``)
holds it. Run this once after an install or a torch upgrade, as the user the stack runs as (the cache is per
directory), and before the first ``launch``. It opens no device and no socket. sim_world's plant is not compiled
here: it solves the bubble to convergence (a ``torch.while_loop``), which torch cannot cache, so it compiles at
every launch (20-60 s). Exit codes: 0 compiled (or nothing to compile: ``planner.compile`` is false), 1 the step
or a cost fell back to eager (each named with its reason), 2 a config that cannot be used.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import torch

from hydrosoft.services.bus.config import ConfigError, load_config
from hydrosoft.services.planner import PlannerCore, compile_step
from hydrosoft.services.bus.service_cli import CACHE_ENV, use_compile_cache


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("config", type=Path, help="the stack's TOML config (deploy/lab.toml, deploy/sim.toml)")


def run(args: argparse.Namespace) -> int:
    try:
        config = load_config(args.config)
        use_compile_cache(config)  # before anything of torch's asks for its cache (which then fixes the variable)
        core = PlannerCore.build(config)
    except (ConfigError, ValueError) as err:
        print(f"compile: {err}", file=sys.stderr)
        return 2
    if not config.planner.compile:
        print(f"compile: nothing to compile: {args.config} runs the planner eager (planner.compile = false)")
        return 0
    torch.set_num_threads(config.planner.threads)
    cache = os.environ.get(CACHE_ENV, "torch's default cache, /tmp/torchinductor_USER")
    print(f"compile: compiling the planner step into {cache} (minutes the first time, seconds when the cache holds "
          f"it)", flush=True)
    seconds = compile_step(core)
    parts = {"step": core.dynamics, "stage cost": core.cost_terms.stage, "terminal cost": core.cost_terms.terminal}
    failed = [f"{name}: {part.fallback_reason}" for name, part in parts.items() if not part.compiled]
    if failed:
        print(f"compile: the planner fell back to eager ({'; '.join(failed)})", file=sys.stderr)
        return 1
    print(f"compile: planner step and costs compiled in {seconds:.1f} s")
    return 0
