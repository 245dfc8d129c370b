"""PF's implicit friction solve: the exact line search along a Newton direction, Newton's convergence within its
step cap on every task scene, the eager loop on the frictional pairs alone, and the compiled step's friction loop
(one compiled Newton step, early stop)."""

from __future__ import annotations

import msgspec
import pytest
import torch

from hydrosoft import dynamics
from hydrosoft.dynamics import LONGEST_STEP, _line_minimum
from hydrosoft.scene import compile_scene
from hydrosoft.tasks import make_task
from hydrosoft.tasks.scenes import task_scene

F64 = torch.float64
TOL = 1e-7  # PressureField's slip_tolerance (m)


def line_energy(alpha, kinetic, limit, s, ds):
    """phi(alpha) ``(B, A)`` at step lengths ``alpha`` ``(A,)``, written out independently of the solver."""
    k0, k1, k2 = kinetic.unbind(-1)
    quadratic = 0.5 * (k0.unsqueeze(-1) + 2 * alpha * k1.unsqueeze(-1) + alpha**2 * k2.unsqueeze(-1))
    moved = s.unsqueeze(-2) + alpha.view(-1, 1) * ds.unsqueeze(-2)  # (B, M, N, A, 3)
    slide = (limit.unsqueeze(-1) * (torch.sqrt(moved.square().sum(-1) + TOL**2) - TOL)).sum((1, 2))
    return quadratic + slide


def line_problem(seed: int, slip_scale: float, sticking: float, batch: int = 16):
    """A random line through the friction energy: a kinetic term from vectors ``dv``, ``d`` (so ``k1^2 <= k0 k2``)
    and slips of about ``slip_scale`` metres, a fraction ``sticking`` of them exactly zero (the kink)."""
    g = torch.Generator().manual_seed(seed)
    dv, d = torch.randn(batch, 3, generator=g, dtype=F64), torch.randn(batch, 3, generator=g, dtype=F64)
    scale = 10 ** (4 * torch.rand(batch, 1, generator=g, dtype=F64) - 2)
    kinetic = scale * torch.stack([(dv * dv).sum(-1), (d * dv).sum(-1), (d * d).sum(-1)], -1) * 1e-6
    s = slip_scale * torch.randn(batch, 2, 40, 3, generator=g, dtype=F64)
    s = s * (torch.rand(batch, 2, 40, 1, generator=g, dtype=F64) > sticking)
    ds = 10 ** (3 * torch.rand(batch, 1, 1, 1, generator=g, dtype=F64) - 2) * slip_scale * torch.randn(
        batch, 2, 40, 3, generator=g, dtype=F64)
    limit = torch.rand(batch, 2, 40, generator=g, dtype=F64)
    return kinetic, limit, s, ds


@pytest.mark.parametrize("slip_scale,sticking", [(1e-3, 0.0), (1e-6, 0.5), (1e-8, 0.9), (1e-4, 1.0)])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_line_search_finds_the_lowest_energy_along_the_line(seed, slip_scale, sticking):
    """Against a dense scan of [0, LONGEST_STEP] (linear and log-spaced): the step found is never worse than the
    scan's best by more than rounding, and never raises the energy above the start's."""
    kinetic, limit, s, ds = line_problem(seed, slip_scale, sticking)
    alpha = _line_minimum(kinetic, limit, s, ds, TOL)
    assert alpha.shape == (16, 1) and bool(((alpha >= 0) & (alpha <= LONGEST_STEP)).all())
    scan = torch.cat([torch.zeros(1, dtype=F64), torch.logspace(-12, 3, 3000, dtype=F64),
                      torch.linspace(0, LONGEST_STEP, 3000, dtype=F64)])
    found = torch.stack([line_energy(a, k, l, si, di)[0] for a, k, l, si, di in zip(
        alpha, kinetic.unsqueeze(1), limit.unsqueeze(1), s.unsqueeze(1), ds.unsqueeze(1))])
    scanned = line_energy(scan, kinetic, limit, s, ds)
    start = scanned[:, 0]
    rounding = 1e-12 * scanned.abs().amax(-1)
    assert bool((found.squeeze(-1) <= start + rounding).all())
    assert bool((found.squeeze(-1) <= scanned.amin(-1) + rounding).all()), (found.squeeze(-1) - scanned.amin(-1))


def planner_batches(task_name: str, batch: int = 8, steps: int = 2):
    """The inputs of every friction solve of ``steps`` PF steps from the task's start under random actions within
    its bounds, at the full planner's 8.4 mm spacing."""
    task = make_task(task_name)
    scene = msgspec.structs.replace(task_scene(task_name), contact="pf")
    scene = msgspec.structs.replace(scene, object=msgspec.structs.replace(scene.object, spacing=0.0084))
    model, state = compile_scene(scene)[:2]
    state = dynamics.State(*(None if t is None else t.expand(batch, *t.shape[1:]).clone() for t in state))
    low, high = task.bounds(model.body_names, F64)
    g = torch.Generator().manual_seed(3)
    calls = []
    solve = dynamics._implicit_friction_motion

    def recording(*args):
        calls.append(args)
        return solve(*args)

    with torch.no_grad(), pytest.MonkeyPatch.context() as patch:
        patch.setattr(dynamics, "_implicit_friction_motion", recording)
        for _ in range(steps):
            u = torch.rand(batch, *low.shape, generator=g, dtype=F64) * (high - low) + low
            state = dynamics.step(model, state, u)
    return calls


