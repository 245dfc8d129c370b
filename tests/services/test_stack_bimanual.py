"""The two-arm sim stack as separate processes (``deploy/sim-bimanual.toml``): the launcher starts sim_world (the
compiled plant, two simulated UR controllers and two FT 300 ptys, the rendered camera and two depth cameras), one
arm commander, F/T reader and bubble camera per arm, the tag tracker and the planner; the client's goal rotates the
grasped cube 20 degrees about the grasp axis, and both arms must take part.

Every process is stopped by its pid (the launcher's process group, then a check that none is left).
"""

from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest
import torch
from stack_process import Stack, assert_stopped_in_order, bimanual_stack_config

from hydrosoft.geometry.se3 import angle_between
from hydrosoft.services.client import StackClient, true_error_mm
from hydrosoft.services.bus.config import load_config

pytestmark = pytest.mark.slow

GOAL_TIMEOUT_S = 180.0
ARMS = ("bubble_left", "bubble_right")


async def tcp_poses(client: StackClient) -> dict[str, np.ndarray]:
    """Each arm's latest TCP pose ``(7,)`` (base frame) from its commander's arm state."""
    from hydrosoft.services.bus import messages as msg

    poses = {}
    for arm in ARMS:
        sub = client.subscribe(f"arm_commander-{arm}", (f"arm_state/{arm}",))
        await sub.wait(2.0)
        poses[arm] = np.array(sub.latest(f"arm_state/{arm}", 2.0, msg.ArmState).value.tcp_pose)
    return poses


def test_the_bimanual_sim_stack_rotates_the_grasped_cube_with_both_arms_and_shuts_down_in_order(tmp_path):
    config_path = bimanual_stack_config(tmp_path)
    stack = Stack(config_path, tmp_path / "launcher.log")
    client = StackClient(load_config(config_path))
    try:
        stack.wait_ready(client)

        async def rotate():
            before = await tcp_poses(client)
            await client.set_goal("in_hand", droll_rad=math.radians(20.0), tolerance_mm=2.0, timeout_s=GOAL_TIMEOUT_S)
            await client.start()
            reply = await client.wait(GOAL_TIMEOUT_S + 10)
            true = await true_error_mm(client, reply.goal.target_pose, "in_hand")
            return before, reply, true, await tcp_poses(client)

        before, reply, true, after = asyncio.run(rotate())
        assert reply.outcome == "reached", (reply.outcome, reply.outcome_reason, reply.error_mm, stack.text()[-3000:])
        assert true is not None and true < 2.0, true
        assert reply.solves > 0
        for arm in ARMS:  # each bubble turned with the cube, the grasp held between them
            turned = math.degrees(float(angle_between(torch.as_tensor(before[arm][3:]), torch.as_tensor(after[arm][3:]))))
            assert turned > 10.0, (arm, turned, before[arm], after[arm])
    finally:
        client.close()
        elapsed = stack.stop()
    assert_stopped_in_order(stack, elapsed, ARMS)
