"""``hydrosoft-stack view CONFIG``: the live view of a running stack, without recording.

Runs the recorder service (``recorder``) as ``view`` with only its Foxglove WebSocket sink: it subscribes to every
publisher of the config and serves the scene (bubbles, object, contact forces, goal, plan, camera and depth images)
and the raw topics on ``ws://HOST:PORT`` (loopback only) until Ctrl-C. Open Foxglove, choose "Open connection",
"Foxglove WebSocket" and that URL. ``hydrosoft-stack launch CONFIG --view`` does the same as part of the stack.
"""

from __future__ import annotations

import argparse
import sys

from hydrosoft.services.recorder import VIEW_PORT, RecorderOptions, run_with_options

SERVICE = "view"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments: CONFIG [--host H] [--port P]."""
    parser.add_argument("config", help="the running stack's TOML config")
    parser.add_argument("--host", default="127.0.0.1", help="the address to serve on (loopback only)")
    parser.add_argument("--port", type=int, default=VIEW_PORT,
                        help=f"the port to serve on (default {VIEW_PORT}; 0: any free port, logged)")
    parser.add_argument("--name", default=SERVICE, help=f"service name (default {SERVICE})")


def run(args: argparse.Namespace) -> int:
    """Serve the live view until SIGINT/SIGTERM; the exit code (2: a bad config or option)."""
    return run_with_options(args, lambda: RecorderOptions(view=True, view_host=args.host, view_port=args.port))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m hydrosoft.services.commands.view", description=__doc__.split("\n")[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
