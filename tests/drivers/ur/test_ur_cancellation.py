"""A cancelled ur_rtde call always cancels its caller, also when the call finished just before the cancellation
was delivered (Python 3.11's ``asyncio.wait_for`` returned the result then, and a SIGINT was lost)."""

from __future__ import annotations

import asyncio
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import pytest

from hydrosoft.drivers.ur.arm import URArm
from hydrosoft.drivers.ur.config import URArmConfig


def test_a_cancellation_that_meets_a_finished_call_is_not_swallowed():
    arm = URArm(URArmConfig(host="127.0.0.9"))  # never connected: only the thread hop is exercised
    release, finished = threading.Event(), threading.Event()

    def call() -> str:
        release.wait(5.0)
        finished.set()
        return "state"

    async def scenario() -> None:
        with ThreadPoolExecutor(max_workers=1) as thread:
            task = asyncio.create_task(arm._on_thread(thread, call, 5.0))
            await asyncio.sleep(0.05)  # the task now waits on the thread
            release.set()
            assert finished.wait(5.0)
            time.sleep(0.05)  # the loop is held: the result is queued for it before the cancellation
            task.cancel()
            with pytest.raises(asyncio.CancelledError):
                await task

    asyncio.run(scenario())


def test_a_call_past_its_limit_times_out():
    arm = URArm(URArmConfig(host="127.0.0.9"))

    async def scenario() -> None:
        with ThreadPoolExecutor(max_workers=1) as thread:
            with pytest.raises(TimeoutError):
                await arm._on_thread(thread, lambda: time.sleep(0.3), 0.05)

    asyncio.run(scenario())
