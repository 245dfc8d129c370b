"""Rolling (paper V-D, Fig. 4 third row): roll a cylinder lying on the table by translating the bubble on top.

Goal: the cylinder rolled without slipping along the world x axis by 2-4 cm (uniform magnitude, random
sign): its centre moves by ``d`` along x and it turns by ``d / radius`` about the world y axis. Rolling by ``d``
moves the contact by ``d`` along the membrane, whose half-length is 6 cm and which curves away from the
cylinder beyond about 4 cm, so larger rolls would need a regrasp. Actions: the
bubble translates along x by at most ``STEP_M`` per step and along z by at most ``STEP_Z_M`` (to keep the
membrane pressed as the contact moves over its curved surface). The bubble leads the rolling cylinder (its
top moves twice as fast as its centre), so the cost lets it drift up to 4.5 cm relative to the object, and an
episode lasts long enough for the bubble to travel twice the goal distance (``travel_ratio`` 1/2,
``Task.episode_steps``: 30 steps, up to 54 for a 4 cm roll).
"""

from __future__ import annotations

import torch
from torch import Tensor

from hydrosoft.geometry import se3
from hydrosoft.tasks.base import CostWeights, Task
from hydrosoft.tasks.scenes import task_scene

STEP_M = 0.003  # m per control step along x
STEP_Z_M = 0.0005  # m per control step along z
DISTANCE_M = (0.02, 0.04)


def sample_goal(start: Tensor, generator: torch.Generator, radius: float = 0.025) -> Tensor:
    """Goal ``(7,)``: ``start (7,)`` rolled by +-(2-4) cm along x on a cylinder of ``radius`` m."""
    magnitude, sign = torch.rand(2, generator=generator, dtype=torch.float64)
    distance = DISTANCE_M[0] + (DISTANCE_M[1] - DISTANCE_M[0]) * magnitude
    distance = torch.where(sign < 0.5, -distance, distance)
    delta = torch.zeros(6, dtype=torch.float64)
    delta[0] = distance
    delta[4] = distance / radius
    return se3.retract(start, delta)


def make_task(steps: int = 30) -> Task:
    """The rolling task with ``steps`` control steps per episode."""
    scene = task_scene("rolling")
    radius = float(scene.object.params["radius"])
    return Task(
        name="rolling",
        scene=scene,
        step_limits={"bubble": (STEP_M, 0.0, STEP_Z_M, 0.0, 0.0, 0.0)},
        goal_sampler=lambda start, generator: sample_goal(start, generator, radius),
        steps=steps,
        weights=CostWeights(drift_limit=0.045),
        travel_ratio=0.5,
    )
