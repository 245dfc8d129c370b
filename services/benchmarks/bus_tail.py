"""``hydrosoft-stack bench bus --tail``: where a small message's latency tail comes from.

A ``Wrench`` at 1 kHz, over ipc and tcp, through four receive paths, run in turn (one round is every variant for
``--seconds`` each) for ``--rounds`` rounds, so that a machine whose load changes during the run loads each variant
alike; the variants are compared by ratio within the run:

- ``raw``: blocking pyzmq at both ends, no asyncio; the sender paces with ``time.sleep``. The machine's floor:
  the kernel, libzmq and the scheduler, nothing of ours but the message's encoding.
- ``poll``: an asyncio sender (``bus.Publisher``, paced with ``asyncio.sleep``) and a receiver that awaits the
  ``zmq.asyncio`` socket's ``poll()`` before each read, the way ``LatestSubscriber`` read until this benchmark.
- ``stack``: ``LatestSubscriber.wait`` as every service reads now (``loop.add_reader`` on the socket's file
  descriptor, every queued message read per wake-up), with Python's garbage collector as it comes.
- ``stack-gc``: the same with the services' collector settings in both processes
  (``garbage_collection.settle_garbage_collector``, which ``Service.ready`` calls: start-up objects collected once
  and frozen).

Each process records its garbage collections (``gc.callbacks``: generation and pause), the sender also how late each
of its wake-ups came (its pacing). A message's age is its receive time minus its ``stamp_ns`` (one host, one
monotonic clock). Reported per variant and transport: the p50, p99 and largest age over all rounds, each round's
p99, the median over rounds of the p99 relative to ``raw``'s in the same round, the share of ages over 1 ms, how many
of those overlap a collection in either process, the collections per second and their longest pause, and the
sender's pacing lateness (p50, p99). The run reports the load average before and after.
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import json
import math
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import msgspec
import numpy as np
import zmq
import zmq.asyncio

from hydrosoft.services.benchmarks.process_pair import (END_MARGIN_S, SILENCE_END_S, START_TIMEOUT_S, WARMUP_S,
                                                         newest_until_silence, run_pair)
from hydrosoft.services.bus.messages import decode, encode
from hydrosoft.garbage_collection import settle_garbage_collector
from hydrosoft.services.bus.sockets import Bus, LatestSubscriber, Publisher

VARIANTS = ("raw", "poll", "stack", "stack-gc")
TRANSPORTS = ("ipc", "tcp")
RATE_HZ = 1000.0
#: Ages over this are the tail this benchmark explains, ns: the target for small messages.
TAIL_NS = 1_000_000


class Collections:
    """The garbage collections of this process while ``recording`` (``gc.callbacks``): each as ``(start_ns, end_ns,
    generation)``; and the CPU time (ns) the process used from the first recorded message on (``cpu_ns``)."""

    def __init__(self) -> None:
        self.pauses: list[tuple[int, int, int]] = []
        self._recording = False
        self._start_ns = 0
        self._cpu_from_ns = 0
        gc.callbacks.append(self._callback)

    @property
    def recording(self) -> bool:
        return self._recording

    @recording.setter
    def recording(self, on: bool) -> None:
        if on and not self._recording:
            self._cpu_from_ns = time.process_time_ns()
        self._recording = on

    def cpu_ns(self) -> int:
        return time.process_time_ns() - self._cpu_from_ns if self._cpu_from_ns else 0

    def _callback(self, phase: str, info: dict) -> None:
        if not self.recording:
            return
        if phase == "start":
            self._start_ns = time.monotonic_ns()
        else:
            self.pauses.append((self._start_ns, time.monotonic_ns(), info["generation"]))


def _message():
    from hydrosoft.services.bus.messages import Wrench

    return Wrench(sensor="bench", wrench=np.array([0.5, -1.0, 9.8, 0.01, 0.02, -0.03]), tared=True)


# --- the two roles, each in its own process ---------------------------------------------------------------------


def publish(variant: str, endpoint: str, seconds: float) -> None:
    """Bind ``endpoint``, print ``BOUND <endpoint>``, wait for a line on stdin, publish a wrench at ``RATE_HZ`` for
    ``WARMUP_S + seconds``; print the count, the collections and the pacing lateness (ns) as JSON."""
    if variant == "stack-gc":
        settle_garbage_collector()
    collections = Collections()
    total = round((WARMUP_S + seconds) * RATE_HZ)
    if variant == "raw":
        lateness = _publish_raw(endpoint, total, collections)
    else:
        lateness = asyncio.run(_publish_bus(endpoint, total, collections))
    print(json.dumps({"sent": total, "gc": collections.pauses, "lateness_ns": lateness,
                      "cpu_ns": collections.cpu_ns()}), flush=True)


def _paced(total: int, collections: Collections):
    """The send instants: yields the planned time (ns) of each message and records how late each wake-up came."""
    period_ns = round(1e9 / RATE_HZ)
    warmup = round(WARMUP_S * RATE_HZ)
    next_ns = time.monotonic_ns()
    for index in range(total):
        collections.recording = index >= warmup
        yield next_ns
        next_ns = max(next_ns + period_ns, time.monotonic_ns() - period_ns)  # late: no catch-up burst


def _publish_raw(endpoint: str, total: int, collections: Collections) -> list[int]:
    context = zmq.Context()
    sock = context.socket(zmq.PUB)
    sock.setsockopt(zmq.LINGER, 0)
    sock.bind(endpoint)
    print(f"BOUND {sock.getsockopt_string(zmq.LAST_ENDPOINT)}", flush=True)
    sys.stdin.readline()
    message, lateness = _message(), []
    for seq, planned_ns in enumerate(_paced(total, collections), start=1):
        now = time.monotonic_ns()
        if planned_ns > now:
            time.sleep((planned_ns - now) * 1e-9)
            lateness.append(time.monotonic_ns() - planned_ns)
        stamped = msgspec.structs.replace(message, seq=seq, stamp_ns=time.monotonic_ns(), source="bench")
        sock.send_multipart(encode(stamped, stamped.topic), copy=False)
    sock.close()
    context.term()
    return lateness


async def _publish_bus(endpoint: str, total: int, collections: Collections) -> list[int]:
    message, lateness = _message(), []
    with Bus() as bus:
        publisher = Publisher(bus, endpoint, source="bench")
        print(f"BOUND {publisher.endpoint}", flush=True)
        await asyncio.get_running_loop().run_in_executor(None, sys.stdin.readline)
        for planned_ns in _paced(total, collections):
            now = time.monotonic_ns()
            if planned_ns > now:
                await asyncio.sleep((planned_ns - now) * 1e-9)
                lateness.append(time.monotonic_ns() - planned_ns)
            await publisher.send(message)
    return lateness


def subscribe(variant: str, endpoint: str, seconds: float) -> None:
    """Connect to ``endpoint``, print ``READY``, then take each handed-out message's ``(stamp_ns, received_ns)``
    after the warm-up until ``SILENCE_END_S`` without messages; print them and the collections as JSON."""
    if variant == "stack-gc":
        settle_garbage_collector()
    collections = Collections()
    warmup = round(WARMUP_S * RATE_HZ)
    deadline_s = time.monotonic() + START_TIMEOUT_S + WARMUP_S + seconds
    if variant == "raw":
        samples = _receive_raw(endpoint, warmup, deadline_s, collections)
    elif variant == "poll":
        samples = asyncio.run(_receive_poll(endpoint, warmup, deadline_s, collections))
    else:
        samples = asyncio.run(_receive_stack(endpoint, warmup, deadline_s, collections))
    print(json.dumps({"samples": samples, "gc": collections.pauses, "cpu_ns": collections.cpu_ns()}), flush=True)


def _subscribed(context: zmq.Context, endpoint: str) -> zmq.Socket:
    sock = context.socket(zmq.SUB)
    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.SUBSCRIBE, b"")
    sock.connect(endpoint)
    return sock


def _receive_raw(endpoint: str, warmup: int, deadline_s: float, collections: Collections) -> list[tuple[int, int]]:
    context = zmq.Context()
    sock = _subscribed(context, endpoint)
    print("READY", flush=True)
    samples: list[tuple[int, int]] = []
    while time.monotonic() < deadline_s:
        timeout_ms = SILENCE_END_S * 1e3 if samples else (deadline_s - time.monotonic()) * 1e3
        if not sock.poll(max(1, round(timeout_ms))):
            break
        _, message = decode(sock.recv_multipart(copy=False))
        received_ns = time.monotonic_ns()
        collections.recording = message.seq > warmup
        if message.seq > warmup:
            samples.append((message.stamp_ns, received_ns))
    sock.close()
    context.term()
    return samples


async def _receive_poll(endpoint: str, warmup: int, deadline_s: float, collections: Collections
                        ) -> list[tuple[int, int]]:
    context = zmq.asyncio.Context()
    sock = _subscribed(context, endpoint)
    print("READY", flush=True)
    samples: list[tuple[int, int]] = []
    while time.monotonic() < deadline_s:
        timeout_ms = SILENCE_END_S * 1e3 if samples else (deadline_s - time.monotonic()) * 1e3
        if not await sock.poll(max(1, round(timeout_ms))):
            break
        newest = None
        while sock.getsockopt(zmq.EVENTS) & zmq.POLLIN:
            _, newest = decode(sock.recv_multipart(zmq.NOBLOCK, copy=False).result())
        if newest is not None:
            received_ns = time.monotonic_ns()
            collections.recording = newest.seq > warmup
            if newest.seq > warmup:
                samples.append((newest.stamp_ns, received_ns))
    sock.close()
    context.term()
    return samples


async def _receive_stack(endpoint: str, warmup: int, deadline_s: float, collections: Collections
                         ) -> list[tuple[int, int]]:
    topic = _message().topic
    samples: list[tuple[int, int]] = []
    with Bus() as bus:
        subscriber = LatestSubscriber(bus, endpoint, [topic])
        print("READY", flush=True)
        async for newest in newest_until_silence(subscriber, topic, deadline_s, warmup):
            received_ns = newest.stamp_ns + round(newest.age_s * 1e9)  # when it was handed out
            collections.recording = newest.value.seq > warmup
            if newest.value.seq > warmup:
                samples.append((newest.value.stamp_ns, received_ns))
    return samples


# --- the orchestrator -------------------------------------------------------------------------------------------


async def measure(variant: str, transport: str, seconds: float, ipc_dir: Path) -> dict:
    """One variant over one transport: the sender's and the receiver's reports (``publish``, ``subscribe``)."""
    endpoint = {"tcp": "tcp://127.0.0.1:*", "ipc": f"ipc://{ipc_dir}/{variant}.ipc"}[transport]
    sent, got = await run_pair(
        lambda role, address: ["hydrosoft.services.benchmarks.bus_tail", role, variant, address, str(seconds)],
        endpoint, START_TIMEOUT_S, WARMUP_S + seconds + SILENCE_END_S + END_MARGIN_S)
    return {"sender": sent, "receiver": got}


def overlaps(samples: np.ndarray, pauses: list[tuple[int, int, int]]) -> np.ndarray:
    """Per sample ``(stamp_ns, received_ns)`` of ``samples (N, 2)``: whether a collection ``(start_ns, end_ns, _)``
    of ``pauses`` ran within its flight, ``(N,)`` bool."""
    if not pauses or len(samples) == 0:
        return np.zeros(len(samples), dtype=bool)
    spans = np.asarray([(start, end) for start, end, _ in pauses], dtype=np.int64)
    order = np.argsort(spans[:, 0])
    starts, ends = spans[order, 0], np.maximum.accumulate(spans[order, 1])
    # the last collection that started before the message arrived; it overlaps when it ended after the stamp
    last = np.searchsorted(starts, samples[:, 1], side="right") - 1
    return (last >= 0) & (ends[np.maximum(last, 0)] > samples[:, 0])


def summarize(variant: str, transport: str, runs: list[dict], seconds: float) -> dict:
    """One variant's rows over all rounds (``measure``'s reports): ages (us), tail shares, collections, pacing."""
    ages, tails, tails_in_gc, p99s = [], 0, 0, []
    gc_counts, longest_pause_ns, lateness = [0, 0, 0], 0, []
    cpu_ns = {"sender": 0, "receiver": 0}
    for run in runs:
        for role in cpu_ns:
            cpu_ns[role] += run[role]["cpu_ns"]
        samples = np.asarray(run["receiver"]["samples"], dtype=np.int64).reshape(-1, 2)
        age = samples[:, 1] - samples[:, 0]
        ages.append(age)
        p99s.append(float(np.percentile(age, 99)) * 1e-3 if len(age) else math.nan)
        tail = age > TAIL_NS
        pauses = run["sender"]["gc"] + run["receiver"]["gc"]
        tails += int(tail.sum())
        tails_in_gc += int((tail & overlaps(samples, pauses)).sum())
        for start, end, generation in pauses:
            gc_counts[generation] += 1
            longest_pause_ns = max(longest_pause_ns, end - start)
        lateness += run["sender"]["lateness_ns"]
    age_us = np.concatenate(ages) * 1e-3
    late_us = np.asarray(lateness, dtype=np.float64) * 1e-3
    measured_s = seconds * len(runs)
    return {
        "variant": variant, "transport": transport, "rounds": len(runs), "samples": int(age_us.size),
        "p50_us": round(float(np.percentile(age_us, 50)), 1), "p99_us": round(float(np.percentile(age_us, 99)), 1),
        "max_us": round(float(age_us.max()), 1), "round_p99_us": [round(p, 1) for p in p99s],
        "over_1ms": round(tails / max(age_us.size, 1), 5), "over_1ms_in_gc": tails_in_gc,
        "over_1ms_count": tails, "gc_per_s": [round(n / measured_s, 1) for n in gc_counts],
        "gc_longest_us": round(longest_pause_ns * 1e-3, 1),
        "receiver_cpu_us_per_msg": round(cpu_ns["receiver"] * 1e-3 / max(age_us.size, 1), 1),
        "sender_cpu_us_per_msg": round(cpu_ns["sender"] * 1e-3 / (seconds * RATE_HZ * len(runs)), 1),
        "pacing_late_p50_us": round(float(np.percentile(late_us, 50)), 1) if late_us.size else math.nan,
        "pacing_late_p99_us": round(float(np.percentile(late_us, 99)), 1) if late_us.size else math.nan,
    }


def with_ratios(rows: list[dict]) -> list[dict]:
    """Each row with ``p99_vs_raw``: the median over rounds of its round's p99 over ``raw``'s in the same round and
    transport (None without a ``raw`` row)."""
    raw = {row["transport"]: row["round_p99_us"] for row in rows if row["variant"] == "raw"}
    out = []
    for row in rows:
        floor = raw.get(row["transport"])
        ratio = None if floor is None else round(statistics.median(
            p / f for p, f in zip(row["round_p99_us"], floor) if f > 0), 2)
        out.append({**row, "p99_vs_raw": ratio})
    return out


async def measure_rounds(variants: list[str], transports: list[str], seconds: float, rounds: int) -> list[dict]:
    """Every variant over every transport, ``rounds`` times in turn; one summarized row per variant and transport."""
    reports: dict[tuple[str, str], list[dict]] = {(v, t): [] for t in transports for v in variants}
    with tempfile.TemporaryDirectory(prefix="hs-bench-tail-") as ipc_dir:
        for _ in range(rounds):
            for transport in transports:
                for variant in variants:
                    reports[variant, transport].append(await measure(variant, transport, seconds, Path(ipc_dir)))
    return with_ratios([summarize(v, t, runs, seconds) for (v, t), runs in reports.items()])


def format_table(rows: list[dict], load: tuple[list[float], list[float]]) -> str:
    """The rows as a text table, with the load averages before and after."""
    lines = [f"load average before {', '.join(f'{x:.2f}' for x in load[0])}; after "
             f"{', '.join(f'{x:.2f}' for x in load[1])}",
             f"{'variant':<9} {'tr':<4} {'p50 us':>7} {'p99 us':>8} {'max us':>8} {'p99/raw':>7} {'>1ms':>7} "
             f"{'in gc':>6} {'gc/s g0,g1,g2':>16} {'gc max us':>9} {'pace p99 us':>11} {'cpu us/msg tx,rx':>16}"]
    for r in rows:
        ratio = "-" if r["p99_vs_raw"] is None else f"{r['p99_vs_raw']:.2f}"
        lines.append(f"{r['variant']:<9} {r['transport']:<4} {r['p50_us']:7.1f} {r['p99_us']:8.1f} {r['max_us']:8.1f} "
                     f"{ratio:>7} {r['over_1ms']:7.2%} {r['over_1ms_in_gc']:>3}/{r['over_1ms_count']:<3}"
                     f"{','.join(f'{n:g}' for n in r['gc_per_s']):>15} {r['gc_longest_us']:9.1f} "
                     f"{r['pacing_late_p99_us']:11.1f} {r['sender_cpu_us_per_msg']:8.1f},"
                     f"{r['receiver_cpu_us_per_msg']:.1f}")
    return "\n".join(lines)


def run(seconds: float, rounds: int, as_json: bool) -> int:
    """Measure, print the table (or JSON), return the exit code."""
    before = list(os.getloadavg())
    rows = asyncio.run(measure_rounds(list(VARIANTS), list(TRANSPORTS), seconds, rounds))
    load = (before, list(os.getloadavg()))
    if as_json:
        print(json.dumps({"tail": rows, "load_average": {"before": load[0], "after": load[1]}}))
    else:
        print(format_table(rows, load))
    return 0


def main(argv: list[str] | None = None) -> int:
    """One process role: ``publish|subscribe VARIANT ENDPOINT SECONDS`` (started by ``measure``)."""
    parser = argparse.ArgumentParser(prog="hydrosoft.services.benchmarks.bus_tail")
    parser.add_argument("role", choices=["publish", "subscribe"])
    parser.add_argument("variant", choices=VARIANTS)
    parser.add_argument("endpoint")
    parser.add_argument("seconds", type=float)
    args = parser.parse_args(argv)
    (publish if args.role == "publish" else subscribe)(args.variant, args.endpoint, args.seconds)
    return 0


if __name__ == "__main__":
    sys.exit(main())
