"""``hydrosoft-stack status CONFIG [--json] [--wait S]``: each service's health, read from its status endpoint.

For ``--wait`` seconds (default ``DEFAULT_WINDOW_S``, above the runtime's 1 s status period; it ends early once
every service has reported) one SUB socket listens to the ``status/NAME`` and ``heartbeat/NAME`` topics of every
service of the config, then prints per service: state, pid, uptime, published and received message rates (Hz per
topic, from its newest ``ServiceStatus``), restarts, error counts by kind, the newest error text and the age of its
newest heartbeat, and its note when it has one (the F/T reader's bias and its age, or why its readings are
untared). A service that sent no status in the window is listed as ``no status`` (``null`` in JSON); that
is a report, not an error: the exit code is 0, or 2 for a bad config.

``--json`` prints one document ``{"services": {NAME: {state, pid, uptime_s, published_hz, received_hz, restarts,
errors, last_error, heartbeat_age_s, instance[, note]} | null}}`` (``note`` only when the service set one);
``instance`` is the stack launch the service belongs to (the table prints it once, or per service when they differ).
Refused requests are error kinds like any other (``rate_limited``, ``busy``, ``reply_too_large``, ``request_failed``,
``other_instance``), as are the links a subscriber lost (``link_dropped``).

Status endpoints on ``tcp://`` are read with the config's CURVE keys (``[curve]``), so ``status`` on either host
of a split stack shows every service of both. A status endpoint that is not local while the config holds no CURVE
keys is not read; the service is reported as ``null`` and a note goes to stderr.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import sys
import time
from collections.abc import Sequence
from typing import Any

from hydrosoft.services.bus.sockets import Bus, LatestSubscriber, Stale, is_local_endpoint
from hydrosoft.services.bus.config import ConfigError, StackConfig, load_config
from hydrosoft.services.bus.messages import Heartbeat, ServiceStatus, topic_for

#: How long ``status`` listens by default, s (the runtime publishes a status every second).
DEFAULT_WINDOW_S = 1.5

EXIT_OK = 0
EXIT_USAGE = 2

#: One service's report in the JSON document, or None when it sent no status.
Report = dict[str, Any] | None


def report_for(status: ServiceStatus | None, heartbeat_age_s: float | None) -> Report:
    """The JSON-ready report of one service from its newest status and the age of its newest heartbeat (s), or
    None when it sent no status."""
    if status is None:
        return None
    report = {
        "state": status.state,
        "pid": status.pid,
        "uptime_s": round(status.uptime_s, 3),
        "published_hz": {topic: round(hz, 2) for topic, hz in sorted(status.published_hz.items())},
        "received_hz": {topic: round(hz, 2) for topic, hz in sorted(status.received_hz.items())},
        "restarts": status.restarts,
        "errors": dict(sorted(status.errors.items())),
        "last_error": status.last_error,
        "heartbeat_age_s": None if heartbeat_age_s is None else round(heartbeat_age_s, 3),
        "instance": status.instance,
    }
    if status.note:
        report["note"] = status.note
    return report


def _rates(rates: dict[str, float]) -> str:
    return ", ".join(f"{topic} {hz:.1f}" for topic, hz in rates.items()) or "-"


def format_table(reports: dict[str, Report]) -> str:
    """A human-readable table of ``reports`` (service name -> report or None), one row per service with total
    rates, and indented detail lines for per-topic rates and errors."""
    header = (f"{'SERVICE':<26} {'STATE':<9} {'PID':>7} {'UPTIME':>9} {'PUB Hz':>7} {'RECV Hz':>8} {'RESTARTS':>8} "
              f"{'ERRORS':>6}")
    lines = [header]
    for name, report in reports.items():
        if report is None:
            lines.append(f"{name:<26} no status")
            continue
        errors = sum(report["errors"].values())
        lines.append(f"{name:<26} {report['state']:<9} {report['pid']:>7} {report['uptime_s']:>8.1f}s "
                     f"{sum(report['published_hz'].values()):>7.1f} {sum(report['received_hz'].values()):>8.1f} "
                     f"{report['restarts']:>8} {errors:>6}")
        lines.append(f"{'':<4}publishes: {_rates(report['published_hz'])}; receives: {_rates(report['received_hz'])}")
        if "note" in report:
            lines.append(f"{'':<4}note: {report['note']}")
        if report["heartbeat_age_s"] is None:
            lines.append(f"{'':<4}no heartbeat in the window")
        if errors:
            counts = ", ".join(f"{kind} {n}" for kind, n in report["errors"].items())
            lines.append(f"{'':<4}errors: {counts}; last: {report['last_error']}")
    launches = {name: report["instance"] for name, report in reports.items() if report is not None}
    if len(set(launches.values())) == 1:
        lines.append(f"stack launch {next(iter(launches.values()))}")
    elif launches:
        lines.append("services of SEVERAL stack launches: " + ", ".join(f"{name} {launch}"
                                                                        for name, launch in launches.items()))
    return "\n".join(lines)


async def collect(config: StackConfig, names: Sequence[str], window_s: float) -> dict[str, Report]:
    """Listen to the status endpoints of ``names`` for up to ``window_s`` s (less once every one has reported)
    and return each one's report (None: no status)."""
    keys = config.curve_keys()
    local = [name for name in names if keys is not None or is_local_endpoint(config.endpoint(name, "status"))]
    for name in names:
        if name not in local:
            print(f"status: {name}'s status endpoint {config.endpoint(name, 'status')} is not local; not read "
                  "(it needs the CURVE keys of a [curve] table)", file=sys.stderr)
    statuses: dict[str, ServiceStatus | None] = dict.fromkeys(names)
    heartbeat_ages: dict[str, float | None] = dict.fromkeys(names)
    if not local:
        return {name: None for name in names}
    with Bus(curve=keys, local_sources=config.local_sources()) as bus:
        topics = [topic_for(kind, name) for name in local for kind in (ServiceStatus, Heartbeat)]
        subscriber = LatestSubscriber(bus, [config.endpoint(name, "status") for name in local], topics)
        deadline_s = time.monotonic() + window_s
        while (remaining_s := deadline_s - time.monotonic()) > 0:
            await subscriber.wait(remaining_s)
            for name in local:
                for kind, found in ((ServiceStatus, statuses), (Heartbeat, heartbeat_ages)):
                    try:
                        received = subscriber.latest(topic_for(kind, name), math.inf, kind)
                    except Stale:
                        continue
                    found[name] = received.value if kind is ServiceStatus else received.age_s
            if all(statuses[name] is not None for name in local):
                break
    return {name: report_for(statuses[name], heartbeat_ages[name]) for name in names}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments: CONFIG [--json] [--wait S]."""
    parser.add_argument("config", help="the stack's TOML config (deploy/sim.toml, deploy/lab.toml)")
    parser.add_argument("--json", action="store_true",
                        help='print one JSON document {"services": {NAME: {...} | null}}')
    parser.add_argument("--wait", type=float, default=DEFAULT_WINDOW_S, metavar="S",
                        help=f"listen this long for status messages, s (default {DEFAULT_WINDOW_S})")


def run(args: argparse.Namespace) -> int:
    """Run ``hydrosoft-stack status``; the exit code (0, or 2 for a bad config or --wait)."""
    if not (math.isfinite(args.wait) and args.wait > 0):
        print(f"hydrosoft-stack status: --wait must be a positive number of seconds, got {args.wait}", file=sys.stderr)
        return EXIT_USAGE
    try:
        config = load_config(args.config)
    except ConfigError as err:
        print(f"hydrosoft-stack status: {err}", file=sys.stderr)
        return EXIT_USAGE
    reports = asyncio.run(collect(config, config.service_names(), args.wait))
    print(json.dumps({"services": reports}, indent=2) if args.json else format_table(reports))
    return EXIT_OK


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m hydrosoft.services.commands.status", description=__doc__.split("\n", 1)[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
