"""``hydrosoft-stack bench bus``: one-way latency of the bus between two processes on this host.

For each transport (``tcp://127.0.0.1`` and ``ipc://``) and payload (a ``Wrench``, a 640 x 480 uint16
``DepthFrame``) the benchmark starts a publisher process and a subscriber process. The publisher sends at a fixed
rate through ``bus.Publisher``; the subscriber reads through ``bus.LatestSubscriber`` as a service does and takes,
for each message it hands out, its age: ``time.monotonic_ns()`` after receiving and decoding minus the
publisher's ``stamp_ns`` (one host, one monotonic clock). The first ``WARMUP_S`` of messages are not measured
(connection set-up, slow joiner). Rows report the median and 99th percentile age in microseconds and the
messages per second the subscriber received. Targets: small messages p99 < 1 ms, depth frames p99 < 5 ms.

``--tcp-peer ADDRESS`` measures the link between two hosts instead: the publisher binds ``tcp://ADDRESS:*`` (another
127.0.0.N simulates the other host on one machine, a LAN address the real one), plain (``tcp-peer``) and with CURVE
(``tcp-peer-curve``: a fresh key pair in a temporary folder, as ``hydrosoft-stack keys generate`` writes it, and the
ZAP handshake the stack's services do). Both processes still run here, so their ages share one clock.

``--tail [--rounds N]`` explains a small message's latency tail instead (``bus_tail``): raw pyzmq against the
stack's receive paths and garbage-collector settings, in turns within one run, with each process's collections,
the sender's pacing and the load average.

Each row's two processes run ``python -m hydrosoft.services.benchmarks.bus publish|subscribe ...``; they are
stopped by pid when they overrun their time limits.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from hydrosoft.services.benchmarks import bus_tail
from hydrosoft.services.benchmarks.process_pair import (END_MARGIN_S, SILENCE_END_S, START_TIMEOUT_S, WARMUP_S,
                                                         newest_until_silence, run_pair)
from hydrosoft.services.bus.sockets import Bus, CurveKeys, LatestSubscriber, Publisher
from hydrosoft.services.commands.keys import generate_key_pair
from hydrosoft.services.bus.messages import DepthFrame, Message, Wrench

#: Publishing rate per payload, Hz: above an F/T sensor's stream rate we consume, and a depth camera's frame rate.
RATES_HZ = {"wrench": 1000.0, "depth_640x480": 100.0}
TRANSPORTS = ("tcp", "ipc")
#: The transports of ``--tcp-peer``: the other host's address, without and with CURVE.
PEER_TRANSPORTS = ("tcp-peer", "tcp-peer-curve")
#: The key pair's name in a ``tcp-peer-curve`` row's key folder.
BENCH_HOST = "bench"


def make_message(payload: str) -> Message:
    """The message a row publishes: a wrench, or a 640 x 480 uint16 depth frame of random values."""
    if payload == "wrench":
        return Wrench(sensor="bench", wrench=np.array([0.5, -1.0, 9.8, 0.01, 0.02, -0.03]), tared=True)
    depth = np.random.default_rng(0).integers(0, 4000, size=(480, 640), dtype=np.uint16)
    return DepthFrame(bubble="bench", depth=depth, depth_scale_m=1e-4, fx_px=380.0, fy_px=380.0, cx_px=320.0,
                      cy_px=240.0)


@dataclass(frozen=True)
class Row:
    """One payload over one transport. p50_us, p99_us: message age when handed out, us; msgs_per_s: messages the
    subscriber received per second of measurement; rate_hz: the publishing rate; sent, received: message counts
    after the warm-up; samples: ages measured (one per hand-out, so at most ``received``)."""

    payload: str
    transport: str
    p50_us: float
    p99_us: float
    msgs_per_s: float
    rate_hz: float
    sent: int
    received: int
    samples: int


# --- the two roles, each in its own process ---------------------------------------------------------------------


def curve_keys(key_dir: str) -> CurveKeys | None:
    """CURVE on every tcp endpoint with the pair in ``key_dir`` (its public key the only one admitted), or None for
    an empty ``key_dir``."""
    if not key_dir:
        return None
    folder = Path(key_dir)
    return CurveKeys(folder / f"{BENCH_HOST}.key_secret", folder / "authorized", loopback=True)


async def publish(endpoint: str, payload: str, seconds: float, key_dir: str = "") -> None:
    """Bind ``endpoint`` (with CURVE when ``key_dir`` names a key folder), print ``BOUND <endpoint>``, wait for a
    line on stdin, then publish ``payload`` at its rate for ``WARMUP_S + seconds`` and print ``{"sent": N}``
    (messages after the warm-up)."""
    rate_hz = RATES_HZ[payload]
    period_ns = round(1e9 / rate_hz)
    warmup_count = round(WARMUP_S * rate_hz)
    total = warmup_count + round(seconds * rate_hz)
    message = make_message(payload)
    with Bus(curve=curve_keys(key_dir)) as bus:
        publisher = Publisher(bus, endpoint, source="bench_publisher")
        print(f"BOUND {publisher.endpoint}", flush=True)
        await asyncio.get_running_loop().run_in_executor(None, sys.stdin.readline)
        next_ns = time.monotonic_ns()
        for _ in range(total):
            await publisher.send(message)
            next_ns = max(next_ns + period_ns, time.monotonic_ns() - period_ns)  # late: no catch-up burst
            await asyncio.sleep(max(0.0, (next_ns - time.monotonic_ns()) * 1e-9))
    print(json.dumps({"sent": total - warmup_count}), flush=True)


async def subscribe(endpoint: str, payload: str, seconds: float, key_dir: str = "") -> None:
    """Connect to ``endpoint`` (with CURVE when ``key_dir`` names a key folder), print ``READY``, then take the age of every message handed out (after the
    warm-up's ``seq``) until ``SILENCE_END_S`` without messages; print the counts and percentiles as JSON."""
    rate_hz = RATES_HZ[payload]
    warmup_count = round(WARMUP_S * rate_hz)
    topic = make_message(payload).topic
    ages_ns: list[int] = []
    received = 0
    deadline_s = time.monotonic() + START_TIMEOUT_S + WARMUP_S + seconds
    with Bus(curve=curve_keys(key_dir)) as bus:
        subscriber = LatestSubscriber(bus, endpoint, [topic])
        print("READY", flush=True)
        async for newest in newest_until_silence(subscriber, topic, deadline_s, warmup_count):
            if newest.value.seq > warmup_count:
                ages_ns.append(round(newest.age_s * 1e9))
                received = subscriber.received[topic] - warmup_count
    ages_us = np.asarray(ages_ns, dtype=np.float64) * 1e-3
    print(json.dumps({
        "received": received,
        "samples": len(ages_ns),
        "p50_us": float(np.percentile(ages_us, 50)) if ages_ns else math.nan,
        "p99_us": float(np.percentile(ages_us, 99)) if ages_ns else math.nan,
    }), flush=True)


# --- the orchestrator -------------------------------------------------------------------------------------------


async def measure(payload: str, transport: str, seconds: float, ipc_dir: Path, peer: str = "") -> Row:
    """Run one publisher and one subscriber process for ``payload`` over ``transport`` (to ``peer``'s address for
    the ``PEER_TRANSPORTS``; ``ipc_dir`` also holds a ``tcp-peer-curve`` row's keys) and return their row."""
    endpoints = {"tcp": "tcp://127.0.0.1:*", "ipc": f"ipc://{ipc_dir}/{payload}.ipc", "tcp-peer": f"tcp://{peer}:*",
                 "tcp-peer-curve": f"tcp://{peer}:*"}
    endpoint = endpoints[transport]
    key_dir = ""
    if transport == "tcp-peer-curve":
        key_dir = str(ipc_dir / "keys")
        if not (ipc_dir / "keys").exists():
            public, _ = generate_key_pair(ipc_dir / "keys", BENCH_HOST)
            (ipc_dir / "keys" / "authorized").mkdir()
            (ipc_dir / "keys" / "authorized" / public.name).write_bytes(public.read_bytes())
    sent, got = await run_pair(
        lambda role, address: ["hydrosoft.services.benchmarks.bus", role, address, payload, str(seconds), key_dir],
        endpoint, START_TIMEOUT_S, WARMUP_S + seconds + SILENCE_END_S + END_MARGIN_S)
    return Row(payload=payload, transport=transport, p50_us=round(got["p50_us"], 1), p99_us=round(got["p99_us"], 1),
               msgs_per_s=round(got["received"] / seconds, 1), rate_hz=RATES_HZ[payload], sent=int(sent["sent"]),
               received=int(got["received"]), samples=int(got["samples"]))


async def measure_all(seconds: float, peer: str = "") -> list[Row]:
    """Every payload over every transport (the ``PEER_TRANSPORTS`` to ``peer`` when one is given), one after the
    other."""
    transports = PEER_TRANSPORTS if peer else TRANSPORTS
    with tempfile.TemporaryDirectory(prefix="hs-bench-") as ipc_dir:
        return [await measure(payload, transport, seconds, Path(ipc_dir), peer)
                for transport in transports for payload in RATES_HZ]


def format_table(rows: list[Row]) -> str:
    """The rows as a text table."""
    lines = [f"{'payload':<14} {'transport':<14} {'p50 us':>8} {'p99 us':>8} {'msgs/s':>8} {'rate Hz':>8} "
             f"{'sent':>6} {'received':>8}"]
    lines += [f"{r.payload:<14} {r.transport:<14} {r.p50_us:8.1f} {r.p99_us:8.1f} {r.msgs_per_s:8.1f} "
              f"{r.rate_hz:8.0f} {r.sent:6d} {r.received:8d}" for r in rows]
    return "\n".join(lines)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of ``hydrosoft-stack bench bus``."""
    parser.add_argument("--seconds", type=float, default=2.0,
                        help="measured seconds per payload and transport, after a 0.3 s warm-up (default 2)")
    parser.add_argument("--json", action="store_true", help='print {"rows": [...]} as JSON instead of a table')
    parser.add_argument("--tail", action="store_true",
                        help="explain the small-message latency tail: raw pyzmq vs the stack's receive paths and "
                             "garbage-collector settings, in turns within one run (services/benchmarks/bus_tail.py)")
    parser.add_argument("--rounds", type=int, default=3,
                        help="with --tail: rounds of every variant in turn (default 3)")
    parser.add_argument("--tcp-peer", default="", metavar="ADDRESS",
                        help="measure tcp to this address (another 127.0.0.N simulates a second host), without and "
                        "with CURVE, instead of tcp and ipc on loopback")


def run(args: argparse.Namespace) -> int:
    """Measure every row and print them; return the exit code."""
    if not args.seconds > 0:
        print(f"--seconds must be > 0, got {args.seconds}", file=sys.stderr)
        return 2
    if getattr(args, "tail", False):
        if args.rounds < 1:
            print(f"--rounds must be >= 1, got {args.rounds}", file=sys.stderr)
            return 2
        return bus_tail.run(args.seconds, args.rounds, args.json)
    rows = asyncio.run(measure_all(args.seconds, getattr(args, "tcp_peer", "")))
    if args.json:
        print(json.dumps({"rows": [asdict(row) for row in rows]}))
    else:
        print(format_table(rows))
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m hydrosoft.services.benchmarks.bus [--seconds S] [--json] [--tcp-peer ADDRESS]``, or one process
    role (``publish|subscribe ENDPOINT PAYLOAD SECONDS [KEY_DIR]``, started by ``measure``)."""
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] in ("publish", "subscribe"):
        role = argparse.ArgumentParser(prog="hydrosoft.services.benchmarks.bus ROLE")
        role.add_argument("role", choices=["publish", "subscribe"])
        role.add_argument("endpoint")
        role.add_argument("payload", choices=sorted(RATES_HZ))
        role.add_argument("seconds", type=float)
        role.add_argument("key_dir", nargs="?", default="")
        args = role.parse_args(argv)
        asyncio.run((publish if args.role == "publish" else subscribe)(args.endpoint, args.payload, args.seconds,
                                                                        args.key_dir))
        return 0
    parser = argparse.ArgumentParser(prog="hydrosoft-stack bench bus", description=__doc__.splitlines()[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
