"""``hydrosoft-stack replay PATH.mcap``: publish a recording back onto the bus with its original timing.

Where. Each recorded message goes out on the endpoint its source service binds in the config (the data endpoint;
status and heartbeat on the status endpoint), from a publisher named as that service, so a service under test
(the planner, the tag tracker) receives it as if from the device or service that sent it. The replay binds the
endpoints of every source in the chosen topics: those services must not run meanwhile (``--topics`` picks what to
stand in for, e.g. ``--topics image/tag_camera`` to re-run a live tag tracker on recorded images). Requests and
replies (the client API) are not streams and are never replayed. The config is ``--config``, or else the one the
recorder stored in the file.

When. Messages leave in the order of their recorded publish stamps (``stamp_ns``; the file is in receive order,
which a ``REORDER_WINDOW_S`` buffer sorts), message i at ``start + (stamp_i - stamp_0) / rate``. A replay that
falls behind by up to ``MAX_BEHIND_S`` sends at once to catch up; further behind (a stalled process), its schedule
slips instead: that message goes out now and the later ones keep their recorded spacing from it, so subscribers
never get a burst at many times the recorded rate and the replayed rates stay the recorded ones (the replay then
ends later, by ``slipped_ms`` in its summary). It never skips a message. Before the first message it waits ``--connect-s`` for subscribers to
connect (a ZeroMQ subscriber misses what is sent before its connection is up).

What. Every field as recorded (arrays as the file holds them: bit for bit, camera images as their JPEG holds them
unless the recorder kept them raw) and ``hw_stamp_ns`` included, except ``seq`` and ``stamp_ns``,
which the replay's publishers set as every publisher does (``seq`` from 1 per topic, ``stamp_ns`` = now): the stack
refuses stamps from the future and treats old ones as stale, so a replayed message must carry the time it is sent.
A file cut short by a crash replays up to its last complete chunk.

Exit codes: 0 replayed, 1 nothing to replay, 2 a bad file, config or option.
"""

from __future__ import annotations

import argparse
import asyncio
import heapq
import json
import sys
import time
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from mcap.records import Channel

from hydrosoft.services.bus import messages as msg
from hydrosoft.services.bus.sockets import Bus, BusConfigError, Publisher
from hydrosoft.services.bus.config import ConfigError, StackConfig, load_config, parse_config
from hydrosoft.services.recording.mcap_format import (
    SOURCE_KEY,
    RecordedMessage,
    RecordingError,
    RecordingReader,
    bus_topic,
    raw_channel_name,
)

#: Messages are sorted by publish stamp within this window of the file's receive order, s.
REORDER_WINDOW_S = 0.5
#: Default wait between binding the endpoints and the first message, s.
CONNECT_S = 1.0
MAX_BEHIND_S = 0.05  # how far behind schedule a replay catches up by sending at once; beyond, the schedule slips
#: Messages each replay publisher queues per subscriber (a replay is for tests: a slow reader should get them all).
REPLAY_SNDHWM = 1000
#: Kinds that travel on a service's status endpoint.
STATUS_KINDS = (msg.ServiceStatus, msg.Heartbeat)


class ReplayError(Exception):
    """A recording that cannot be replayed with this config; the text says why."""


def endpoint_kind(kind: type[msg.Message]) -> str | None:
    """Which endpoint of its source a message of ``kind`` goes to: ``status``, ``data``, or None for the client
    API's requests and replies, which are not replayed."""
    if issubclass(kind, (msg.Request, msg.Reply)):
        return None
    return "status" if issubclass(kind, STATUS_KINDS) else "data"


def in_stamp_order(messages: Iterable[RecordedMessage], window_ns: int) -> Iterator[RecordedMessage]:
    """``messages`` (in receive order) in the order of their ``stamp_ns``, given that none arrived more than
    ``window_ns`` after a message stamped later (equal stamps keep their order)."""
    heap: list[tuple[int, int, RecordedMessage]] = []
    newest_ns = None
    for index, item in enumerate(messages):
        stamp_ns = item.message.stamp_ns
        newest_ns = stamp_ns if newest_ns is None else max(newest_ns, stamp_ns)
        heapq.heappush(heap, (stamp_ns, index, item))
        while heap and heap[0][0] < newest_ns - window_ns:
            yield heapq.heappop(heap)[2]
    while heap:
        yield heapq.heappop(heap)[2]


def recorded_config(reader: RecordingReader) -> StackConfig:
    """The stack config the recorder stored in the file. Raises ReplayError when it is not there."""
    text = reader.metadata.get("hydrosoft.run", {}).get("config_text")
    if text is None:
        raise ReplayError(f"{reader.path} holds no stack config (hydrosoft.run metadata): pass --config")
    return parse_config(text, origin=f"the config recorded in {reader.path}")


@dataclass
class ReplayStats:
    """What a replay sent: messages per topic, how far behind schedule the latest send was (s), how far the
    schedule slipped in all (s), what it left out (topic -> reason)."""

    sent: Counter[str] = field(default_factory=Counter)
    max_late_s: float = 0.0
    slipped_s: float = 0.0
    skipped: dict[str, str] = field(default_factory=dict)

    def summary(self) -> dict[str, object]:
        return {"messages": sum(self.sent.values()), "per_topic": dict(self.sent),
                "max_late_ms": round(1e3 * self.max_late_s, 2), "slipped_ms": round(1e3 * self.slipped_s, 2),
                "skipped": self.skipped}


