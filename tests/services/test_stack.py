"""The whole stack in sim-hardware mode as separate processes: the launcher starts sim_world (plant, simulated UR
controller, FT 300 pty, rendered camera and depth images), the arm commander (the real ur_rtde client), the F/T
reader (the real serial driver), the bubble camera, the tag tracker and the planner; the cube starts 6 cm to the side
of the bubble (``sim.object_offset_m``), so the planner first re-approaches it (up, across, down onto it), then the
client's goal pushes it (and the arm's stop cause then reads "goal reached"); the planner is SIGKILLed during a
second goal (the arm stops, the launcher restarts it)
and the client resumes that goal on the new planner, which reaches it. The scene lies away from the base origin, turned 90 degrees
(``scene.task_frame``), as a lab's table would: every pose on the bus is in the base frame, and the goals push the
cube along the base's y, which is the task scene's x.

Every process is stopped by its pid (the launcher's process group, then a check that none is left).
"""

from __future__ import annotations

import asyncio
import math
import os
import signal
import time

import numpy as np
import pytest
from stack_process import READY_POLL_S, READY_TIMEOUT_S, Stack, assert_stopped_in_order, stack_config

from hydrosoft.services.client import StackClient, true_error_mm
from hydrosoft.services.bus.config import load_config

pytestmark = pytest.mark.slow

GOAL_TIMEOUT_S = 240.0
#: The planner's heartbeat timeout (deploy/sim.toml: 0.5 s) plus one servo period (8 ms), plus the time for the
#: commander's next published state to show it (one servo period) and scheduling slack on a busy machine.
KILL_STOP_BOUND_S = 0.5 + 0.008 + 0.008 + 0.2
#: T_base_task: the scene 0.4 m ahead of the base, 0.1 m to its right, the table 5 cm below the base's plane, its x
#: along the base's y.
TASK_FRAME = [0.4, -0.1, -0.05, math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5)]
#: Where sim_world's cube starts, from under the bubble (task frame): the bubble (0.045 m half-width in y) misses it.
OBJECT_OFFSET_M = (0.0, 0.06)


async def kill_the_planner_mid_task(client: StackClient) -> tuple[float, int]:
    """Start a second goal, SIGKILL the planner while the arm servoes, and return the seconds from the kill until
    the arm commander reports the arm stopped, and the planner's restart count once the launcher restarted it."""
    from hydrosoft.services.bus import messages as msg
    from hydrosoft.services.commands.status import collect

    arm = client.subscribe("arm_commander-bubble", ("arm_state/bubble",))
    await client.set_goal("pushing", dy_m=-0.03, tolerance_mm=3.0, timeout_s=GOAL_TIMEOUT_S)
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
        await asyncio.sleep(READY_POLL_S)
    raise AssertionError("the launcher did not restart the planner")


async def stop_cause_after(arm, expected: str, timeout_s: float = 3.0) -> tuple[str, bool]:
    """The arm commander's stop cause and ``servo_active`` once the cause reads ``expected``, or as they are after
    ``timeout_s`` (s)."""
    from hydrosoft.services.bus import messages as msg
    from hydrosoft.services.bus.sockets import Stale

    deadline, seen = time.monotonic() + timeout_s, ("no fresh arm state", True)
    while time.monotonic() < deadline:
        await arm.wait(1.0)
        try:
            state = arm.latest("arm_state/bubble", 1.0, msg.ArmState).value
        except Stale:
            continue
        seen = (state.stop_reason, state.servo_active)
        if state.stop_reason == expected:
            break
    return seen


def test_the_sim_stack_pushes_the_cube_to_the_goal_and_shuts_down_in_order(tmp_path):
    config_path = stack_config(tmp_path, compiled_plant=True, task_frame=TASK_FRAME, object_offset_m=OBJECT_OFFSET_M)
    stack = Stack(config_path, tmp_path / "launcher.log")
    client = StackClient(load_config(config_path))
    try:
        stack.wait_ready(client)

        async def push():
            await client.set_goal("pushing", dy_m=0.035, tolerance_mm=3.0, timeout_s=GOAL_TIMEOUT_S)
            await client.start()
            reply = await client.wait(GOAL_TIMEOUT_S + 10)
            true = await true_error_mm(client, reply.goal.target_pose, "pushing")
            arm = client.subscribe("arm_commander-bubble", ("arm_state/bubble",))  # subscribed now: fresh states
            return reply, true, await stop_cause_after(arm, "goal reached")

        reply, true, (stop_reason, servo_active) = asyncio.run(push())
        assert reply.outcome == "reached", (reply.outcome, reply.outcome_reason, reply.error_mm, stack.text()[-3000:])
        assert stop_reason == "goal reached" and not servo_active, stop_reason  # the goal's end, not the last fault
        # base frame: the task frame's y is the base's -x, so the cube started at x = 0.4 - 0.06
        assert abs(reply.goal.target_pose[0] - 0.34) < 0.005 and reply.goal.target_pose[1] > -0.1 + 0.03
        assert true is not None and true < 5.0, true
        assert reply.solves > 0
        assert reply.reapproaches == 1, (reply.reapproaches, stack.text()[-3000:])

        stop_s, restarts = asyncio.run(kill_the_planner_mid_task(client))
        assert stop_s < KILL_STOP_BOUND_S, stop_s
        assert restarts >= 1

        async def resumed():  # the restarted planner has no goal: wait sends it the one it lost, which it reaches
            target = client.pursuit.goal.target_pose
            reply = await client.wait(GOAL_TIMEOUT_S, resume=True)  # asked for: a goal is not resumed by default
            return reply, target, await true_error_mm(client, target, "pushing")

        reply, target, true = asyncio.run(resumed())
        assert client.resumes == 1
        assert reply.outcome == "reached", (reply.outcome, reply.outcome_reason, reply.error_mm, stack.text()[-3000:])
        # the same absolute target, not 3 cm from the new start (to rounding: it went through the task frame and back)
        np.testing.assert_allclose(reply.goal.target_pose, target, rtol=0, atol=1e-12)
        assert true is not None and true < 5.0, true
    finally:
        client.close()
        elapsed = stack.stop()
    assert_stopped_in_order(stack, elapsed, ("bubble",))
