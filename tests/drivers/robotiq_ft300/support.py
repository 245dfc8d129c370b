"""Helpers of the FT 300 tests: an asyncio runner with a deadline, a wrench source whose every frame carries a
different wrench, and driver settings for tests."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Coroutine
from typing import Any

import numpy as np

from hydrosoft.drivers.base import WrenchSample
from hydrosoft.drivers.errors import DriverError
from hydrosoft.drivers.robotiq_ft300.config import FT300Config
from hydrosoft.drivers.robotiq_ft300.sensor import FT300Sensor

TEST_TIMEOUT_S = 20.0  # no single test coroutine may run longer; a hang fails instead of stalling the suite
POLL_S = 0.002
RECOVERY_TIMEOUT_S = 3.0  # a fresh sample must come within this (a reconnect takes about 0.3 s)


def run_async(coroutine: Coroutine[Any, Any, Any], timeout_s: float = TEST_TIMEOUT_S) -> Any:
    """Run ``coroutine`` on a fresh event loop, failing with ``TimeoutError`` after ``timeout_s``."""
    return asyncio.run(asyncio.wait_for(coroutine, timeout_s))


class CountingWrench:
    """A wrench source that gives frame ``k`` its own wrench (Mx = k mN - 15 N m, distinct for 30 000 frames),
    with Fx = 200.00 N (``20 4E`` inside the payload) every 5th frame and Fy = 200.00 N every 7th."""

    def __init__(self) -> None:
        self.calls = 0

    def __call__(self) -> np.ndarray:
        k = self.calls
        self.calls += 1
        fx = 200.0 if k % 5 == 0 else -100.0 + 0.01 * (k % 10_000)
        fy = 200.0 if k % 7 == 0 else 0.01 * (k % 13)
        return np.array([fx, fy, 5.0 - 0.01 * (k % 11), 0.001 * (k % 30_000) - 15.0, -0.25, 0.5])


def fast_config(port: str, **overrides: Any) -> FT300Config:
    """Driver settings for tests: defaults, with quicker reconnects."""
    settings = {"backoff_initial_s": 0.05, "backoff_max_s": 0.2} | overrides
    return FT300Config(port=port, **settings)


async def wait_for_sample(
    sensor: FT300Sensor, timeout_s: float = RECOVERY_TIMEOUT_S, after_ns: int = 0
) -> WrenchSample:
    """The first sample stamped after ``after_ns`` that ``read()`` returns, polling until ``timeout_s`` (on two busy
    cores a read right after connect can be stale: the threads may not have run for a few tens of ms)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            sample = await sensor.read()
            if sample.stamp_ns > after_ns:
                return sample
        except DriverError:
            pass
        await asyncio.sleep(POLL_S)
    raise TimeoutError(f"no fresh sample within {timeout_s} s; health {sensor.health()}")
