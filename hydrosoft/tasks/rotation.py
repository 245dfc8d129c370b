"""Planar rotation (paper V-D, Fig. 4 second row): twist a cube about the vertical through the bubble's shear.

Goal: the initial pose rotated about the world z axis (through the object's centre) by 15-45 degrees
(uniform magnitude, random sign), position unchanged. Actions: the bubble yaws by at most ``STEP_RAD`` per
step and translates in x and y by at most ``STEP_M`` per step (to hold the cube in place).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from hydrosoft.tasks.base import Task, rotated_goal
from hydrosoft.tasks.scenes import task_scene

STEP_RAD = math.radians(4.0)  # rad per control step
STEP_M = 0.001  # m per control step and axis
ANGLE_DEG = (15.0, 45.0)


def sample_goal(start: Tensor, generator: torch.Generator) -> Tensor:
    """Goal ``(7,)``: ``start (7,)`` yawed by +-(15-45) degrees about its own centre."""
    return rotated_goal(start, generator, axis=2, degrees=ANGLE_DEG)


def make_task(steps: int = 30) -> Task:
    """The planar rotation task with ``steps`` control steps per episode."""
    return Task(
        name="rotation",
        scene=task_scene("rotation"),
        step_limits={"bubble": (STEP_M, STEP_M, 0.0, 0.0, 0.0, STEP_RAD)},
        goal_sampler=sample_goal,
        steps=steps,
    )
