"""The controller watchdog that ``URArm`` arms: an idle but live driver keeps the script running; when the driver
process dies mid-motion, the simulated controller stops the program and the arm within the watchdog period."""

from __future__ import annotations

import os
import selectors
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

WATCHDOG_PERIOD_S = 0.25  # URArmConfig's default watchdog_min_hz = 4
LINE_TIMEOUT_S = 10.0
IDLE_S = 0.8

# The driver process: connect, stay idle (the supervisor's kicks must keep the watchdog fed), then servo toward a
# target 0.3 m away, which the simulated TCP needs more than half a second to reach.
DRIVER = """
import asyncio, sys
import numpy as np
from hydrosoft.drivers.ur.arm import URArm
from hydrosoft.drivers.ur.config import URArmConfig

async def main(host):
    arm = URArm(URArmConfig(host=host))
    await arm.connect()
    print("connected", flush=True)
    await asyncio.sleep(float(sys.argv[2]))
    target = (await arm.read_state()).tcp_pose
    target[0] += 0.3
    for i in range(100000):
        await arm.servo_to(target)
        if i == 5:
            print("servoing", flush=True)
        await asyncio.sleep(0.008)

asyncio.run(main(sys.argv[1]))
"""


def read_line(proc: subprocess.Popen, timeout_s: float) -> str:
    with selectors.DefaultSelector() as selector:
        selector.register(proc.stdout, selectors.EVENT_READ)
        if not selector.select(timeout_s):
            raise TimeoutError(f"driver process printed nothing within {timeout_s} s")
        return proc.stdout.readline().strip()


@pytest.fixture
def driver_process(sim):
    proc = subprocess.Popen([sys.executable, "-c", DRIVER, sim.host, str(IDLE_S)], stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True)
    yield proc
    if proc.poll() is None:
        os.kill(proc.pid, signal.SIGKILL)
    proc.wait(5.0)
    proc.stdout.close()


def test_watchdog_stops_the_arm_when_the_driver_dies(sim, driver_process):
    assert read_line(driver_process, LINE_TIMEOUT_S) == "connected"
    assert sim.state()["watchdog_period_s"] == pytest.approx(WATCHDOG_PERIOD_S)
    time.sleep(IDLE_S / 2 + WATCHDOG_PERIOD_S)  # idle for longer than the watchdog period
    idle = sim.state()
    assert idle["runtime_state"] == 2
    assert idle["counters"].get("watchdog_expired", 0) == 0
    assert read_line(driver_process, LINE_TIMEOUT_S) == "servoing"
    start_x = idle["pose"][0]
    target_x = start_x + 0.3
    assert np.linalg.norm(sim.state()["twist"][:3]) > 0.0
    os.kill(driver_process.pid, signal.SIGKILL)
    killed = time.monotonic()
    while True:
        state = sim.state()
        if state["runtime_state"] == 1 and not any(state["twist"]):
            break
        assert time.monotonic() - killed < 2.0, f"arm still running 2 s after the driver died: {state}"
        time.sleep(0.01)
    stopped_s = time.monotonic() - killed
    # the watchdog period, plus the stop itself (1 m/s at 10 m/s^2: 0.1 s), plus polling
    assert stopped_s < WATCHDOG_PERIOD_S + 0.1 + 0.1
    assert state["counters"]["watchdog_expired"] == 1
    assert state["pose"][0] < target_x - 0.05  # stopped well short of the last commanded target
    time.sleep(0.1)
    assert sim.state()["pose"] == state["pose"]
