"""Episodes on the plant: bounds on every applied action, clear statuses and finite errors at the edges."""

from __future__ import annotations

import dataclasses
import math

import msgspec
import pytest
import torch
from conftest import quick_planner

from hydrosoft.tasks import make_task
from hydrosoft.tasks.base import Task
from hydrosoft.tasks.evaluation import EpisodeResult, PlantSettings, prepare, run_episode

F64 = torch.float64


def finite(result: EpisodeResult) -> bool:
    values = [result.error_mm, result.position_mm, result.angle_deg, result.solve_s, *result.errors_mm]
    return all(math.isfinite(v) for v in values) and bool(torch.isfinite(result.final_pose).all())


def assert_within_bounds(task: Task, setup, result: EpisodeResult) -> None:
    low, high = task.bounds(setup.planner_model.body_names)
    assert result.actions.shape == (len(result.errors_mm) - 1, *low.shape)
    assert bool(((result.actions >= low - 1e-15) & (result.actions <= high + 1e-15)).all())


@pytest.mark.parametrize("name", ["pushing", "rolling", "in_hand"])
@pytest.mark.parametrize("loop", ["closed", "open"])
def test_every_applied_action_is_within_the_bounds(name, loop):
    task = make_task(name)
    setup = prepare(task, quick_planner(samples=8, horizon=3, open_loop_iterations=1))
    result = run_episode(setup, task.sample_goal(0), loop, steps=3)
    assert_within_bounds(task, setup, result)
    assert bool((result.actions.abs() > 0).any())
    assert result.solves == (3 if loop == "closed" else 1)
    assert finite(result) and result.status == "unreachable"  # 3 steps cannot get there


def test_a_goal_one_metre_away_is_unreachable_and_stays_finite():
    task = make_task("pushing")
    setup = prepare(task, quick_planner(samples=8, horizon=3))
    goal = task.initial_pose()
    goal[0] += 1.0
    result = run_episode(setup, goal, "closed", steps=3)
    assert result.status == "unreachable" and not result.success
    assert finite(result) and abs(result.error_mm - 1000.0) < 20.0
    assert_within_bounds(task, setup, result)


@pytest.mark.parametrize("name", ["pushing", "rolling", "in_hand"])
def test_object_starting_out_of_contact_gives_a_clear_status_and_no_nan(name):
    """Each bubble lifted 3 cm off (in-hand: backed off 3 cm along x): no contact force, no gradient."""
    task = make_task(name)
    bodies = []
    for body in task.scene.bodies:
        pose = list(body.pose)
        if body.name in task.step_limits:
            axis = 0 if name == "in_hand" else 2
            pose[axis] += 0.03 if pose[axis] >= 0 else -0.03
        bodies.append(msgspec.structs.replace(body, pose=pose))
    task = dataclasses.replace(task, scene=msgspec.structs.replace(task.scene, bodies=bodies))
    setup = prepare(task, quick_planner(samples=8, horizon=3), PlantSettings())
    bubbles = [setup.plant.model.body_names.index(b) for b in task.step_limits]
    assert float(setup.plant.state.forces[0, bubbles].abs().sum()) == 0.0
    result = run_episode(setup, task.sample_goal(1), "closed", steps=3)
    assert finite(result)
    assert result.status in ("not_reached", "unreachable")  # the latter when 3 steps cannot get there
    assert result.error_mm > 0.8 * result.initial_error_mm


class NaNCostTask(Task):
    """A task whose cost is NaN for every sample: the planner never has a finite plan."""

    def costs(self, model, goal, anchor=None, **terms):
        stage, terminal = super().costs(model, goal, anchor, **terms)
        return (lambda states, u: stage(states, u) * math.nan), terminal


def test_a_plan_without_a_finite_sample_applies_the_rest_action_and_says_so():
    base = make_task("pushing")
    task = NaNCostTask(**{f.name: getattr(base, f.name) for f in dataclasses.fields(Task)})
    setup = prepare(task, quick_planner(samples=8, horizon=3))
    result = run_episode(setup, task.sample_goal(0), "closed", steps=2)
    assert result.status == "no_finite_plan"
    assert finite(result) and bool((result.actions == 0).all())
    assert abs(result.error_mm - result.initial_error_mm) < 0.5


def test_episodes_are_reproducible():
    task = make_task("rotation")
    setup = prepare(task, quick_planner(samples=8, horizon=3))
    first = run_episode(setup, task.sample_goal(2), "closed", steps=3)
    second = run_episode(setup, task.sample_goal(2), "closed", steps=3)
    assert first.errors_mm == second.errors_mm and torch.equal(first.actions, second.actions)
