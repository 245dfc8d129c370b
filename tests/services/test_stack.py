"""The whole stack in sim-hardware mode as separate processes: the launcher starts sim_world (plant, simulated UR
controller, FT 300 pty, rendered camera and depth images), the arm commander (the real ur_rtde client), the F/T
reader (the real serial driver), the bubble camera, the tag tracker and the planner; the client pushes the cube.

Every process is stopped by its pid (the launcher's process group, then a check that none is left).
"""

from __future__ import annotations

import asyncio
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hydrosoft.services.client import StackClient, true_error_mm
from hydrosoft.services.config import load_config

pytestmark = pytest.mark.slow

SIM_TOML = Path(__file__).parents[2] / "deploy" / "sim.toml"
READY_TIMEOUT_S = 240.0  # every service up and READY on a busy 2-core machine
GOAL_TIMEOUT_S = 240.0
STOP_BOUND_S = 10.0
#: The planner's heartbeat timeout (deploy/sim.toml: 0.5 s) plus one servo period (8 ms), plus the time for the
#: commander's next published state to show it (one servo period) and scheduling slack on a busy machine.
KILL_STOP_BOUND_S = 0.5 + 0.008 + 0.008 + 0.2
def free_ur_host() -> str:
    """A 127.0.0.N whose UR ports are free right now (another test's simulated controller may still hold its own)."""
    import socket

    for offset in range(60):
        host = f"127.0.0.{60 + (os.getpid() + offset) % 60}"
        with socket.socket() as probe:
            try:
                probe.bind((host, 30004))
            except OSError:
                continue
        return host
    raise RuntimeError("no free 127.0.0.N for the simulated UR controller")


def stack_config(tmp_path: Path) -> Path:
    """deploy/sim.toml with its run_dir, FT 300 link and UR address made private to this test."""
    run_dir = tmp_path / "run"
    text = SIM_TOML.read_text()
    text = text.replace('"/tmp/hydrosoft-sim/ft300-bubble"', f'"{run_dir}/ft300-bubble"')
    text = text.replace('"/tmp/hydrosoft-sim"', f'"{run_dir}"').replace('"127.0.0.2"', f'"{free_ur_host()}"')
    path = tmp_path / "sim.toml"
    path.write_text(text)
    return path


class Stack:
    """The launcher as a subprocess in its own session, its output collected to a file."""

    def __init__(self, config: Path, log: Path) -> None:
        self.config, self.log = config, log
        self._out = log.open("wb")
        self.process = subprocess.Popen([sys.executable, "-m", "hydrosoft.services.cli", "launch", str(config)],
                                        stdout=self._out, stderr=subprocess.STDOUT, start_new_session=True)

    def text(self) -> str:
        return self.log.read_text(errors="replace")

    def wait_ready(self, client: StackClient) -> None:
        deadline = time.monotonic() + READY_TIMEOUT_S
        while time.monotonic() < deadline:
            assert self.process.poll() is None, f"the launcher exited early:\n{self.text()[-4000:]}"
            try:
                asyncio.run(asyncio.wait_for(client.status(), 5.0))
                return
            except Exception:  # noqa: BLE001 - not up yet
                time.sleep(1.0)
        raise AssertionError(f"the stack did not become ready within {READY_TIMEOUT_S} s:\n{self.text()[-4000:]}")

    def stop(self) -> float:
        """SIGINT the launcher; the seconds until it exited (SIGKILL of its group after the bound)."""
        if self.process.poll() is not None:
            return 0.0
        tic = time.monotonic()
        os.killpg(self.process.pid, signal.SIGINT)
        try:
            self.process.wait(STOP_BOUND_S + 5)
        except subprocess.TimeoutExpired:
            os.killpg(self.process.pid, signal.SIGKILL)
            self.process.wait(5)
        self._out.close()
        return time.monotonic() - tic


async def kill_the_planner_mid_task(client: StackClient) -> tuple[float, int]:
    """Start a second goal, SIGKILL the planner while the arm servoes, and return the seconds from the kill until
    the arm commander reports the arm stopped, and the planner's restart count once the launcher restarted it."""
    from hydrosoft.services import messages as msg
    from hydrosoft.services.status import collect

    arm = client.subscribe("arm_commander-bubble", ("arm_state/bubble",))
    await client.set_goal("pushing", dx_m=-0.03, tolerance_mm=1.0, timeout_s=60.0)
    await client.start()
    deadline = time.monotonic() + 30.0
    while True:  # wait until the arm servoes towards a target
        await arm.wait(1.0)
        state = arm.latest("arm_state/bubble", 1.0, msg.ArmState).value
        if state.servo_active:
            break
        assert time.monotonic() < deadline, "the arm never started servoing"
    pid = (await client.status()).status.pid
    os.kill(pid, signal.SIGKILL)
    killed = time.monotonic()
    while True:
        await arm.wait(1.0)
        state = arm.latest("arm_state/bubble", 1.0, msg.ArmState).value
        if not state.servo_active:
            stop_s = time.monotonic() - killed
            break
        assert time.monotonic() - killed < 5.0, "the arm kept servoing after the planner died"
    deadline = time.monotonic() + READY_TIMEOUT_S
    while time.monotonic() < deadline:
        report = (await collect(client.config, ["planner"], 2.0))["planner"]
        if report is not None and report.get("restarts", 0) >= 1 and report.get("pid") != pid:
            return stop_s, report["restarts"]
        await asyncio.sleep(1.0)
    raise AssertionError("the launcher did not restart the planner")


def children_left(session_pid: int) -> list[str]:
    """Processes still in the launcher's session (``ps``), excluding zombies."""
    out = subprocess.run(["ps", "-eo", "pid,sid,stat,args"], capture_output=True, text=True).stdout.splitlines()
    return [line for line in out[1:] if line.split()[1] == str(session_pid) and not line.split()[2].startswith("Z")]


def test_the_sim_stack_pushes_the_cube_to_the_goal_and_shuts_down_in_order(tmp_path):
    config_path = stack_config(tmp_path)
    stack = Stack(config_path, tmp_path / "launcher.log")
    client = StackClient(load_config(config_path))
    try:
        stack.wait_ready(client)

        async def push():
            await client.set_goal("pushing", dx_m=0.035, tolerance_mm=3.0, timeout_s=GOAL_TIMEOUT_S)
            await client.start()
            reply = await client.wait(GOAL_TIMEOUT_S + 10)
            true = await true_error_mm(client, reply.goal.target_pose, "pushing")
            return reply, true

        reply, true = asyncio.run(push())
        assert reply.outcome == "reached", (reply.outcome, reply.outcome_reason, reply.error_mm, stack.text()[-3000:])
        assert true is not None and true < 5.0, true
        assert reply.solves > 0

        stop_s, restarts = asyncio.run(kill_the_planner_mid_task(client))
        assert stop_s < KILL_STOP_BOUND_S, stop_s
        assert restarts >= 1
    finally:
        client.close()
        elapsed = stack.stop()
    assert elapsed < STOP_BOUND_S, elapsed
    assert not children_left(stack.process.pid), children_left(stack.process.pid)
    text = stack.text()
    order = [text.find(f"stopped {name}") for name in ("planner", "arm_commander-bubble", "sim_world")]
    assert -1 not in order and order == sorted(order), text[-3000:]