@pytest.mark.parametrize("task_name", ["pushing", "rotation", "rolling", "in_hand"])
def test_the_friction_solve_converges_within_its_newton_cap(task_name, monkeypatch):
    """Every solve, taken to its cap of ``FRICTION_NEWTON_STEPS`` without the early stop, ends where ten times as
    many steps end, to 1e-12 m (rad). The earlier search over fixed halvings needed up to 23 steps in the in-hand
    scene and failed this by a few 1e-12 m."""
    calls = planner_batches(task_name)
    assert calls
    monkeypatch.setattr(dynamics, "NEWTON_TOLERANCE", -1.0)  # no early stop: every step is taken
    with torch.no_grad():
        for args in calls[:: max(1, len(calls) // 4)]:
            capped = dynamics._implicit_friction_motion(*args)
            with monkeypatch.context() as longer:
                longer.setattr(dynamics, "FRICTION_NEWTON_STEPS", 10 * dynamics.FRICTION_NEWTON_STEPS)
                converged = dynamics._implicit_friction_motion(*args)
            assert float(converged.abs().max()) > 1e-5  # the object does move
            assert torch.allclose(capped, converged, rtol=0, atol=1e-12), (capped - converged).abs().max()


@pytest.mark.parametrize("task_name", ["pushing", "in_hand"])
def test_the_eager_newton_loop_on_the_frictional_pairs_alone_ends_where_the_full_system_ends(task_name):
    """``_frictional_pairs`` drops the (body, point) pairs without friction (most of them) and keeps the minimiser:
    the eager loop on the full system and on the pairs end within 1e-12 m (rad) on every solve of the planner
    scenes (planar pushing; in-hand rotation, spatial, two bubbles); a NaN limit is kept, so NaN stays NaN."""
    calls = planner_batches(task_name)
    with torch.no_grad():
        for model, state, body_poses, w, dt_sub, tolerance in calls:
            system = dynamics._friction_system(model, state, body_poses, w, dt_sub, tolerance)
            pairs = dynamics._frictional_pairs(system)
            kept = pairs.limit.shape[-1]
            assert 0 < kept < system.limit[0].numel() // 2
            nonzero = [(limits[limits != 0]).sort().values for limits in (pairs.limit, system.limit)]
            assert torch.equal(*nonzero)  # every non-zero limit kept
            full = dynamics._minimise_friction_energy(dynamics._newton_move, system)
            on_pairs = dynamics._minimise_friction_energy(dynamics._newton_move, pairs)
            assert float(full.abs().max()) > 1e-5  # the object does move
            assert torch.allclose(on_pairs, full, rtol=0, atol=1e-12), (on_pairs - full).abs().max()
        broken = system._replace(limit=torch.where(system.limit > 0, system.limit, torch.nan))
        assert bool(dynamics._minimise_friction_energy(dynamics._newton_move, dynamics._frictional_pairs(broken)
                                                       ).isnan().all())


def test_a_compiled_pf_step_runs_one_compiled_newton_step_per_iteration_and_stops_when_converged(monkeypatch):
    """``CompiledStep`` keeps the Newton loop out of its graphs and calls a compiled ``_newton_move`` in it, as
    often as the eager loop takes steps (the early stop works compiled too), with the eager step's result and
    gradient (dynamo's ``eager`` backend: the graph capture and breaks, no code generation)."""
    scene = msgspec.structs.replace(task_scene("pushing"), contact="pf")
    model, state = compile_scene(scene)[:2]
    batch = 4
    state = dynamics.State(*(None if t is None else t.expand(batch, *t.shape[1:]).clone() for t in state))
    u = torch.zeros(batch, model.n_bodies, 6, dtype=F64)
    u[:, 0, 0] = torch.linspace(5e-4, 2e-3, batch, dtype=F64)
    moves = {"eager": 0, "compiled": 0}
    real_minimise = dynamics._minimise_friction_energy

    def counting(move, system):
        def counted(*args):
            moves["compiled" if move is not dynamics._newton_move else "eager"] += 1
            return move(*args)
        return real_minimise(counted, system)

    monkeypatch.setattr(dynamics, "_minimise_friction_energy", counting)
    fast = dynamics.CompiledStep(model, backend="eager")
    leaves = [u.clone().requires_grad_(True) for _ in range(2)]
    eager, compiled = dynamics.step(model, state, leaves[0]), fast(state, leaves[1])
    assert fast.compiled
    assert 0 < moves["compiled"] == moves["eager"] < dynamics.FRICTION_NEWTON_STEPS * model.substeps
    assert torch.allclose(compiled.object_pose, eager.object_pose, rtol=0, atol=1e-12)
    assert float((compiled.object_pose[:, 0] - state.object_pose[:, 0]).detach().min()) > 0  # the cube is pushed
    grads = [torch.autograd.grad(out.object_pose[:, :2].sum(), leaf)[0] for out, leaf in zip((eager, compiled), leaves)]
    assert torch.allclose(grads[1], grads[0], rtol=1e-9, atol=1e-12)
