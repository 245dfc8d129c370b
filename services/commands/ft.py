"""``hydrosoft-stack ft tare ARM [--config CONFIG]``: ask arm ARM's running F/T reader to tare its sensor.

Sends ``Tare`` to ``ft_reader-ARM``'s cmd endpoint with the bus's ``RequestClient`` and prints the reply: the new
bias and when it was taken (exit 0), or why the reader refused (the arm is not at rest, the bubble is in contact,
the readings were not steady, the bias could not be stored: exit 1). No reply within ``REQUEST_TIMEOUT_S``, or a
bad config or arm: exit 2. The reader stores an accepted bias (``state_dir``) and keeps using it after restarts.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys

import numpy as np

from hydrosoft.services.bus import messages as msg
from hydrosoft.services.bus.sockets import Bus, RequestClient
from hydrosoft.services.bus.config import ConfigError, StackConfig, load_config

#: The config read when neither --config nor the environment variable names one (as ``hydrosoft-stack goal``).
DEFAULT_CONFIG = "deploy/sim.toml"
CONFIG_ENV = "HYDROSOFT_CONFIG"
#: How long to wait for the reader's answer, s: its checks, the ``ft_reader.TARE_S`` average and storing the file.
REQUEST_TIMEOUT_S = 5.0

EXIT_TARED = 0
EXIT_REFUSED = 1
EXIT_FAILED = 2


async def request_tare(config: StackConfig, arm: str, timeout_s: float = REQUEST_TIMEOUT_S) -> msg.TareReply:
    """``arm``'s F/T reader's reply to ``Tare``. Raises TimeoutError when it does not answer within ``timeout_s``,
    or the ``MessageError`` of a malformed reply."""
    with Bus(curve=config.curve_keys()) as bus:
        client = RequestClient(bus, config.endpoint(f"ft_reader-{arm}", "cmd"), source="ft tare", timeout_s=timeout_s)
        reply = await client.request(msg.Tare())
    if not isinstance(reply, msg.TareReply | msg.CommandReply):
        raise msg.UnknownTopic(f"ft_reader-{arm} answered Tare with {type(reply).__name__}")
    return reply


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments: ARM [--config CONFIG]."""
    parser.add_argument("arm", help="the arm whose F/T sensor to tare (its [[arms]] name)")
    parser.add_argument("--config", default=os.environ.get(CONFIG_ENV, DEFAULT_CONFIG),
                        help=f"the running stack's config (default ${CONFIG_ENV} or {DEFAULT_CONFIG})")


def run(args: argparse.Namespace) -> int:
    """Run ``hydrosoft-stack ft tare``; the exit code (0 tared, 1 refused, 2 no answer or a bad config or arm)."""
    try:
        config = load_config(args.config)
        config.arm(args.arm)
    except ConfigError as error:
        print(f"hydrosoft-stack ft tare: {error}", file=sys.stderr)
        return EXIT_FAILED
    try:
        reply = asyncio.run(request_tare(config, args.arm))
    except (TimeoutError, msg.MessageError) as error:
        print(f"hydrosoft-stack ft tare: {error} (is ft_reader-{args.arm} running?)", file=sys.stderr)
        return EXIT_FAILED
    if not reply.ok:
        print(f"hydrosoft-stack ft tare {args.arm}: {reply.error}", file=sys.stderr)
        return EXIT_REFUSED
    bias = " ".join(f"{v:.3f}" for v in np.asarray(reply.bias))
    print(f"tared {args.arm}: bias [{bias}] N, N m, stored in {config.state_path()}; the reader subtracts it from "
          "now on, also after a restart")
    return EXIT_TARED
