"""CEM + gradient-descent MPC (Algorithm 1) on a single integrator x_{k+1} = x_k + u_k with known optimum."""
from __future__ import annotations

import math
import threading
from typing import NamedTuple

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from hydrosoft.control import CemGd, CemGdConfig, effort_cost

F64 = torch.float64
GOAL = torch.tensor([0.5, -0.3, 0.2], dtype=F64)
BOUND = 0.1  # |u| per axis and step (m)


class State(NamedTuple):
    pos: torch.Tensor  # (B, 3) m
    steps: torch.Tensor  # (B,) int64, steps taken: a non-float leaf rides along


def integrator(state: State, u: torch.Tensor) -> State:
    """Single integrator on a (B, 1, 3) action."""
    return State(state.pos + u[:, 0], state.steps + 1)


def to_goal(state: State) -> torch.Tensor:
    return (state.pos - GOAL.to(state.pos)).square().sum(-1)


def tracking_cost(states: list[State], u: torch.Tensor) -> torch.Tensor:
    return sum(to_goal(state) for state in states) + 0.01 * effort_cost(u)


def x0(pos=(0.0, 0.0, 0.0), dtype=F64) -> State:
    return State(torch.tensor([pos], dtype=dtype), torch.zeros(1, dtype=torch.int64))


def make_solver(config: CemGdConfig, dynamics=integrator, stage=tracking_cost, dtype=F64) -> CemGd:
    low = torch.full((1, 3), -BOUND, dtype=F64)
    return CemGd(dynamics, stage, to_goal, low, -low, config, dtype=dtype)


class Recorder:
    """Dynamics wrapper recording every action batch it is called with (detached)."""

    def __init__(self, dynamics):
        self.dynamics = dynamics
        self.calls: list[torch.Tensor] = []

    def __call__(self, state, u):
        self.calls.append(u.detach().clone())
        return self.dynamics(state, u)

    def sequences(self, first_call: int, horizon: int) -> torch.Tensor:
        """(B, K, *A) sequences of the K consecutive calls starting at ``first_call``."""
        return torch.stack(self.calls[first_call : first_call + horizon], dim=1)


def close_loop(solver: CemGd, steps: int) -> tuple[list[float], float]:
    """Receding horizon: apply each first action; distances to the goal and the summed stage cost."""
    state, errors, total = x0(), [], 0.0
    for _ in range(steps):
        result = solver.solve(state)
        assert result.status == "ok"
        total += to_goal(state).item()
        state = integrator(state, result.action.unsqueeze(0))
        errors.append((state.pos[0] - GOAL).norm().item())
    return errors, total


def test_config_and_bounds_are_validated():
    with pytest.raises(ValueError):
        CemGdConfig(samples=4, elites=5)
    with pytest.raises(ValueError):
        CemGdConfig(horizon=0)
    low = torch.zeros(1, 3, dtype=F64)
    with pytest.raises(ValueError):
        CemGd(integrator, tracking_cost, to_goal, low, low - 1.0)
    with pytest.raises(ValueError):
        CemGd(integrator, tracking_cost, to_goal, low, torch.full((1, 3), math.inf))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_gradient_steps_lower_the_cost_of_the_same_samples(seed):
    pure = make_solver(CemGdConfig(grad_steps=0, seed=seed)).solve(x0())
    descended = make_solver(CemGdConfig(grad_steps=2, seed=seed)).solve(x0())
    assert descended.cost < 0.9 * pure.cost


