"""``hydrosoft-stack compile CONFIG``: build the artefacts of a config's compiled parts (sim_world's plant with
``sim.compile``, the planner's step and costs with ``planner.compile``) into torch's compile cache, so that every
launch after it loads them instead of compiling them.

Each part says what it does: it loads an artefact built for this config and torch, or builds a missing or stale one
(``services/bus/artefacts.py``), with a progress line every 15 s, and records it when done. The planner's step and
costs are built once, in its process, for one solver worker's share of the samples, and its worker processes then
load them, as at a launch. The parts build at once, each in a process of its own (``run``). Building from cold takes
minutes on a 2-core machine; a launch then starts each part from the cache. Run it once after an install, a torch
upgrade or a config change, as the user the stack runs as (the cache is per directory), before the first
``launch``; a launch that finds an artefact missing or stale builds it itself, saying so in its log and status. It
opens no device and no socket. Exit codes: 0 every part compiled (or nothing to compile), 1 a part fell back to
eager (named with its reason), 2 a config that cannot be used.
"""

from __future__ import annotations

import argparse
import functools
import multiprocessing
import sys
import threading
import time
from collections.abc import Callable, Mapping
from multiprocessing.connection import Connection
from pathlib import Path
from typing import NamedTuple

import torch

from hydrosoft.compilation import use_precompiled
from hydrosoft.services.bus import artefacts
from hydrosoft.services.bus.config import ConfigError, StackConfig, load_config
from hydrosoft.services.planner import PlannerCore, build_precompiled_rollouts, compile_planner
from hydrosoft.services.bus.service_cli import use_compile_cache
from hydrosoft.services.sim_world import TORCH_THREADS, SimPlant


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("config", type=Path, help="the stack's TOML config (deploy/lab.toml, deploy/sim.toml)")


class CompiledPart(NamedTuple):
    """One compiled part of a config: its artefact key, its torch threads, and ``prepare()``, which builds the part's
    model in the process that builds the part and returns what compiles it (``compile(rebuild)``: None once
    compiled, or why it fell back to eager; ``rebuild`` when its artefact is missing or stale) and the precompiled
    functions of its other processes (``artefacts.PartBuild.run``'s ``elsewhere``, or None)."""

    key: artefacts.ArtefactKey
    threads: int
    prepare: Callable[[], tuple[Callable[[bool], str | None], Callable[[], Mapping[str, int]] | None]]


def compiled_parts(config: StackConfig) -> list[CompiledPart]:
    """The config's compiled parts, in launch order. The plant is built with its precompiled directory set to build
    (``artefacts.use_precompiled``), so that its compiled functions are saved there whole, for every launch to load.
    The planner builds its precompiled functions in its process (``planner.build_precompiled``) when its artefact
    is missing or stale, then its solver worker processes load them, as at a launch. A part's ``prepare`` raises
    ValueError for a config whose arms the scene lacks."""
    parts = []
    if config.mode == "sim" and config.sim.compile:
        def prepare_plant() -> tuple[Callable[[bool], str | None], None]:
            artefacts.use_precompiled(config, artefacts.plant_key(config), build=True)
            plant = SimPlant.from_config(config)
            use_precompiled(None)
            return lambda rebuild: plant.compile(), None

        parts.append(CompiledPart(artefacts.plant_key(config), TORCH_THREADS, prepare_plant))
    if config.planner.compile:
        key = artefacts.planner_key(config)

        def prepare_planner() -> tuple[Callable[[bool], str | None], Callable[[], Mapping[str, int]] | None]:
            directory = artefacts.use_precompiled(config, key)  # its worker processes load from there
            core = PlannerCore.build(config)
            use_precompiled(None)

            def compile(rebuild: bool) -> str | None:
                return compile_planner(core, directory if rebuild else None)

            return compile, None if core.processes is None else core.processes.precompiled

        parts.append(CompiledPart(key, config.planner.threads, prepare_planner))
    return parts


class Outcome(NamedTuple):
    """How a part's build ended: ``code`` 0 compiled, 1 fell back to eager, 2 a config its model cannot be built
    from; ``reason`` says why for 1 and 2."""

    code: int
    reason: str = ""


