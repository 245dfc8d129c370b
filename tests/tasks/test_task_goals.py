"""Task definitions: seeded goals within their stated ranges, action bounds, reachability and costs."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from hydrosoft.control.costs import orientation_error, position_error
from hydrosoft.geometry import se3
from hydrosoft.scene import compile_scene
from hydrosoft.tasks import TASKS, make_task
from hydrosoft.tasks.base import PointTracking, mean_point_distance, mean_squared_point_distance

F64 = torch.float64
RANGES = {  # task -> (what is measured, low, high), as stated in the task modules' docstrings
    "pushing": ("position_m", 0.03, 0.08),
    "rotation": ("angle_deg", 15.0, 45.0),
    "rolling": ("position_m", 0.02, 0.04),
    "in_hand": ("angle_deg", 10.0, 30.0),
}


@pytest.mark.parametrize("name", TASKS)
@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_goal_sampler_is_deterministic_per_seed_and_within_its_range(name, seed):
    task = make_task(name)
    goal = task.sample_goal(seed)
    assert torch.equal(goal, task.sample_goal(seed))
    start = task.initial_pose()
    kind, low, high = RANGES[name]
    value = float(position_error(start, goal)) if kind == "position_m" else math.degrees(orientation_error(start, goal))
    assert low - 1e-9 <= value <= high + 1e-9
    assert abs(float(goal[3:].norm()) - 1) < 1e-12


@pytest.mark.parametrize("name", TASKS)
def test_different_seeds_give_different_goals(name):
    task = make_task(name)
    goals = torch.stack([task.sample_goal(seed) for seed in range(10)])
    assert torch.unique(goals, dim=0).shape[0] == 10


def test_goal_shapes_match_the_task():
    start = make_task("pushing").initial_pose()
    push = make_task("pushing").sample_goal(3)
    assert torch.allclose(push[2:], start[2:])  # planar translation, same height and yaw
    rot = make_task("rotation").sample_goal(3)
    assert torch.allclose(rot[:3], start[:3]) and float(rot[4].abs() + rot[5].abs()) < 1e-12  # yaw only
    roll_task = make_task("rolling")
    roll = roll_task.sample_goal(3)
    d = float(roll[0] - roll_task.initial_pose()[0])
    turn = float(orientation_error(roll_task.initial_pose(), roll))
    assert abs(abs(d) / 0.025 - turn) < 1e-9 and abs(float(roll[1])) < 1e-12  # rolled without slipping along x
    hand_task = make_task("in_hand")
    hand = hand_task.sample_goal(3)
    axis = se3.so3_log(se3.quat_multiply(hand[3:], se3.quat_conjugate(hand_task.initial_pose()[3:])))
    assert torch.allclose(axis[1:], torch.zeros(2, dtype=F64), atol=1e-12)  # about the grasp axis x


@pytest.mark.parametrize("name", TASKS)
def test_bounds_follow_the_compiled_bodies(name):
    task = make_task(name)
    model, _, _ = compile_scene(task.scene)
    low, high = task.bounds(model.body_names)
    assert low.shape == high.shape == (model.n_bodies, 6)
    assert torch.equal(low, -high) and bool((high >= 0).all())
    for m, body in enumerate(model.body_names):
        assert bool((high[m] > 0).any()) == (body in task.step_limits)
    if name == "in_hand":
        assert model.body_names == ("bubble_left", "bubble_right")  # the table is pruned
    if task.scene.planar:
        assert bool((high[:, 2:5] == 0).all())  # planar tasks actuate x, y, yaw only


def test_reachability():
    task = make_task("pushing")
    start = task.initial_pose()
    assert task.reachable(start, task.sample_goal(0), task.steps)
    far = start.clone()
    far[0] += 1.0
    assert not task.reachable(start, far, task.steps)
    assert not task.reachable(start, task.sample_goal(0), 1)


def test_point_distance_is_the_add_and_zero_at_the_goal():
    points = torch.randn(50, 3, dtype=F64)
    pose = torch.tensor([0.1, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0], dtype=F64)
    goal = se3.identity(dtype=F64)
    assert abs(float(mean_point_distance(points, pose, goal)) - 0.1) < 1e-12
    assert abs(float(mean_squared_point_distance(points, pose.unsqueeze(0), goal)[0]) - 0.01) < 1e-12
    assert float(mean_point_distance(points, goal, goal)) == 0.0


def test_the_closed_form_tracking_term_is_the_mean_over_the_points_with_its_gradient():
    g = torch.Generator().manual_seed(0)
    points = 0.02 * torch.randn(132, 3, dtype=F64, generator=g)
    turns = torch.nn.functional.normalize(torch.randn(16, 4, dtype=F64, generator=g), dim=-1)
    pose = torch.cat([0.01 * torch.randn(16, 3, dtype=F64, generator=g), turns], -1).requires_grad_(True)
    goal = torch.cat([0.01 * torch.randn(3, dtype=F64, generator=g), se3.quat_normalize(torch.randn(4, dtype=F64,
                                                                                                  generator=g))])
    per_point = (se3.transform_points(pose, points) - se3.transform_points(goal, points)).square().sum(-1).mean(-1)
    closed = mean_squared_point_distance(points, pose, goal)
    torch.testing.assert_close(closed, per_point, rtol=1e-12, atol=1e-18)
    (want,) = torch.autograd.grad(per_point.sum(), pose)
    (got,) = torch.autograd.grad(mean_squared_point_distance(points, pose, goal).sum(), pose)

    def along_unit_quaternions(grad):  # poses move on unit quaternions: only the tangent part reaches the actions
        q = pose.detach()[:, 3:]
        return torch.cat([grad[:, :3], grad[:, 3:] - (grad[:, 3:] * q).sum(-1, keepdim=True) * q], -1)

    torch.testing.assert_close(along_unit_quaternions(got), along_unit_quaternions(want), rtol=1e-10, atol=1e-15)


def test_the_tracking_term_is_that_of_the_rotation_a_quaternion_of_any_scale_or_sign_represents():
    g = torch.Generator().manual_seed(1)
    points = 0.02 * torch.randn(60, 3, dtype=F64, generator=g) + torch.tensor([0.01, -0.02, 0.005], dtype=F64)
    goal = torch.cat([0.01 * torch.randn(3, dtype=F64, generator=g), se3.quat_normalize(torch.randn(4, dtype=F64,
                                                                                                  generator=g))])
    unit = torch.cat([0.01 * torch.randn(8, 3, dtype=F64, generator=g),
                      se3.quat_normalize(torch.randn(8, 4, dtype=F64, generator=g))], -1)
    scale = torch.tensor([0.3, 1.0, 2.5, -1.0, -0.7, 4.0, 1e-3, 1e3], dtype=F64).view(-1, 1)
    scaled = torch.cat([unit[:, :3], scale * unit[:, 3:]], -1)
    tracking = PointTracking.of(points, goal)
    per_point = (se3.transform_points(unit, points) - se3.transform_points(goal, points)).square().sum(-1).mean(-1)
    torch.testing.assert_close(tracking(scaled), per_point, rtol=1e-11, atol=1e-18)
    assert float(tracking(goal.unsqueeze(0))[0]) < 1e-15


def test_the_tracking_term_keeps_float32_precision_micrometres_from_the_goal():
    """Near the goal the term is tiny; a form that cancels two O(|p|^2) terms there loses it in float32 (and its
    clamp at zero then zeroes the gradient): measured 2e2 relative error at 2.6 um with such a form."""
    g = torch.Generator().manual_seed(2)
    points = 0.025 * (2 * torch.rand(216, 3, dtype=F64, generator=g) - 1) + torch.tensor([0.0, 0.0, 0.025], dtype=F64)
    goal = torch.tensor([0.05, 0.03, 0.025, math.cos(0.3), 0.0, 0.0, math.sin(0.3)], dtype=F64)
    for size in (1e-6, 1e-5, 1e-3):
        delta = torch.cat([size * torch.randn(32, 3, dtype=F64, generator=g),
                           size / 0.03 * torch.randn(32, 3, dtype=F64, generator=g)], -1)
        pose = se3.retract(goal.expand(32, 7), delta)
        values, grads = [], []
        for dtype in (F64, torch.float32):
            leaf = pose.to(dtype).requires_grad_(True)
            value = PointTracking.of(points.to(dtype), goal.to(dtype))(leaf)
            (grad,) = torch.autograd.grad(value.sum(), leaf)
            values.append(value.double())
            grads.append(grad[:, :3].double())
        assert ((values[1] - values[0]).abs() / values[0]).max() < 1e-2
        assert ((grads[1] - grads[0]).norm(dim=-1) / grads[0].norm(dim=-1)).max() < 1e-2


@pytest.mark.parametrize("name", TASKS)
def test_costs_are_finite_with_finite_gradients_and_lowest_at_the_goal(name):
    task = make_task(name)
    model, state, _ = compile_scene(task.scene)
    goal = task.sample_goal(0)
    stage, terminal = task.costs(model, goal)
    u = torch.zeros(2, model.n_bodies, 6, dtype=F64, requires_grad=True)
    batch = type(state)(*(t.expand(2, *t.shape[1:]).clone() for t in state[:3]))
    at_goal = batch._replace(object_pose=torch.stack([batch.object_pose[0], goal]))
    cost = stage([at_goal], u.unsqueeze(1)) + terminal(at_goal)
    (grad,) = torch.autograd.grad(cost.sum(), u)
    assert bool(torch.isfinite(cost).all()) and bool(torch.isfinite(grad).all())
    cost = cost.detach()
    assert float(cost[1]) < 1e-6 < float(cost[0])


def moved(state, object_m: float, bubble_m: float):
    """``state`` with the object and the actuated bubble moved along x by the given distances (m)."""
    object_pose, body_poses = state.object_pose.clone(), state.body_poses.clone()
    object_pose[:, 0] += object_m
    body_poses[:, 0, 0] += bubble_m
    return state._replace(object_pose=object_pose, body_poses=body_poses, phi=None)


def drift_cost(task, model, anchor_state, state) -> float:
    """The terminal cost of ``state`` at its own object pose as goal, with the drift anchored at ``anchor_state``:
    only the drift hinge is left."""
    anchor = (anchor_state.object_pose[0], anchor_state.body_poses[0])
    _, terminal = task.costs(model, state.object_pose[0], anchor=anchor)
    return float(terminal(state)[0])


def test_the_anchored_drift_bounds_slip_accumulated_over_replans():
    """A closed loop replans from states where the bubble already slipped; the anchored drift still counts that
    slip (25 mm over the cube: penalised), while dragging the cube along (no slip) costs nothing."""
    task = make_task("pushing")
    model, state, _ = compile_scene(task.scene)
    assert drift_cost(task, model, state, moved(state, 0.03, 0.03)) < 1e-6
    assert drift_cost(task, model, state, moved(state, 0.01, 0.035)) > 1.0
    slipped = moved(state, 0.01, 0.035)
    stage, _ = task.costs(model, slipped.object_pose[0])  # anchored at each plan's start: the slip is forgotten
    assert float(stage([slipped], torch.zeros(1, 1, model.n_bodies, 6, dtype=F64))[0]) < 1e-6


def test_rolling_without_slip_is_no_drift_and_dragging_is():
    """Rolling: the bubble on top moves twice as far as the cylinder's centre when nothing slips."""
    task = make_task("rolling")
    model, state, _ = compile_scene(task.scene)
    assert drift_cost(task, model, state, moved(state, 0.04, 0.08)) < 1e-6
    assert drift_cost(task, model, state, moved(state, 0.08, 0.08)) > 1.0