def test_reaches_the_known_optimum():
    # min |x_K - g|^2 + lam sum_k |u_k|^2 from x_0 = 0: u_k = g / (K + lam), J* = lam |g|^2 / (K + lam).
    goal, lam, horizon = torch.tensor([0.2, -0.1, 0.15], dtype=F64), 0.1, 5
    low = torch.full((3,), -BOUND, dtype=F64)
    solver = CemGd(
        lambda x, u: x + u,
        lambda states, u: lam * effort_cost(u),
        lambda x: (x - goal).square().sum(-1),
        low, -low,
        CemGdConfig(horizon=horizon, grad_steps=10, cem_iterations=5),
    )
    result = solver.solve(torch.zeros(1, 3, dtype=F64))
    optimum = lam * goal.square().sum().item() / (horizon + lam)
    assert optimum <= result.cost < 1.1 * optimum
    assert torch.allclose(result.plan, (goal / (horizon + lam)).expand(horizon, 3), atol=0.01)


@pytest.mark.parametrize("grad_steps", [0, 2])
def test_receding_horizon_drives_the_state_to_the_goal(grad_steps):
    errors, _ = close_loop(make_solver(CemGdConfig(grad_steps=grad_steps)), steps=20)
    assert max(errors[-5:]) < 0.04


def test_pure_cem_converges_more_slowly():
    _, with_gradients = close_loop(make_solver(CemGdConfig(grad_steps=2)), steps=12)
    _, pure = close_loop(make_solver(CemGdConfig(grad_steps=0)), steps=12)
    assert with_gradients < pure


def test_same_seed_same_plans_bitwise_and_other_seed_differs():
    def plans(seed):
        solver = make_solver(CemGdConfig(seed=seed, cem_iterations=2))
        state, out = x0(), []
        for _ in range(3):
            result = solver.solve(state)
            out.append(result.plan)
            state = integrator(state, result.action.unsqueeze(0))
        return out

    first, again, other = plans(3), plans(3), plans(4)
    assert all(torch.equal(a, b) for a, b in zip(first, again))
    assert not torch.equal(first[0], other[0])


def test_reset_behaves_like_a_fresh_solver():
    solver = make_solver(CemGdConfig())
    first = solver.solve(x0())
    solver.solve(x0((0.1, 0.0, 0.0)))
    solver.reset()
    assert torch.equal(solver.solve(x0()).plan, first.plan)


def test_global_rng_is_untouched():
    before = torch.get_rng_state()
    make_solver(CemGdConfig()).solve(x0())
    assert torch.equal(torch.get_rng_state(), before)


def test_solves_with_gradients_under_no_grad():
    expected = make_solver(CemGdConfig()).solve(x0())
    with torch.no_grad():
        result = make_solver(CemGdConfig()).solve(x0())
    assert torch.equal(result.plan, expected.plan)


def test_float32_result_and_timings():
    result = make_solver(CemGdConfig(), dtype=torch.float32).solve(x0(dtype=torch.float32))
    assert result.plan.dtype == result.action.dtype == torch.float32
    assert result.plan.shape == (10, 1, 3) and result.action.shape == (1, 3)
    assert set(result.timings) == {"rollout_s", "backward_s", "cem_s"}
    assert all(t > 0 for t in result.timings.values())


def test_cost_of_wrong_shape_is_rejected():
    solver = make_solver(CemGdConfig(), stage=lambda states, u: to_goal(states[0]).unsqueeze(-1))
    with pytest.raises(ValueError, match="shape"):
        solver.solve(x0())


