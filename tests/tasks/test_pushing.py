"""Pushing goals back to back: a push back after a push reaches its goal (docs/benchmarks.md, "A goal near its
tolerance")."""

from __future__ import annotations

import pytest
import torch

from hydrosoft.dynamics import State
from hydrosoft.scene import compile_scene
from hydrosoft.tasks import make_task
from hydrosoft.tasks.evaluation import PlantSettings, prepare, run_episode

from conftest import quick_planner

TOLERANCE_MM = 3.0  # the soak's goal tolerance (services/benchmarks/soak.py)
SHEAR_M = 0.008  # how far a 3 cm push leaves the bubble ahead of the cube (7.9-9.4 mm in the episodes below)


def holding_cost(task, model, state: State, goal: torch.Tensor, anchor, object_x: float, bubble_x: float) -> float:
    """The cost of a plan that holds the cube at ``object_x`` and the bubble at ``bubble_x`` (m) for its 10 steps."""
    stage, terminal = task.costs(model, goal, anchor=anchor)
    pose = state.object_pose.clone()
    pose[:, 0] = object_x
    bodies = state.body_poses.clone()
    bodies[:, 0, 0] = bubble_x
    held = State(pose, bodies, state.forces)
    u = torch.zeros(1, 10, model.n_bodies, 6, dtype=model.dtype)
    return float(stage([held] * 10, u) + terminal(held))


def test_holding_a_push_back_at_its_goal_costs_less_than_stopping_short():
    # After a push along +x the bubble rests SHEAR_M ahead of the cube; the goal is 3 cm back. At the goal the
    # push back leaves it SHEAR_M behind: 16 mm from where it started. The drift hinge (15 mm) measured from the
    # goal's start made stopping 3 mm short, with 3 mm less shear, the cheaper plan: the stall.
    task = make_task("pushing")
    model, state, _ = compile_scene(task.scene)
    bubble = model.body_names.index("bubble")
    assert bubble == 0
    start = state.object_pose[0].clone()
    anchor = (start, state.body_poses[0].clone())
    anchor[1][bubble, 0] += SHEAR_M
    goal = start.clone()
    goal[0] -= 0.03
    at_goal = holding_cost(task, model, state, goal, anchor, -0.03, -0.03 - SHEAR_M)
    short = holding_cost(task, model, state, goal, anchor, -0.027, -0.027 - SHEAR_M + 0.003)
    assert at_goal < short
    # the hinge still keeps the bubble on the cube: 20 mm off its centre costs more than stopping short
    assert holding_cost(task, model, state, goal, anchor, -0.03, -0.05) > short


@pytest.mark.slow
def test_a_push_back_after_a_push_reaches_its_goal():
    # The soak's goals at the model level: +3 cm, then -3 cm, the plant kept between them (the paper preset's
    # float32 and linearly implicit update, the small planner, the finer plant). Before the drift hinge was measured
    # from the bubble's resting place the push back stalled 3-4 mm short, at the hinge's limit.
    task = make_task("pushing")
    planner = quick_planner(dtype=torch.float32, sdf_solver_steps=2, object_update="linearly_implicit")
    setup = prepare(task, planner, PlantSettings())
    start = task.initial_pose()
    there = start.clone()
    there[0] += 0.03
    first = run_episode(setup, there, steps=30)
    assert first.error_mm <= TOLERANCE_MM
    ahead = float(setup.plant.state.body_poses[0, setup.body_index[0], 0] - setup.plant.state.object_pose[0, 0])
    assert ahead > 0.005  # the premise: the push left the bubble ahead of the cube
    back = run_episode(setup, start, steps=40, keep_plant=True)
    assert back.initial_error_mm == pytest.approx(30.0, abs=TOLERANCE_MM)
    assert max(back.errors_mm[-6:]) <= TOLERANCE_MM, back.errors_mm


def test_an_episode_that_keeps_the_plant_starts_where_the_last_one_ended():
    task = make_task("pushing")
    setup = prepare(task, quick_planner(), PlantSettings.same_as_planner())
    goal = task.initial_pose()
    goal[0] += 0.01
    first = run_episode(setup, goal, steps=2)
    kept = run_episode(setup, goal, steps=1, keep_plant=True)
    fresh = run_episode(setup, goal, steps=1)
    assert kept.initial_error_mm == pytest.approx(first.errors_mm[-1])
    assert fresh.initial_error_mm == pytest.approx(first.errors_mm[0])


def test_the_drift_keeps_the_height_the_goal_started_at():
    # A TCP that presses from 5 mm higher than the scene's pose is no slip: only x and y come from the scene.
    task = make_task("pushing")
    model, state, _ = compile_scene(task.scene)
    start = state.object_pose[0].clone()
    goal = start.clone()
    goal[0] -= 0.03
    raised = state._replace(body_poses=state.body_poses.clone())
    raised.body_poses[:, 0, 2] += 0.005
    as_scene = holding_cost(task, model, state, goal, (start, state.body_poses[0]), 0.0, -0.014)
    assert holding_cost(task, model, raised, goal, (start, raised.body_poses[0]), 0.0, -0.014) == pytest.approx(
        as_scene)
