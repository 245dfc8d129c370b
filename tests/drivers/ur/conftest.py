"""Helpers for the UR tests: a simulated controller in a subprocess on its own 127.0.0.N, and an event loop thread.

The simulator always runs in another process: ur_rtde's constructors hold the GIL while they wait for the
controller, so a simulator in the test process could not answer them. Every wait has a timeout, and every process
started here is stopped by its pid in teardown.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import os
import selectors
import socket
import subprocess
import sys
import threading
from collections.abc import Callable, Coroutine, Iterator
from typing import Any, TypeVar

import pytest

from hydrosoft.drivers.ur.config import DASHBOARD_PORT, RTDE_PORT, SIM_CONTROL_PORT

T = TypeVar("T")

SIM_READY_TIMEOUT_S = 10.0
SIM_STOP_TIMEOUT_S = 5.0
SOCKET_TIMEOUT_S = 2.0
FIRST_HOST, LAST_HOST = 2, 250
_host_counter = itertools.count()


def loopback_host() -> str:
    """A 127.0.0.N (N in 2..250) derived from the pid and a counter, whose RTDE port is free right now."""
    span = LAST_HOST - FIRST_HOST + 1
    for _ in range(span):
        host = f"127.0.0.{FIRST_HOST + (os.getpid() * 7 + next(_host_counter)) % span}"
        with socket.socket() as probe:
            try:
                probe.bind((host, RTDE_PORT))
            except OSError:
                continue
        return host
    raise RuntimeError("no free 127.0.0.N for a simulated UR controller")


class SimulatorProcess:
    """``python -m hydrosoft.drivers.ur.simulator`` on ``host``; ``request`` talks to its control endpoint."""

    def __init__(self, host: str, *extra_args: str) -> None:
        self.host = host
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "hydrosoft.drivers.ur.simulator", "--host", host, "--unlock-delay-s", "0",
             *extra_args],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        self._wait_ready()

    def _wait_ready(self) -> None:
        assert self.proc.stdout is not None
        with selectors.DefaultSelector() as selector:
            selector.register(self.proc.stdout, selectors.EVENT_READ)
            if not selector.select(SIM_READY_TIMEOUT_S):
                self.stop()
                raise TimeoutError(f"UR simulator on {self.host} not ready within {SIM_READY_TIMEOUT_S} s")
            line = self.proc.stdout.readline()
        if "ready" not in line:
            self.stop()
            raise RuntimeError(f"UR simulator on {self.host} failed to start: {line!r}")

    def request(self, op: str, **fields: Any) -> dict[str, Any]:
        """One control request (``op`` plus fields); returns the reply, which must say ``ok``."""
        with socket.create_connection((self.host, SIM_CONTROL_PORT), timeout=SOCKET_TIMEOUT_S) as conn:
            conn.sendall((json.dumps({"op": op, **fields}) + "\n").encode())
            reply = json.loads(conn.makefile().readline())
        assert reply["ok"], reply
        return reply

    def state(self) -> dict[str, Any]:
        return self.request("state")

    def stop(self) -> None:
        """SIGTERM by pid, then SIGKILL if it has not exited within ``SIM_STOP_TIMEOUT_S``."""
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(SIM_STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(SIM_STOP_TIMEOUT_S)
        if self.proc.stdout is not None:
            self.proc.stdout.close()


def dashboard_request(host: str, line: str) -> str:
    """Send one dashboard request and return the reply line (the banner is skipped)."""
    with socket.create_connection((host, DASHBOARD_PORT), timeout=SOCKET_TIMEOUT_S) as conn:
        lines = conn.makefile("rw", newline="\n")
        lines.readline()
        lines.write(line + "\n")
        lines.flush()
        return lines.readline().strip()


class LoopThread:
    """An asyncio loop running in a daemon thread, so drivers' background tasks run between test functions."""

    def __init__(self) -> None:
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self.loop.run_forever, name="test-loop", daemon=True)
        self._thread.start()

    def run(self, coro: Coroutine[Any, Any, T], timeout_s: float) -> T:
        """Run ``coro`` on the loop; ``TimeoutError`` (and the coroutine cancelled) past ``timeout_s``."""
        return asyncio.run_coroutine_threadsafe(asyncio.wait_for(coro, timeout_s), self.loop).result(timeout_s + 1.0)

    def close(self) -> None:
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(SIM_STOP_TIMEOUT_S)
        self.loop.close()


@pytest.fixture(scope="module")
def tick_hz() -> float | None:
    """The simulated controller's cycle (Hz) for ``sim``; None: the simulator's default (an e-Series' 500 Hz). A
    module overrides this fixture to run its tests at other rates."""
    return None


@pytest.fixture(scope="module")
def sim(tick_hz: float | None) -> Iterator[SimulatorProcess]:
    """A simulated controller for the whole test module, on a 127.0.0.N of its own, cycling at ``tick_hz``."""
    process = SimulatorProcess(loopback_host(), *(() if tick_hz is None else ("--tick-hz", str(tick_hz))))
    yield process
    process.stop()


@pytest.fixture
def start_simulator() -> Iterator[Callable[..., SimulatorProcess]]:
    """``start_simulator(host, *args)`` starts a simulator process; all are stopped at teardown."""
    started: list[SimulatorProcess] = []

    def start(host: str, *extra_args: str) -> SimulatorProcess:
        started.append(SimulatorProcess(host, *extra_args))
        return started[-1]

    yield start
    for process in started:
        process.stop()


@pytest.fixture
def free_host() -> str:
    """A 127.0.0.N where nothing listens on the RTDE port."""
    return loopback_host()


@pytest.fixture
def dashboard():
    """``dashboard(host, line) -> reply``: one request to a controller's dashboard server."""
    return dashboard_request


@pytest.fixture(scope="module")
def loop_thread() -> Iterator[LoopThread]:
    runner = LoopThread()
    yield runner
    runner.close()