@settings(max_examples=40, deadline=None)
@given(
    low=st.lists(st.floats(-1.0, 1.0), min_size=6, max_size=6),
    width=st.lists(st.sampled_from([0.0, 0.01, 0.3, 2.0]), min_size=6, max_size=6),
    start=st.lists(st.floats(-5.0, 5.0), min_size=6, max_size=6),
    dtype=st.sampled_from([torch.float32, torch.float64]),
)
def test_every_sample_and_the_action_stay_within_bounds(low, width, start, dtype):
    low_t = torch.tensor(low, dtype=dtype).view(2, 3)
    high_t = low_t + torch.tensor(width, dtype=dtype).view(2, 3)
    far = torch.tensor([[10.0, -10.0, 10.0], [-10.0, 10.0, 0.0]], dtype=dtype)
    recorder = Recorder(lambda x, u: x + u)
    config = CemGdConfig(samples=12, elites=3, horizon=3, grad_steps=3, cem_iterations=2, lr=0.5)
    solver = CemGd(
        recorder, lambda states, u: effort_cost(u), lambda x: (x - far).square().flatten(1).sum(-1),
        low_t, high_t, config, dtype=dtype,
    )
    state = torch.tensor(start, dtype=dtype).view(1, 2, 3)
    for _ in range(2):
        result = solver.solve(state)
        state = state + result.action
        for u in [*recorder.calls, result.action.unsqueeze(0), result.plan]:
            assert bool(((u >= low_t) & (u <= high_t)).all())
    fixed = low_t == high_t
    assert torch.equal(result.action[fixed], low_t[fixed])


@pytest.mark.parametrize("workers", [1, 2])
def test_samples_with_nan_dynamics_are_never_chosen(workers):
    def nan_when_pushing_x(state, u):  # the goal lies towards +x, but any u_x > 0.05 gives NaN
        nxt = integrator(state, u)
        bad = (u[:, 0, 0] > 0.05).unsqueeze(-1)
        return State(torch.where(bad, math.nan, nxt.pos), nxt.steps)

    solver = make_solver(CemGdConfig(grad_steps=2, workers=workers), dynamics=nan_when_pushing_x)
    for _ in range(2):
        result = solver.solve(x0())
        assert result.status == "ok" and math.isfinite(result.cost)
        assert torch.isfinite(result.plan).all() and (result.plan[..., 0] <= 0.05).all()
        assert torch.isfinite(solver.mean).all() and torch.isfinite(solver.std).all()


def test_all_nan_returns_the_rest_action_and_recovers():
    broken = True

    def dynamics(state, u):
        nxt = integrator(state, u)
        return State(nxt.pos * math.nan, nxt.steps) if broken else nxt

    solver = make_solver(CemGdConfig(grad_steps=2), dynamics=dynamics)
    result = solver.solve(x0())
    assert result.status == "no_finite_sample" and result.cost == math.inf and result.states == []
    assert torch.equal(result.action, torch.zeros(1, 3, dtype=F64))
    assert torch.equal(result.plan, torch.zeros(10, 1, 3, dtype=F64))
    broken = False
    result = solver.solve(x0())
    assert result.status == "ok" and math.isfinite(result.cost)


def test_nan_gradients_are_zeroed_per_sample():
    def dynamics(state, u):  # finite forward; NaN backward where u_x < -0.08 (the unselected sqrt branch)
        u_x = u[:, 0, 0]
        bump = torch.where(u_x < -0.08, 0.0, (u_x + 0.08).sqrt())
        return State(state.pos + u[:, 0] + 1e-3 * bump.unsqueeze(-1), state.steps + 1)

    recorder = Recorder(dynamics)
    solver = make_solver(CemGdConfig(grad_steps=3), dynamics=recorder)
    result = solver.solve(x0())
    assert result.status == "ok" and math.isfinite(result.cost)
    assert all(torch.isfinite(u).all() for u in recorder.calls)
    # The samples that kept finite gradients did move: some recorded actions differ between steps.
    horizon = solver.config.horizon
    assert not torch.equal(recorder.sequences(0, horizon), recorder.sequences(3 * horizon, horizon))


