"""Planar pushing (paper V-D, Fig. 4 top row): drag a cube across the table through the bubble's shear.

Goal: the initial pose translated by 3-8 cm (uniform) in a uniformly random direction of the table plane,
yaw unchanged. Actions: the bubble translates in x and y only, at most ``STEP_M`` per step per axis. The drift
hinge holds the bubble within ``CostWeights.drift_limit`` of its resting place centred on the cube
(``Task.drift_from_scene``), whatever shear the last push left.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from hydrosoft.tasks.base import Task
from hydrosoft.tasks.scenes import task_scene

STEP_M = 0.002  # m per control step and axis: the cube follows at up to ~2.5 mm per step (pushing.toml)
DISTANCE_M = (0.03, 0.08)


def sample_goal(start: Tensor, generator: torch.Generator) -> Tensor:
    """Goal ``(7,)``: ``start (7,)`` moved by 3-8 cm in a random planar direction, orientation kept."""
    distance, direction = torch.rand(2, generator=generator, dtype=torch.float64)
    distance = DISTANCE_M[0] + (DISTANCE_M[1] - DISTANCE_M[0]) * distance
    direction = 2 * math.pi * direction
    goal = start.clone()
    goal[0] += distance * torch.cos(direction)
    goal[1] += distance * torch.sin(direction)
    return goal


def make_task(steps: int = 40) -> Task:
    """The planar pushing task with ``steps`` control steps per episode."""
    return Task(
        name="pushing",
        scene=task_scene("pushing"),
        step_limits={"bubble": (STEP_M, STEP_M, 0.0, 0.0, 0.0, 0.0)},
        goal_sampler=sample_goal,
        steps=steps,
        drift_from_scene=True,
    )
