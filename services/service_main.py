"""The command line of a service that runs once per stack: ``python -m hydrosoft.services.MODULE CONFIG [--name
NAME]``, shared by sim_world, the tag tracker and the planner (per-arm services: ``arm_service_main``)."""

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

from hydrosoft.services.config import ConfigError, StackConfig, load_config
from hydrosoft.services.runtime import run_service

CACHE_ENV = "TORCHINDUCTOR_CACHE_DIR"
#: The service's main: ``serve(service, config=...)``.
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
    stops the services one phase after another within ``launcher.SHUTDOWN_BOUND_S``. Nothing is lost by skipping it:
    everything a service must finish (the arm's stop, the bus's last messages, a recording's file) is done in its
    shutdown hooks, before ``run_service`` returns; any process it started is swept by the launcher with its group."""
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):  # a killed launcher's pipe: the log file holds the lines
            stream.flush()
    os._exit(code)