def test_warm_start_refits_to_elites_then_shifts():
    config = CemGdConfig(samples=256, elites=16, horizon=4, grad_steps=0, min_std=0.01)
    recorder = Recorder(integrator)
    solver = make_solver(config, dynamics=recorder)
    solver.solve(x0())
    first = recorder.sequences(0, config.horizon)  # (B, K, 1, 3), G = 0: one rollout per solve
    positions = first[:, :, 0].cumsum(1)  # x_1..x_K
    costs = (positions - GOAL).square().sum(-1)
    costs = costs[:, :-1].sum(1) + costs[:, -1] + 0.01 * first.square().flatten(1).sum(1)
    elites = first[torch.argsort(costs)[: config.elites]]
    rest = torch.zeros(1, 1, 1, 3, dtype=F64)
    shifted = torch.cat([elites[:, 1:], rest.expand(config.elites, 1, 1, 3)], dim=1)
    assert torch.allclose(solver.mean, shifted.mean(0), atol=1e-12)

    solver.solve(x0())
    second = recorder.sequences(config.horizon, config.horizon)
    assert torch.equal(second[: config.elites], shifted)  # elites kept, shifted
    fresh = second[config.elites :]  # resampled around the shifted mean
    spread = solver.std.new_tensor(BOUND) / math.sqrt(fresh.shape[0])
    assert ((fresh.mean(0) - shifted.mean(0)).abs() < 5 * spread).all()


def test_second_solve_starts_from_the_shifted_plan():
    # One elite and no std floor: the mean is the best plan and every fresh sample equals it exactly.
    config = CemGdConfig(samples=16, elites=1, horizon=5, grad_steps=0, min_std=0.0)
    recorder = Recorder(integrator)
    solver = make_solver(config, dynamics=recorder)
    best = solver.solve(x0()).plan
    assert torch.equal(solver.mean[:-1], best[1:])
    assert torch.equal(solver.mean[-1], torch.zeros(1, 3, dtype=F64))
    solver.solve(x0())
    second = recorder.sequences(config.horizon, config.horizon)
    assert torch.equal(second[:, :-1], best[1:].expand(16, 4, 1, 3))
    assert second[1:, -1].std(0).min() > 0.01  # the appended step is explored with init_std


def test_refitted_std_is_floored_to_keep_exploring():
    # A single elite has zero spread: the std falls to the floor, then the appended step gets init_std.
    config = CemGdConfig(samples=8, elites=1, horizon=4, min_std=0.2, init_std=0.5)
    solver = make_solver(config)
    solver.solve(x0())
    torch.testing.assert_close(solver.std[:-1], torch.full((3, 1, 3), 0.2 * BOUND, dtype=F64))
    torch.testing.assert_close(solver.std[-1], torch.full((1, 3), 0.5 * BOUND, dtype=F64))


class ThreadRecorder:
    """Dynamics wrapper recording which threads ran it and the batch sizes they were given."""

    def __init__(self, dynamics):
        self.dynamics = dynamics
        self.threads: set[int] = set()
        self.batches: set[int] = set()

    def __call__(self, state, u):
        self.threads.add(threading.get_ident())
        self.batches.add(u.shape[0])
        return self.dynamics(state, u)


@pytest.mark.parametrize("workers", [2, 3])
def test_workers_split_the_batch_over_threads_and_plan_the_same(workers):
    """64 samples over 2 workers (32 each) or 3 (22, 21, 21): every share on a worker thread, and three
    receding-horizon solves give the plans, costs and warm starts of the single-thread solver."""
    recorder = ThreadRecorder(integrator)
    alone, shared = make_solver(CemGdConfig(seed=3)), make_solver(CemGdConfig(seed=3, workers=workers), recorder)
    state = x0()
    for _ in range(3):
        expected, result = alone.solve(state), shared.solve(state)
        torch.testing.assert_close(result.plan, expected.plan, rtol=0, atol=1e-12)
        assert result.cost == pytest.approx(expected.cost, rel=1e-12)
        torch.testing.assert_close(shared.mean, alone.mean, rtol=0, atol=1e-12)
        state = integrator(state, result.action.unsqueeze(0))
    assert threading.get_ident() not in recorder.threads and 1 <= len(recorder.threads) <= workers
    assert recorder.batches == {len(share) for share in torch.arange(64).tensor_split(workers)}