@pytest.mark.parametrize("name", TASKS)
def test_pruning_keeps_every_point_that_touches_a_fixed_body_at_any_goal(name):
    """The compiler prunes points out of ``reach``; a task's motion must not bring a pruned point into contact.

    At each of 20 seeded goal poses, every object point that the unactuated bodies (the table) touch in the
    unpruned model is one the pruned model kept (rolling turns the whole lateral surface down to the table)."""
    task = make_task(name)
    full, state, _ = compile_scene(task.scene, prune=False)
    pruned, _, _ = compile_scene(task.scene)
    kept = {tuple(p) for p in pruned.points.round(decimals=9).tolist()}
    start = state.object_pose[0]
    for seed in range(20):
        goal = task.sample_goal(seed)
        world = se3.transform_points(goal, full.points)
        for m, sdf in enumerate(full.bodies):
            if full.actuated[m]:
                continue
            body_pose = state.body_poses[0, m]
            touching = sdf(se3.transform_points(se3.inverse(body_pose), world)) <= 0
            missing = [p for p in full.points[touching].round(decimals=9).tolist() if tuple(p) not in kept]
            assert not missing, f"{name} goal {seed}: {len(missing)} pruned points touch {full.body_names[m]}"
    assert torch.equal(start, state.object_pose[0])