def build_part(part: CompiledPart, cache: Path, say: Callable[[str], None]) -> Outcome:
    """Build (or load) ``part``'s artefact in this process, saying what happens through ``say``."""
    torch.set_num_threads(part.threads)
    try:
        compile, elsewhere = part.prepare()
    except ValueError as err:
        return Outcome(2, str(err))
    build = artefacts.PartBuild(part.key, cache)
    if not build.run(lambda: compile(not build.ready), say, elsewhere=elsewhere):
        return Outcome(1, f"{part.key.part}: {build.fallback}")
    return Outcome(0)


def build_planner_rollouts(config: StackConfig, cache: Path, say: Callable[[str], None]) -> Outcome:
    """The planner's functions without gradients (``planner.build_precompiled_rollouts``), into its artefact's
    precompiled directory, for the planner's build to load (a quarter of its CPU time, built beside it). A failure
    here is only said: the planner's build builds what it does not find, and says how that ends."""
    torch.set_num_threads(config.planner.threads)
    directory = artefacts.precompiled_dir(cache, artefacts.planner_key(config))
    say("planner: building its functions without gradients in a process of its own")
    started = time.monotonic()
    try:
        build_precompiled_rollouts(config, directory)
    except Exception as err:  # noqa: BLE001 - the planner's own build then builds them
        say(f"planner: its functions without gradients failed to build beside it ({type(err).__name__}: {err})")
    else:
        say(f"planner: its functions without gradients built in {time.monotonic() - started:.1f} s")
    return Outcome(0)


def _in_child(body: Callable[[Callable[[str], None]], Outcome], name: str, pipe: Connection) -> None:
    """A forked process's body: ``body(say)``, its lines and its outcome sent through ``pipe``."""
    try:
        outcome = body(lambda line: pipe.send(("line", line)))
    except BaseException as err:  # noqa: BLE001 - reported by the parent as the part's failure
        outcome = Outcome(1, f"{name}: {type(err).__name__}: {err}")
    pipe.send(("done", outcome))
    pipe.close()


class ForkedBuild:
    """``body(say) -> Outcome`` run in a process forked from this one (before this one has started threads or run
    any computation), whose lines this process prints as they come (``say``) from a thread of its own."""

    def __init__(self, name: str, body: Callable[[Callable[[str], None]], Outcome],
                 say: Callable[[str], None]) -> None:
        ours, theirs = multiprocessing.Pipe(duplex=False)
        self.process = multiprocessing.get_context("fork").Process(target=_in_child, args=(body, name, theirs),
                                                                   name=f"compile-{name}")
        self.process.start()
        theirs.close()
        self.outcome = Outcome(1, f"{name}: its build process died")
        self._relay = threading.Thread(target=self._read, args=(ours, say), name=f"compile-{name}-lines", daemon=True)
        self._relay.start()

    def _read(self, pipe: Connection, say: Callable[[str], None]) -> None:
        with pipe:
            while True:
                try:
                    kind, payload = pipe.recv()
                except (EOFError, OSError):
                    return
                if kind == "line":
                    say(payload)
                else:
                    self.outcome = payload

    def wait(self) -> Outcome:
        """The outcome, once the process has ended."""
        self.process.join()
        self._relay.join()
        if self.outcome.code and self.process.exitcode:
            return self.outcome._replace(reason=f"{self.outcome.reason} (exit code {self.process.exitcode})")
        return self.outcome


def run(args: argparse.Namespace) -> int:
    """Build the parts at once: each but the last in a process forked from this one, the last here (the plant's
    build and the planner's share the machine's cores instead of taking turns); a planner that builds has its
    functions without gradients built in one more forked process (``build_planner_rollouts``)."""
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

    def say(line: str) -> None:
        print(f"compile: {line}", flush=True)

    elsewhere = [ForkedBuild(part.key.part, functools.partial(build_part, part, cache), say) for part in parts[:-1]]
    if config.planner.compile and artefacts.check(cache, artefacts.planner_key(config)) != "ready":
        elsewhere.append(ForkedBuild("planner rollouts", functools.partial(build_planner_rollouts, config, cache), say))
    last = build_part(parts[-1], cache, say)
    outcomes = [process.wait() for process in elsewhere] + [last]
    refused = [outcome.reason for outcome in outcomes if outcome.code == 2]
    if refused:
        print(f"compile: {'; '.join(refused)}", file=sys.stderr)
        return 2
    eager = [outcome.reason for outcome in outcomes if outcome.code == 1]
    if eager:
        print(f"compile: fell back to eager ({'; '.join(eager)})", file=sys.stderr)
        return 1
    print(f"compile: {', '.join(part.key.part for part in parts)} compiled; artefacts in {cache}")
    return 0
