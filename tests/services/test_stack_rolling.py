"""Rolling on the sim stack as separate processes: ``deploy/sim.toml`` with ``scene.task = "rolling"`` and its one tag
camera. The tracker must see the cylinder's cap tag (before, every image was rejected at a grazing angle, and the
stack said ``ready`` while no goal could start); the client's goal rolls the cylinder 2 cm along base x, turning it
2 cm / radius about base y, as rolling without slipping does.

Every process is stopped by its pid (the launcher's process group, then a check that none is left).
"""

from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest
import torch
from stack_process import Stack, assert_stopped_in_order, stack_config, tracked_object_pose

from hydrosoft.geometry import se3
from hydrosoft.services.client import StackClient, true_error_mm
from hydrosoft.services.bus.config import load_config
from hydrosoft.services.commands.status import collect
from hydrosoft.tasks import make_task

pytestmark = pytest.mark.slow

GOAL_TIMEOUT_S = 180.0
ROLL_M = 0.02  # the rolling task's shortest goal (hydrosoft.tasks.rolling.DISTANCE_M)
TOLERANCE_MM = 3.0


def rolled(start: np.ndarray, distance_m: float, radius_m: float) -> np.ndarray:
    """``start (7,)`` (base frame) rolled without slipping by ``distance_m`` along base x: moved by it and turned by
    ``distance_m / radius_m`` about base y through the object's centre, as ``rolling.sample_goal`` does."""
    delta = torch.zeros(6, dtype=torch.float64)
    delta[0], delta[4] = distance_m, distance_m / radius_m
    return se3.retract(torch.as_tensor(start, dtype=torch.float64), delta).numpy()


def test_the_sim_stack_tracks_and_rolls_the_cylinder_and_shuts_down_in_order(tmp_path):
    config_path = stack_config(tmp_path, compiled_plant=True, task="rolling")
    stack = Stack(config_path, tmp_path / "launcher.log")
    client = StackClient(load_config(config_path))
    radius_m = float(make_task("rolling").scene.object.params["radius"])
    try:
        stack.wait_ready(client)  # the planner receives object poses: the tracker sees the cylinder

        async def roll():
            tracker = (await collect(client.config, ["tag_tracker"], 2.0))["tag_tracker"]
            start = await tracked_object_pose(client)
            target = rolled(start, ROLL_M, radius_m)
            await client.set_goal("rolling", target_pose=target, tolerance_mm=TOLERANCE_MM, timeout_s=GOAL_TIMEOUT_S)
            await client.start()
            reply = await client.wait(GOAL_TIMEOUT_S + 10)
            return tracker, start, reply, await true_error_mm(client, target, "rolling")

        tracker, start, reply, true = asyncio.run(roll())
        assert tracker is not None and tracker["state"] == "ready" and "note" not in tracker, tracker
        assert reply.outcome == "reached", (reply.outcome, reply.outcome_reason, reply.error_mm, stack.text()[-3000:])
        assert true is not None and true < 5.0, true
        assert reply.solves > 0
        print(f"rolling {ROLL_M * 1e3:.0f} mm: reached in {reply.elapsed_s:.1f} s, error {reply.error_mm:.2f} mm "
              f"(tracked), {true:.2f} mm (true), {reply.solves} solves of {reply.mean_solve_ms:.0f} ms mean")
        turned_deg = math.degrees(float(se3.angle_between(torch.as_tensor(start[3:]),
                                                          torch.as_tensor(reply.goal.target_pose[3:]))))
        assert abs(turned_deg - math.degrees(ROLL_M / radius_m)) < 0.5, turned_deg  # the goal asked for a roll
    finally:
        client.close()
        elapsed = stack.stop()
    assert_stopped_in_order(stack, elapsed, ("bubble",))