def test_solver_workers_plan_what_one_thread_plans_with_the_task_costs():
    """The costs anchor the drift at each plan's first state, per thread: three solver workers (shares of 6, 5 and 5
    samples, each anchoring its own) plan what one thread plans, over three receding-horizon solves of pushing."""
    from functools import partial

    from hydrosoft.control import CemGd, CemGdConfig
    from hydrosoft.dynamics import step

    task = make_task("pushing")
    model, state, _ = compile_scene(task.scene)
    stage, terminal = task.costs(model, task.sample_goal(0))
    low, high = task.bounds(model.body_names)
    solvers = [CemGd(partial(step, model), stage, terminal, low, high,
                     CemGdConfig(samples=16, elites=4, horizon=4, grad_steps=1, workers=workers))
               for workers in (1, 3)]
    for _ in range(3):
        alone, shared = (solver.solve(state) for solver in solvers)
        torch.testing.assert_close(shared.plan, alone.plan, rtol=0, atol=1e-12)
        assert shared.cost == pytest.approx(alone.cost, rel=1e-9)
        state = step(model, state, alone.action.unsqueeze(0))


@pytest.mark.parametrize("name", TASKS)
def test_a_rollouts_stage_cost_is_the_sum_of_its_steps(name):
    """``stage_cost`` takes a whole rollout's states at once: it equals its steps' costs one by one (anchored), and
    unanchored it anchors at the rollout's first state with its own offsets (anchored pushing takes the scene's:
    ``Task.drift_from_scene``), for the terminal cost that follows too."""
    task = dataclasses.replace(make_task(name), drift_from_scene=False)
    model, state, _ = compile_scene(task.scene)
    g = torch.Generator().manual_seed(3)
    states = [state._replace(object_pose=state.object_pose + 1e-3 * torch.randn(1, 7, generator=g, dtype=F64),
                             body_poses=state.body_poses + 2e-2 * torch.randn(*state.body_poses.shape, generator=g,
                                                                              dtype=F64), phi=None)
              for _ in range(4)]
    high = task.bounds(model.body_names, F64)[1]
    u = high * (2 * torch.rand(1, 4, *high.shape, generator=g, dtype=F64) - 1)
    goal = task.sample_goal(0)
    stage, terminal = task.costs(model, goal, anchor=(states[0].object_pose[0], states[0].body_poses[0]))
    whole = stage(states, u)
    steps = sum(stage([s], u[:, k : k + 1]) for k, s in enumerate(states))
    assert whole.shape == (1,) and float(whole) > 0 and torch.allclose(whole, steps, rtol=1e-12, atol=0)
    free_stage, free_terminal = task.costs(model, goal)
    assert torch.allclose(free_stage(states, u), whole, rtol=1e-12, atol=0)
    assert torch.allclose(free_terminal(states[-1]), terminal(states[-1]), rtol=1e-12, atol=0)
    elsewhere, _ = task.costs(model, goal, anchor=(states[1].object_pose[0], states[1].body_poses[0]))
    assert not torch.allclose(elsewhere(states, u), whole, rtol=1e-6, atol=0)  # the anchor counts