class Schedule:
    """When each message is due (module docstring, "When"): ``wait_s`` of the first message anchors the schedule."""

    def __init__(self, rate: float, stats: ReplayStats) -> None:
        self.rate, self.stats = rate, stats
        self.start_s: float | None = None
        self.first_ns = 0

    def wait_s(self, stamp_ns: int, now_s: float) -> float:
        """Seconds to wait before sending the message recorded at ``stamp_ns`` (ns) at ``now_s`` (s, monotonic):
        0 when it is due or late; a send more than ``MAX_BEHIND_S`` late slips the schedule to now."""
        if self.start_s is None:
            self.start_s, self.first_ns = now_s, stamp_ns
        wait_s = self.start_s + (stamp_ns - self.first_ns) * 1e-9 / self.rate - now_s
        if wait_s < -MAX_BEHIND_S:
            self.start_s -= wait_s
            self.stats.slipped_s -= wait_s
        elif wait_s < 0:
            self.stats.max_late_s = max(self.stats.max_late_s, -wait_s)
        return max(wait_s, 0.0)


def plan_publishers(channels: dict[str, Channel], config: StackConfig) -> tuple[dict[str, tuple[str, str]],
                                                                                dict[str, str]]:
    """For each replayable raw channel of ``channels`` (by name), the endpoint to publish it on and the service
    publishing it; for each other channel why it is left out. Raises ReplayError when a replayable channel's
    service is not one of ``config``."""
    routes, skipped = {}, {}
    services = config.service_names()
    for name, channel in channels.items():
        where = endpoint_kind(msg.kind_for_topic(bus_topic(channel)))
        if where is None:
            skipped[name] = "a request or reply of the client API"
            continue
        source = channel.metadata.get(SOURCE_KEY, "")
        if source not in services:
            raise ReplayError(f"{bus_topic(channel)} was published by {source!r}, which is not a service of this "
                              f"config ({', '.join(services)}); leave it out with --topics")
        routes[name] = (config.endpoint(source, where), source)
    return routes, skipped


async def replay(reader: RecordingReader, config: StackConfig, rate: float = 1.0,
                 connect_s: float = CONNECT_S) -> ReplayStats:
    """Publish the raw messages of ``reader`` onto ``config``'s endpoints at ``rate`` times their recorded pace
    (see the module docstring). Raises ReplayError, RecordingError or BusConfigError (an endpoint that cannot be
    bound)."""
    if not rate > 0:
        raise ReplayError(f"--rate must be > 0, got {rate}")
    routes, skipped = plan_publishers(reader.raw_channels(), config)
    if not routes:
        raise ReplayError(f"{reader.path} holds no replayable topic"
                          + (f" among {', '.join(reader.topics)}" if reader.topics else ""))
    stats = ReplayStats(skipped=skipped)
    with Bus() as bus:
        publishers = {route: Publisher(bus, route[0], source=route[1], sndhwm=REPLAY_SNDHWM)
                      for route in set(routes.values())}
        await asyncio.sleep(connect_s)
        loop = asyncio.get_running_loop()
        schedule = Schedule(rate, stats)
        for item in in_stamp_order(reader, int(REORDER_WINDOW_S * 1e9)):
            route = routes.get(raw_channel_name(item.topic, item.message.source))
            if route is None:
                continue
            message = item.message
            wait_s = schedule.wait_s(message.stamp_ns, loop.time())
            if wait_s > 0:
                await asyncio.sleep(wait_s)
            await publishers[route].send(message, item.topic)
            stats.sent[item.topic] += 1
        await asyncio.sleep(connect_s / 2)  # let the last messages leave before the sockets close
    return stats


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments: PATH.mcap [--config CONFIG] [--rate X] [--topics T ...] [--connect-s S] [--json]."""
    parser.add_argument("recording", type=Path, help="an MCAP file written by the recorder")
    parser.add_argument("--config", default=None,
                        help="the stack config whose endpoints to publish on (default: the one recorded in the file)")
    parser.add_argument("--rate", type=float, default=1.0, help="speed factor (default 1: the original timing)")
    parser.add_argument("--topics", nargs="+", default=None, metavar="TOPIC",
                        help="replay only these topics and their sub-topics (e.g. image/tag_camera wrench)")
    parser.add_argument("--connect-s", type=float, default=CONNECT_S,
                        help=f"wait between binding and the first message, s (default {CONNECT_S})")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")


def run(args: argparse.Namespace) -> int:
    """Run ``hydrosoft-stack replay``; the exit code."""
    reader = RecordingReader(args.recording, args.topics)
    try:
        if not args.recording.is_file():
            raise RecordingError(f"{args.recording} does not exist")
        if args.config is not None:
            config = load_config(args.config)
        else:
            reader.raw_channels()
            config = recorded_config(reader)
        tic_s = time.monotonic()
        stats = asyncio.run(replay(reader, config, args.rate, args.connect_s))
    except (RecordingError, ConfigError, BusConfigError) as error:
        print(f"hydrosoft-stack replay: {error}", file=sys.stderr)
        return 2
    except ReplayError as error:
        print(f"hydrosoft-stack replay: {error}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps(stats.summary()))
        return 0
    print(f"replayed {sum(stats.sent.values())} messages on {len(stats.sent)} topics in "
          f"{time.monotonic() - tic_s:.1f} s (latest send {1e3 * stats.max_late_s:.1f} ms behind schedule, "
          f"schedule slipped {1e3 * stats.slipped_s:.1f} ms)")
    if reader.truncated:
        print(f"the file ends early (a crashed recorder?): replayed up to its last complete chunk ({reader.error})")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m hydrosoft.services.commands.replay", description=__doc__.split("\n")[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
