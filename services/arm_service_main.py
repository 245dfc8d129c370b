"""The command line of a service that runs once per arm (``MODULE-ARM``): ``python -m
hydrosoft.services.MODULE CONFIG [--name MODULE-ARM]``, shared by the arm commander, the F/T reader and the
bubble camera (``main`` is ``service_main.main``).
"""

from __future__ import annotations

import argparse
import functools
import sys
from collections.abc import Awaitable, Callable

from hydrosoft.services.config import ConfigError, StackConfig, load_config
from hydrosoft.services.runtime import run_service

#: The service's main: ``serve(service, config=..., arm=...)``.
Serve = Callable[..., Awaitable[None]]


def add_arguments(parser: argparse.ArgumentParser, module: str) -> None:
    """Arguments: CONFIG [--name MODULE-ARM]."""
    parser.add_argument("config", help="the stack's TOML config (deploy/sim.toml, deploy/lab.toml)")
    parser.add_argument("--name", default=None,
                        help=f"service name {module}-ARM (default: {module}- and the config's first arm)")


def run(args: argparse.Namespace, module: str, serve: Serve,
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