def rollout_inputs(model, state, task, batch: int, horizon: int, seed: int):
    """``horizon`` random states near ``state`` (batch ``batch``) and actions within the task's bounds."""
    g = torch.Generator().manual_seed(seed)

    def near(t, size):
        return t.expand(batch, *t.shape[1:]) + size * torch.randn(batch, *t.shape[1:], generator=g, dtype=F64)

    states = [state._replace(object_pose=near(state.object_pose, 1e-3), body_poses=near(state.body_poses, 2e-2),
                             forces=state.forces.expand(batch, *state.forces.shape[1:]), phi=None)
              for _ in range(horizon)]
    high = task.bounds(model.body_names, F64)[1]
    return states, high * (2 * torch.rand(batch, horizon, *high.shape, generator=g, dtype=F64) - 1)


def costs_and_gradients(task, model, goal, anchor, terms, states, u):
    """A rollout's total cost ``(B,)`` and its gradient with respect to the actions and the states' poses."""
    stage, terminal = task.costs(model, goal, anchor=anchor, terms=terms)
    u = u.clone().requires_grad_(True)
    poses = [s.object_pose.clone().requires_grad_(True) for s in states]
    states = [s._replace(object_pose=p) for s, p in zip(states, poses)]
    cost = stage(states[:-1], u[:, :-1]) + terminal(states[-1])
    return cost.detach(), torch.autograd.grad(cost.sum(), [u, *poses])


