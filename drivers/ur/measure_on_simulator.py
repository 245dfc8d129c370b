"""Figures of ``URArm`` against the simulated controller: ``python -m hydrosoft.drivers.ur.measure_on_simulator``.

Starts the simulator as a subprocess on a free 127.0.0.N (ur_rtde must not share its process), then measures:
the event-loop freeze while connecting (ur_rtde's constructors hold the GIL), ``servo_to`` latency, servo tracking
error, ``Stale`` detection latency after a stream stall, reconnection time after the controller drops for 1 s, the
simulator's CPU use while serving both clients, and this process's own CPU use while the arm is connected and no
call is made (ur_rtde's receive threads, which poll their sockets every 100 us, and the driver's watchdog kicks: the
driver's floor in an idle stack).
Prints one line per figure; about 12 s in all.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import socket
import statistics
import subprocess
import sys
import time
from typing import Any

import numpy as np

from hydrosoft.drivers.errors import DriverError, Stale
from hydrosoft.drivers.ur.arm import URArm
from hydrosoft.drivers.ur.config import RTDE_PORT, SIM_CONTROL_PORT, URArmConfig

SIM_START_TIMEOUT_S = 10.0
LOOP_PROBE_PERIOD_S = 0.001
SERVO_CALLS = 500


def _free_host() -> str:
    for n in range(200, 251):
        host = f"127.0.0.{n}"
        with socket.socket() as probe:
            try:
                probe.bind((host, RTDE_PORT))
            except OSError:
                continue
        return host
    raise RuntimeError("no free 127.0.0.N in 200..250")


def _request(host: str, **fields: Any) -> dict[str, Any]:
    with socket.create_connection((host, SIM_CONTROL_PORT), timeout=2.0) as conn:
        conn.sendall((json.dumps(fields) + "\n").encode())
        return json.loads(conn.makefile().readline())


def _cpu_s(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as stat:
        fields = stat.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


class _LoopLag:
    """Longest gap between wake-ups of a 1 ms sleeper: how long the event loop was frozen."""

    def __init__(self) -> None:
        self.worst_s = 0.0
        self._task = asyncio.create_task(self._run())

    async def _run(self) -> None:
        while True:
            start = time.perf_counter()
            await asyncio.sleep(LOOP_PROBE_PERIOD_S)
            self.worst_s = max(self.worst_s, time.perf_counter() - start - LOOP_PROBE_PERIOD_S)

    def take(self) -> float:
        worst, self.worst_s = self.worst_s, 0.0
        return worst

    def cancel(self) -> None:
        self._task.cancel()


async def _measure(host: str, sim_pid: int) -> None:
    lag = _LoopLag()
    arm = URArm(URArmConfig(host=host, reconnect_initial_s=0.1, reconnect_max_s=0.5))
    start = time.perf_counter()
    await arm.connect()
    print(f"connect: {time.perf_counter() - start:.3f} s, longest event-loop freeze {lag.take() * 1e3:.1f} ms")

    pose = (await arm.read_state()).tcp_pose
    target = pose.copy()
    target[0] += 0.05
    latencies = []
    loop = asyncio.get_running_loop()
    next_t = loop.time()
    for i in range(SERVO_CALLS):
        step = pose + min(1.0, (i + 1) / 125) * (target - pose)
        step[3:] = pose[3:]
        t0 = time.perf_counter()
        await arm.servo_to(step)
        latencies.append(time.perf_counter() - t0)
        if i == 124:  # end of the ramp: how far the TCP lags the commanded target
            ramp_lag_mm = np.linalg.norm((await arm.read_state()).tcp_pose[:3] - step[:3]) * 1e3
        next_t += arm.config.servo_period_s
        await asyncio.sleep(max(0.0, next_t - loop.time()))
    ms = sorted(x * 1e3 for x in latencies)
    error_mm = np.linalg.norm((await arm.read_state()).tcp_pose[:3] - target[:3]) * 1e3
    print(f"servo_to latency over {SERVO_CALLS} calls at 125 Hz: median {statistics.median(ms):.2f} ms, "
          f"p99 {ms[int(0.99 * len(ms))]:.2f} ms, max {ms[-1]:.2f} ms; longest loop freeze {lag.take() * 1e3:.1f} ms")
    print(f"tracking: 5 cm ramp over 1 s (5 cm/s), lag {ramp_lag_mm:.2f} mm at its end, error {error_mm:.3f} mm "
          "after 3 s of holding")

    cpu0, wall0 = _cpu_s(sim_pid), time.perf_counter()
    await asyncio.sleep(2.0)
    cpu_share = (_cpu_s(sim_pid) - cpu0) / (time.perf_counter() - wall0)
    print(f"simulator CPU with both clients at 500 Hz: {cpu_share * 100:.0f} % of one core")

    lag.cancel()  # of ours only the driver's supervisor runs now (watchdog kicks); the rest is ur_rtde's threads
    cpu0, wall0 = _cpu_s(os.getpid()), time.perf_counter()
    await asyncio.sleep(2.0)
    idle_share = (_cpu_s(os.getpid()) - cpu0) / (time.perf_counter() - wall0)
    print(f"client CPU while connected and idle: {idle_share * 100:.1f} % of one core (ur_rtde's receive and control "
          "threads, and the driver's watchdog kicks)")
    lag = _LoopLag()

    _request(host, op="stall", duration_s=0.5)
    t0 = time.perf_counter()
    while True:
        try:
            await arm.read_state()
        except Stale:
            break
        await asyncio.sleep(0.001)
    print(f"stream stall -> Stale after {(time.perf_counter() - t0) * 1e3:.0f} ms "
          f"(max_age_s {arm.config.max_age_s * 1e3:.0f} ms)")
    await asyncio.sleep(0.6)

    _request(host, op="drop", duration_s=1.0)
    t0 = time.perf_counter()
    lag.take()
    while True:
        await asyncio.sleep(0.01)
        try:
            if time.perf_counter() - t0 > 0.1 and (await arm.read_state()).running:
                break
        except DriverError:
            pass
    print(f"controller dropped for 1.0 s -> running again after {time.perf_counter() - t0:.2f} s, "
          f"longest loop freeze {lag.take() * 1e3:.1f} ms")
    start = time.perf_counter()
    await arm.close()
    print(f"close (stopScript + disconnect): {time.perf_counter() - start:.2f} s, "
          f"longest loop freeze {lag.take() * 1e3:.1f} ms")
    lag.cancel()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m hydrosoft.drivers.ur.measure_on_simulator", description=__doc__)
    parser.add_argument("--host", default=None, help="127.0.0.N for the simulator (default: a free one in 200-250)")
    args = parser.parse_args(argv)
    host = args.host or _free_host()
    sim = subprocess.Popen([sys.executable, "-m", "hydrosoft.drivers.ur.simulator", "--host", host],
                           stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        deadline = time.monotonic() + SIM_START_TIMEOUT_S
        while True:
            try:
                _request(host, op="state")
                break
            except OSError:
                if time.monotonic() > deadline or sim.poll() is not None:
                    print(f"error: the simulator did not start on {host}", file=sys.stderr)
                    return 1
                time.sleep(0.05)
        asyncio.run(_measure(host, sim.pid))
    finally:
        sim.terminate()
        try:
            sim.wait(5.0)
        except subprocess.TimeoutExpired:
            sim.kill()
            sim.wait(5.0)
    return 0


if __name__ == "__main__":
    sys.exit(main())
