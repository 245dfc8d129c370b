"""A benchmark's publisher and subscriber processes, run as a pair: the publisher binds and reports its address,
the subscriber connects to it, both report their results as a JSON line (``bench bus``, ``bench bus --tail``)."""
from __future__ import annotations

import asyncio
import json
import math
import sys
import time
from collections.abc import AsyncIterator, Callable

from hydrosoft.services.bus.sockets import LatestSubscriber, Received, Stale

#: Messages of the first WARMUP_S seconds are sent but not measured.
WARMUP_S = 0.3
#: The subscriber ends after this long without a message (once measured messages have flowed), s.
SILENCE_END_S = 0.3
#: Longest wait for a process to start and report, s (imports on two busy cores); and beyond its run before it is
#: killed.
START_TIMEOUT_S = 20.0
END_MARGIN_S = 10.0


async def _first_line(process: asyncio.subprocess.Process, role: str, start_timeout_s: float) -> str:
    try:
        line = await asyncio.wait_for(process.stdout.readline(), start_timeout_s)  # type: ignore[union-attr]
    except TimeoutError:
        raise RuntimeError(f"the {role} process did not start within {start_timeout_s} s") from None
    if not line:
        raise RuntimeError(f"the {role} process exited before reporting (exit {await process.wait()})")
    return line.decode().strip()


async def _result(process: asyncio.subprocess.Process, role: str, timeout_s: float) -> dict:
    try:
        out, _ = await asyncio.wait_for(process.communicate(), timeout_s)
    except TimeoutError:
        raise RuntimeError(f"the {role} process did not finish within {timeout_s:.1f} s") from None
    if process.returncode != 0:
        raise RuntimeError(f"the {role} process failed (exit {process.returncode})")
    return json.loads(out.decode().strip().splitlines()[-1])


async def run_pair(arguments: Callable[[str, str], list[str]], endpoint: str, start_timeout_s: float,
                   limit_s: float) -> tuple[dict, dict]:
    """Run a publisher process bound to ``endpoint`` and a subscriber process connected to the address it reports
    (``BOUND ADDRESS``), start the sending once both are up, and return their reports (publisher's, subscriber's),
    each its last stdout line as JSON. ``arguments(role, address)``: the ``python -m`` arguments of role
    ``publish`` or ``subscribe``. Raises RuntimeError naming a process that does not report within
    ``start_timeout_s``, finish within ``limit_s`` of the start of the sending, or exit 0; every process started is
    ended before it returns."""
    processes: list[asyncio.subprocess.Process] = []

    async def start(role: str, address: str) -> asyncio.subprocess.Process:
        process = await asyncio.create_subprocess_exec(sys.executable, "-m", *arguments(role, address),
                                                       stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE)
        processes.append(process)
        return process

    try:
        publisher = await start("publish", endpoint)
        bound = (await _first_line(publisher, "publisher", start_timeout_s)).removeprefix("BOUND ")
        subscriber = await start("subscribe", bound)
        await _first_line(subscriber, "subscriber", start_timeout_s)
        publisher.stdin.write(b"go\n")  # type: ignore[union-attr]
        await publisher.stdin.drain()  # type: ignore[union-attr]
        return tuple(await asyncio.gather(_result(publisher, "publisher", limit_s),
                                          _result(subscriber, "subscriber", limit_s)))
    finally:
        for process in processes:
            if process.returncode is None:
                process.kill()
                await process.wait()


async def newest_until_silence(subscriber: LatestSubscriber, topic: str, deadline_s: float,
                               warmup_seq: int) -> AsyncIterator[Received]:
    """The newest message on ``topic`` each time ``subscriber`` wakes, until ``deadline_s`` (``time.monotonic()``)
    or, once a message past the warm-up (``seq`` over ``warmup_seq``) came, ``SILENCE_END_S`` without one."""
    measuring = False
    while time.monotonic() < deadline_s:
        waited_s = SILENCE_END_S if measuring else deadline_s - time.monotonic()
        if not await subscriber.wait(max(waited_s, 0.0)):
            return
        try:
            newest = subscriber.latest(topic, math.inf)
        except Stale:
            continue
        measuring = measuring or newest.value.seq > warmup_seq
        yield newest