@pytest.mark.parametrize("name", TASKS)
def test_compiled_cost_terms_give_the_eager_costs_and_gradients_and_new_goals_reuse_their_graphs(name, fresh_dynamo):
    """The planner compiles the costs once and keeps them for every goal: with the goal and the anchor as inputs of
    the graphs, a new goal and a new anchor compile nothing, and the costs and their gradients are the eager ones
    (AOT autograd's graphs run eagerly: ``aot_eager``). A second rollout length compiles once more; a third is
    served by that (dynamic) graph, as open-loop plans of each episode's length are."""
    from hydrosoft.tasks.base import EAGER_COST_TERMS, compiled_cost_terms

    task = make_task(name)
    model, state, _ = compile_scene(task.scene)
    compiled = compiled_cost_terms(backend="aot_eager")
    counters = torch._dynamo.utils.counters
    graphs = []
    for k, horizon in enumerate((4, 4, 4, 6, 7)):
        states, u = rollout_inputs(model, state, task, 3, horizon + 1, seed=k)
        goal = task.sample_goal(k)
        anchor = None if k == 1 else (states[0].object_pose[k % 3], states[0].body_poses[k % 3])
        before = counters["stats"]["unique_graphs"]
        got = costs_and_gradients(task, model, goal, anchor, compiled, states, u)
        graphs.append(counters["stats"]["unique_graphs"] - before)
        expected = costs_and_gradients(task, model, goal, anchor, EAGER_COST_TERMS, states, u)
        torch.testing.assert_close(got[0], expected[0], rtol=1e-12, atol=0)
        for grad, eager in zip(got[1], expected[1]):
            torch.testing.assert_close(grad, eager, rtol=1e-9, atol=1e-12)
    assert compiled.stage.compiled and compiled.terminal.compiled
    # the first rollout compiles stage and terminal; an unanchored one anchors at its first state (other shapes)
    assert graphs[0] == 2 and graphs[1] >= 1 and graphs[2] == 0
    assert graphs[3] == 1 and graphs[4] == 0  # the stage cost's horizon: once more, then dynamic