def test_threads_share_chunks_of_the_batch_and_plan_the_same():
    """``chunks = 8`` over two worker threads: the 64 samples go out in chunks of 8, which both threads take, and
    three solves give the single-thread solver's plans."""
    recorder = ThreadRecorder(integrator)
    alone, shared = make_solver(CemGdConfig(seed=3)), make_solver(CemGdConfig(seed=3, workers=2, chunks=8), recorder)
    state = x0()
    for _ in range(3):
        expected, result = alone.solve(state), shared.solve(state)
        torch.testing.assert_close(result.plan, expected.plan, rtol=0, atol=1e-12)
        torch.testing.assert_close(shared.mean, alone.mean, rtol=0, atol=1e-12)
        state = integrator(state, result.action.unsqueeze(0))
    assert recorder.batches == {8} and threading.get_ident() not in recorder.threads


def test_one_worker_never_cuts_its_batch_into_chunks():
    recorder = ThreadRecorder(integrator)
    make_solver(CemGdConfig(seed=3, chunks=4), recorder).solve(x0())
    assert recorder.batches == {64} and recorder.threads == {threading.get_ident()}
    assert CemGdConfig(chunks=4).pieces == 1 and CemGdConfig(workers=2).pieces == 2
    assert CemGdConfig(workers=2, chunks=8).pieces == 8


@pytest.mark.parametrize("workers, cem_iterations", [(1, 1), (1, 3), (3, 1), (3, 3)])
def test_the_states_are_the_models_rollout_of_the_returned_plan(workers, cem_iterations):
    """``PlanResult.states`` is ``x_1 .. x_K`` of the returned plan from the solved state (each a batch-1 copy, the
    non-float leaf too), whichever share and CEM round the best sample came from: the planner's prediction."""
    solver = make_solver(CemGdConfig(seed=5, workers=workers, cem_iterations=cem_iterations))
    state = x0((0.1, 0.2, -0.1))
    for _ in range(2):
        result = solver.solve(state)
        assert len(result.states) == result.plan.shape[0] == 10
        expected = state
        for k, got in enumerate(result.states):
            expected = integrator(expected, result.plan[k].unsqueeze(0))
            torch.testing.assert_close(got.pos, expected.pos, rtol=0, atol=1e-15)
            assert torch.equal(got.steps, state.steps + k + 1) and got.pos._base is None
        assert to_goal(result.states[-1]).item() < to_goal(state).item()
        state = result.states[0]


def test_workers_are_validated():
    with pytest.raises(ValueError, match="workers"):
        CemGdConfig(samples=4, elites=2, workers=5)
    with pytest.raises(ValueError, match="workers"):
        CemGdConfig(workers=0)
    for chunks in (1, 65):
        with pytest.raises(ValueError, match="chunks"):
            CemGdConfig(workers=2, chunks=chunks)


TENSOR_FACTORIES = {"tensor", "as_tensor", "zeros", "ones", "empty", "full", "arange", "linspace", "eye", "rand",
                    "randn", "randint", "Generator"}


@pytest.mark.parametrize("module", ["hydrosoft/control/cem_gd.py", "hydrosoft/control/worker_processes.py"])
def test_the_solver_makes_every_new_tensor_on_a_named_device(module):
    """Each ``torch.<factory>(...)`` call in the solver and its worker processes names its ``device``: a tensor made
    without one lands on the CPU, and a solver on a GPU would then mix devices. (``*_like`` and ``.to`` follow their
    input; ``from_numpy`` is always moved on with ``.to``.)"""
    import ast
    from pathlib import Path

    tree = ast.parse((Path(__file__).parents[2] / module).read_text())
    missing = [f"line {node.lineno}: torch.{node.func.attr}" for node in ast.walk(tree)
               if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
               and isinstance(node.func.value, ast.Name) and node.func.value.id == "torch"
               and node.func.attr in TENSOR_FACTORIES and "device" not in {k.arg for k in node.keywords}]
    assert not missing, missing
