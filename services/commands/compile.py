"""``hydrosoft-stack compile CONFIG``: build the artefacts of a config's compiled parts (sim_world's plant with
``sim.compile``, the planner's step and costs with ``planner.compile``) into torch's compile cache, so that every
launch after it loads them instead of compiling them.

Each part says what it does: it loads an artefact built for this config and torch, or builds a missing or stale one
(``services/bus/artefacts.py``), with a progress line every 15 s, and records it when done. Building from cold takes
minutes on a 2-core machine; a launch then starts each part from the cache. Run it once after an install, a torch
upgrade or a config change, as the user the stack runs as (the cache is per directory), before the first
``launch``; a launch that finds an artefact missing or stale builds it itself, saying so in its log and status. It
opens no device and no socket. Exit codes: 0 every part compiled (or nothing to compile), 1 a part fell back to
eager (named with its reason), 2 a config that cannot be used.
"""

from __future__ import annotations

import argparse
import functools
import sys
from collections.abc import Callable
from pathlib import Path

import torch

from hydrosoft.compilation import use_precompiled
from hydrosoft.services.bus import artefacts
from hydrosoft.services.bus.config import ConfigError, StackConfig, load_config
from hydrosoft.services.planner import PlannerCore, compile_planner
from hydrosoft.services.bus.service_cli import use_compile_cache
from hydrosoft.services.sim_world import TORCH_THREADS, SimPlant


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("config", type=Path, help="the stack's TOML config (deploy/lab.toml, deploy/sim.toml)")


def compiled_parts(config: StackConfig) -> list[tuple[artefacts.ArtefactKey, int, Callable[[], str | None]]]:
    """The config's compiled parts, in launch order: each part's key, its torch threads and what compiles it (None
    once compiled, or why it fell back to eager). The plant is built with its precompiled directory set to build
    (``artefacts.use_precompiled``), so that its compiled functions are saved there whole, for every launch to load.
    Building a part's model here raises ValueError for a config whose arms the scene lacks."""
    parts = []
    if config.mode == "sim" and config.sim.compile:
        artefacts.use_precompiled(config, artefacts.plant_key(config), build=True)
        plant = SimPlant.from_config(config)
        parts.append((artefacts.plant_key(config), TORCH_THREADS, plant.compile))
        use_precompiled(None)  # the planner's functions are not precompiled (artefacts)
    if config.planner.compile:
        core = PlannerCore.build(config)
        parts.append((artefacts.planner_key(config), config.planner.threads, functools.partial(compile_planner, core)))
    return parts


def run(args: argparse.Namespace) -> int:
    try:
        config = load_config(args.config)
        use_compile_cache(config)  # before anything of torch's asks for its cache (which then fixes the variable)
        parts = compiled_parts(config)
    except (ConfigError, ValueError) as err:
        print(f"compile: {err}", file=sys.stderr)
        return 2
    if not parts:
        print(f"compile: nothing to compile: {args.config} runs the plant and the planner eager (sim.compile and "
              f"planner.compile are false)")
        return 0
    cache = artefacts.cache_dir(config)
    eager = []
    for key, threads, compile in parts:
        torch.set_num_threads(threads)
        build = artefacts.PartBuild(key, cache)
        if not build.run(compile, lambda line: print(f"compile: {line}", flush=True)):
            eager.append(f"{key.part}: {build.fallback}")
    if eager:
        print(f"compile: fell back to eager ({'; '.join(eager)})", file=sys.stderr)
        return 1
    print(f"compile: {', '.join(key.part for key, _, _ in parts)} compiled; artefacts in {cache}")
    return 0
