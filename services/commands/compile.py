"""``hydrosoft-stack compile CONFIG``: build the artefacts of a config's compiled parts (sim_world's plant with
``sim.compile``, the planner's step and costs with ``planner.compile``) into torch's compile cache, so that every
launch after it loads them instead of compiling them.

Each part says what it does: it loads an artefact built for this config and torch, or builds a missing or stale one
(``services/bus/artefacts.py``), with a progress line every 15 s, and records it when done. The planner's step and
costs are built once, in this process, for one solver worker's share of the samples, and its worker processes then
load them, as at a launch. Building from cold takes
minutes on a 2-core machine; a launch then starts each part from the cache. Run it once after an install, a torch
upgrade or a config change, as the user the stack runs as (the cache is per directory), before the first
``launch``; a launch that finds an artefact missing or stale builds it itself, saying so in its log and status. It
opens no device and no socket. Exit codes: 0 every part compiled (or nothing to compile), 1 a part fell back to
eager (named with its reason), 2 a config that cannot be used.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import NamedTuple

import torch

from hydrosoft.compilation import use_precompiled
from hydrosoft.services.bus import artefacts
from hydrosoft.services.bus.config import ConfigError, StackConfig, load_config
from hydrosoft.services.planner import PlannerCore, compile_planner
from hydrosoft.services.bus.service_cli import use_compile_cache
from hydrosoft.services.sim_world import TORCH_THREADS, SimPlant


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("config", type=Path, help="the stack's TOML config (deploy/lab.toml, deploy/sim.toml)")


class CompiledPart(NamedTuple):
    """One compiled part of a config: its artefact key, its torch threads, what compiles it (``compile(rebuild)``:
    None once compiled, or why it fell back to eager; ``rebuild`` when its artefact is missing or stale) and the
    precompiled functions of its other processes (``artefacts.PartBuild.run``'s ``elsewhere``)."""

    key: artefacts.ArtefactKey
    threads: int
    compile: Callable[[bool], str | None]
    elsewhere: Callable[[], Mapping[str, int]] | None = None


def compiled_parts(config: StackConfig) -> list[CompiledPart]:
    """The config's compiled parts, in launch order. The plant is built with its precompiled directory set to build
    (``artefacts.use_precompiled``), so that its compiled functions are saved there whole, for every launch to load.
    The planner builds its precompiled functions in this process (``planner.build_precompiled``) when its artefact
    is missing or stale, then its solver worker processes load them, as at a launch. Building a part's model here
    raises ValueError for a config whose arms the scene lacks."""
    parts = []
    if config.mode == "sim" and config.sim.compile:
        artefacts.use_precompiled(config, artefacts.plant_key(config), build=True)
        plant = SimPlant.from_config(config)
        parts.append(CompiledPart(artefacts.plant_key(config), TORCH_THREADS, lambda rebuild: plant.compile()))
        use_precompiled(None)
    if config.planner.compile:
        key = artefacts.planner_key(config)
        directory = artefacts.use_precompiled(config, key)  # its worker processes load from there
        core = PlannerCore.build(config)
        use_precompiled(None)

        def compile(rebuild: bool) -> str | None:
            return compile_planner(core, directory if rebuild else None)

        parts.append(CompiledPart(key, config.planner.threads, compile,
                                  None if core.processes is None else core.processes.precompiled))
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
    for part in parts:
        torch.set_num_threads(part.threads)
        build = artefacts.PartBuild(part.key, cache)
        if not build.run(lambda: part.compile(not build.ready), lambda line: print(f"compile: {line}", flush=True),
                         elsewhere=part.elsewhere):
            eager.append(f"{part.key.part}: {build.fallback}")
    if eager:
        print(f"compile: fell back to eager ({'; '.join(eager)})", file=sys.stderr)
        return 1
    print(f"compile: {', '.join(part.key.part for part in parts)} compiled; artefacts in {cache}")
    return 0
