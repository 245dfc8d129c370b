"""``hydrosoft-stack arm enable ARM``: a person re-enables an arm after an external stop.

After a pendant or dashboard stop or pause, a protective, safeguard or emergency stop, or any program stop the
stack did not send, the arm's commander holds the arm (``ArmState.latched``) until this request. The commander
refuses it while the controller still reports a safety stop or an unpowered arm, restarts the controller's program
when it is not running, logs who asked, and then moves the arm only for a goal started after it.

Exit code: 0 enabled, 1 refused (the reason is printed), 2 a bad config or arm, or no reply from the commander.
"""

from __future__ import annotations

import argparse
import asyncio
import getpass
import os
import sys

from hydrosoft.services.bus import messages as msg
from hydrosoft.services.bus.sockets import Bus, RequestClient
from hydrosoft.services.bus.config import ConfigError, load_config

# As services/client.py's (not imported from there: it loads torch, seconds of start-up for one request).
CONFIG_ENV = "HYDROSOFT_CONFIG"
DEFAULT_CONFIG = "deploy/sim.toml"
#: The commander may restart the controller's program before it answers (up to about 5 s on a real controller).
ENABLE_TIMEOUT_S = 10.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments: ARM [--config CONFIG] [--by NAME]."""
    parser.add_argument("arm", help="the arm's name (its [[arms]] name in the config)")
    parser.add_argument("--config", default=os.environ.get(CONFIG_ENV, DEFAULT_CONFIG),
                        help=f"the running stack's config (default ${CONFIG_ENV} or {DEFAULT_CONFIG})")
    parser.add_argument("--by", default=None, help="who re-enables the arm, for the commander's log (default: the "
                                                   "login name)")


async def enable(config_path: str, arm: str, by: str) -> msg.ArmEnableReply:
    """Send ``EnableArm`` to ``arm``'s commander and return its reply; TimeoutError when none comes."""
    config = load_config(config_path)
    config.arm(arm)
    with Bus(curve=config.curve_keys()) as bus:
        client = RequestClient(bus, config.endpoint(f"arm_commander-{arm}", "cmd"), source="arm enable",
                               timeout_s=ENABLE_TIMEOUT_S)
        reply = await client.request(msg.EnableArm(arm=arm, by=by))
    if not isinstance(reply, msg.ArmEnableReply):
        return msg.ArmEnableReply(ok=False, error=reply.error or f"unexpected reply {type(reply).__name__}")
    return reply


def run(args: argparse.Namespace) -> int:
    """``hydrosoft-stack arm enable``: the exit code (see the module docstring)."""
    by = args.by or getpass.getuser()
    try:
        reply = asyncio.run(enable(args.config, args.arm, by))
    except (ConfigError, TimeoutError) as err:
        print(f"hydrosoft-stack arm enable: {err}", file=sys.stderr)
        return 2
    if not reply.ok:
        print(f"hydrosoft-stack arm enable: refused: {reply.error}", file=sys.stderr)
        return 1
    print(f"arm {args.arm} enabled" + (f" (cleared: {reply.cleared})" if reply.cleared else " (no stop was latched)")
          + "; only a goal started from now moves it")
    return 0
