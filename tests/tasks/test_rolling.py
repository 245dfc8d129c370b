"""The rolling scene rolls: the table holds the cylinder's bottom, so it turns as far as it travels."""

from __future__ import annotations

import math

import torch

from hydrosoft.geometry import se3
from hydrosoft.tasks import make_task
from hydrosoft.tasks.evaluation import Plant, PlantSettings


def test_a_steady_bubble_stroke_rolls_the_cylinder_without_creeping_on_the_table():
    """15 steps of 3 mm along +x: the cylinder moves at least 12 mm and turns within 10 % of ``x / radius``.

    At the membrane's shear stiffness the table let the cylinder creep: it turned 45 deg for 11 mm of travel
    (pure rolling: 25 deg) and stalled once the contact reached the membrane's curved edge."""
    task = make_task("rolling")
    plant = Plant(task.scene, PlantSettings.same_as_planner(), task.scene.object.spacing)
    start = plant.state.object_pose[0].clone()
    u = torch.zeros(plant.model.n_bodies, 6, dtype=torch.float64)
    u[plant.model.body_names.index("bubble"), 0] = 0.003
    for _ in range(15):
        assert plant.apply(u)
    pose = plant.state.object_pose[0]
    travel = float(pose[0] - start[0])
    turn = float(se3.so3_log(se3.quat_multiply(pose[3:], se3.quat_conjugate(start[3:])))[1])
    radius = float(task.scene.object.params["radius"])
    assert travel > 0.012
    assert math.isclose(turn, travel / radius, rel_tol=0.1), (turn, travel / radius)


def test_every_rolling_goal_is_reachable_within_its_episode():
    task = make_task("rolling")
    for seed in range(10):
        goal = task.sample_goal(seed)
        assert task.reachable(task.initial_pose(), goal, task.episode_steps(goal)), seed
