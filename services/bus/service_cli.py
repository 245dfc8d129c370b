"""The command line of a service process: ``python -m hydrosoft.services.MODULE CONFIG [--name NAME]``.

A service that runs once per stack (sim_world, the tag tracker, the planner, the recorder) uses ``add_arguments``
and ``run``; one that runs once per arm as ``MODULE-ARM`` (the arm commander, the F/T reader, the bubble camera)
uses ``add_arm_arguments`` and ``run_arm``. Both parse with ``main`` and end with ``exit_process``.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import logging
import os
import sys
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import NoReturn

from hydrosoft.services.bus.config import ConfigError, StackConfig, load_config
from hydrosoft.services.bus.runtime import run_service

CACHE_ENV = "TORCHINDUCTOR_CACHE_DIR"
#: The service's main: ``serve(service, config=...)``, or ``serve(service, config=..., arm=...)`` per arm.
Serve = Callable[..., Awaitable[None]]


def add_arguments(parser: argparse.ArgumentParser, service: str) -> None:
    """Arguments: CONFIG [--name NAME]."""
    parser.add_argument("config", help="the stack's TOML config (deploy/sim.toml, deploy/lab.toml)")
    parser.add_argument("--name", default=service, help=f"service name (default {service})")


def run(args: argparse.Namespace, serve: Serve, validate: Callable[[StackConfig], None] | None = None) -> int:
    """Run ``serve`` as the service ``args.name`` until SIGINT/SIGTERM; the exit code (2: a config that cannot be
    loaded, or a ``ConfigError`` from ``validate(config)``)."""
    try:
        config = load_config(args.config)
        if validate is not None:
            validate(config)
    except ConfigError as err:
        print(f"{args.name}: {err}", file=sys.stderr)
        return 2
    use_compile_cache(config)
    return run_service(args.name, config.runtime(args.name), functools.partial(serve, config=config))


def add_arm_arguments(parser: argparse.ArgumentParser, module: str) -> None:
    """Arguments of a per-arm service: CONFIG [--name MODULE-ARM]."""
    parser.add_argument("config", help="the stack's TOML config (deploy/sim.toml, deploy/lab.toml)")
    parser.add_argument("--name", default=None,
                        help=f"service name {module}-ARM (default: {module}- and the config's first arm)")


def run_arm(args: argparse.Namespace, module: str, serve: Serve,
            validate: Callable[[StackConfig, str], None] | None = None) -> int:
    """Run ``serve`` for the arm ``args.name`` names until SIGINT/SIGTERM; the exit code (2: a bad config or
    name, or a ``ConfigError`` from ``validate(config, arm)``)."""
    try:
        config = load_config(args.config)
        name, arm = config.arm_service(module, args.name)
        if validate is not None:
            validate(config, arm)
    except ConfigError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return run_service(name, config.runtime(name), functools.partial(serve, config=config, arm=arm))


def use_compile_cache(config: StackConfig) -> None:
    """Point torch's compile cache (inductor's and AOTAutograd's, ``TORCHINDUCTOR_CACHE_DIR``) at the config's
    ``compile_cache_dir``, unless the environment names one already (it wins: a benchmark that wants a cold start
    sets its own). Without either, torch uses ``/tmp/torchinductor_USER``, which a reboot, or systemd's
    ``PrivateTmp`` at every start, empties."""
    if config.compile_cache_dir is not None and CACHE_ENV not in os.environ:
        os.environ[CACHE_ENV] = str(Path(config.compile_cache_dir).expanduser())


def main(module: str, doc: str, argv: list[str] | None, add: Callable[[argparse.ArgumentParser], None],
         start: Callable[[argparse.Namespace], int]) -> int:
    """Parse ``argv`` with ``add`` and run ``start``: the body of a service module's ``main``."""
    parser = argparse.ArgumentParser(prog=f"python -m hydrosoft.services.{module}", description=doc.split("\n", 1)[0])
    add(parser)
    return start(parser.parse_args(argv))


def exit_process(code: int) -> NoReturn:
    """End a service process with exit status ``code`` once its ``main`` returned: flush the log and the standard
    streams, then leave at once (``os._exit``), skipping the interpreter's teardown. That teardown (torch's, ur_rtde's
    and zmq's modules) took 0.4-1.0 s per service on an idle machine and twice that on a loaded one, and the launcher
    stops the services one phase after another within ``commands.launch.SHUTDOWN_BOUND_S``. Nothing is lost by skipping it:
    everything a service must finish (the arm's stop, the bus's last messages, a recording's file) is done in its
    shutdown hooks, before ``run_service`` returns; any process it started is swept by the launcher with its group."""
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):  # a killed launcher's pipe: the log file holds the lines
            stream.flush()
    os._exit(code)
