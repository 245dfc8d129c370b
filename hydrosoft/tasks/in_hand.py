"""Bimanual in-hand rotation (paper V-D, Fig. 4 bottom row): two bubbles squeeze a cube between them and twist
it about the grasp axis (world x, through both bubbles' centres).

Goal: the initial pose rotated about the world x axis through the object's centre by 10-30 degrees (uniform
magnitude, random sign), position unchanged. Actions: each bubble rotates about world x by at most
``STEP_RAD`` per step (about its own centre, which lies on the grasp axis) and translates along z by at most
``STEP_Z_M`` per step (to hold the cube against gravity).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from hydrosoft.tasks.base import Task, rotated_goal
from hydrosoft.tasks.scenes import task_scene

STEP_RAD = math.radians(3.0)  # rad per control step
STEP_Z_M = 0.0005  # m per control step
ANGLE_DEG = (10.0, 30.0)


def sample_goal(start: Tensor, generator: torch.Generator) -> Tensor:
    """Goal ``(7,)``: ``start (7,)`` rotated by +-(10-30) degrees about the world x axis through its centre."""
    return rotated_goal(start, generator, axis=0, degrees=ANGLE_DEG)


def make_task(steps: int = 20) -> Task:
    """The in-hand rotation task with ``steps`` control steps per episode."""
    limits = (0.0, 0.0, STEP_Z_M, STEP_RAD, 0.0, 0.0)
    return Task(
        name="in_hand",
        scene=task_scene("in_hand"),
        step_limits={"bubble_left": limits, "bubble_right": limits},
        goal_sampler=sample_goal,
        steps=steps,
    )
