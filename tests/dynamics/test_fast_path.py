"""The fast step: cached signed distances, the matrix form of the contact geometry and wrenches, and the
torch.compile'd step (dynamics.CompiledStep) against the eager step."""

import warnings
from dataclasses import replace

import msgspec
import pytest
import torch

from hydrosoft.contact import wrench
from hydrosoft.dynamics import (
    CompiledStep,
    State,
    advance_forces,
    contact_geometry,
    signed_distances,
    step,
    stepped_form,
    touchable_points,
    with_gathered_points,
    with_object_update,
)
from hydrosoft.geometry import se3
from hydrosoft.scene import compile_scene
from hydrosoft.tasks.scenes import task_scene


def pushing(dtype=torch.float64, spacing=None, batch=3):
    """The pushing scene with a batch of distinct random bubble motions (bubble pressed into the cube)."""
    scene = task_scene("pushing")
    if spacing is not None:
        scene = msgspec.structs.replace(scene, object=msgspec.structs.replace(scene.object, spacing=spacing))
    model, state, _ = compile_scene(scene, dtype=dtype)
    state = State(state.object_pose.expand(batch, -1), state.body_poses.expand(batch, -1, -1),
                  state.forces.expand(batch, -1, -1, -1))
    g = torch.Generator().manual_seed(1)
    u = torch.zeros(batch, model.n_bodies, 6, dtype=torch.float64)
    u[:, 0, :3] = 1e-3 * torch.randn(batch, 3, generator=g, dtype=torch.float64) * torch.tensor([1.0, 1.0, 0.2])
    u[:, 0, 5] = 0.02 * torch.randn(batch, generator=g, dtype=torch.float64)
    return model, state, u.to(dtype)


@pytest.mark.parametrize("object_update", ["explicit", "linearly_implicit"])
def test_forces_and_model_points_are_coordinate_major_and_any_layout_steps_alike(object_update):
    """The step returns its forces, and the model keeps its points and normals, laid out coordinate-major (each
    coordinate contiguous over the points: what compiled kernels read fastest), the forces as a fresh tensor rather
    than a view; a state whose forces are laid out point-major, as a caller may build it, steps to the same state (to
    rounding), with either object update (the linearly implicit one reads the forces and points coordinate-major
    too, each body's on the points it can touch)."""
    model, state, u = pushing()
    model = with_object_update(model, object_update)
    assert model.object_update == object_update
    out = step(model, state, u)
    B, M, N, _ = out.forces.shape
    assert out.forces.stride() == (M * 3 * N, 3 * N, 1, N) and out.forces._base is None
    for points in (model.points, model.normals):
        assert points.stride() == (1, N)
    point_major = out._replace(forces=out.forces.contiguous())
    assert point_major.forces.stride() == (M * N * 3, N * 3, 3, 1)
    a, b = step(model, out, u), step(model, point_major, u)  # sums over the points may run in another order
    assert torch.allclose(a.forces, b.forces, rtol=1e-12, atol=1e-15)
    assert torch.allclose(a.object_pose, b.object_pose, rtol=1e-12, atol=1e-15)


def test_cached_phi_gives_identical_rollout():
    model, state, u = pushing()
    cached, uncached = state, state
    for _ in range(6):
        cached = step(model, cached, u)
        uncached = step(model, uncached, u)._replace(phi=None)
        assert cached.phi is not None and cached.phi.shape == (3, sum(map(len, model.touchable)))
    assert torch.equal(cached.forces, uncached.forces)
    assert torch.equal(cached.object_pose, uncached.object_pose)


def pairs(model, dense):
    """The ``(B, P)`` per-body touchable entries of a dense ``(B, M, N)`` tensor, body after body."""
    return torch.cat([dense[:, m, index] for m, index in enumerate(touchable_points(model))], dim=-1)


def test_the_pushing_scene_is_pruned_per_body():
    """Bubble and table touch disjoint point sets; the planar table keeps exactly the cube's bottom face."""
    model, _, _ = pushing()
    bubble, table = (set(index.tolist()) for index in model.touchable)
    assert bubble and table and not bubble & table and len(bubble | table) == model.n_points
    bottom = (model.points[:, 2] == model.points[:, 2].min()).nonzero().squeeze(-1).tolist()
    assert table == set(bottom)


def test_cached_phi_is_the_signed_distance_of_the_state():
    model, state, u = pushing()
    nxt = step(model, state, u)
    points = se3.transform_points(nxt.object_pose, model.points).unsqueeze(1)
    local = se3.transform_points(se3.inverse(nxt.body_poses), points)
    assert torch.allclose(nxt.phi, pairs(model, signed_distances(model, local)), rtol=0, atol=1e-15)


def test_forces_stay_zero_on_points_a_body_cannot_touch():
    model, state, u = pushing()
    for _ in range(3):
        state = step(model, state, u)
    for m, index in enumerate(model.touchable):
        outside = torch.ones(model.n_points, dtype=torch.bool)
        outside[index] = False
        assert state.forces[:, m, outside].abs().max() == 0
        assert state.forces[:, m, index].abs().max() > 0


def test_contact_geometry_matches_quaternion_formulas():
    """The matrix form equals the per-point quaternion transforms of eq. 14-15 to rounding (float64)."""
    model, state, u = pushing()
    prev = step(model, state, u)._replace(phi=None)
    object_pose = se3.retract(prev.object_pose, torch.tensor([2e-4, -1e-4, 0, 0, 0, 0.01], dtype=torch.float64))
    body_poses = se3.retract(prev.body_poses, u)
    geometries = contact_geometry(model, prev, object_pose, body_poses)
    p0 = se3.transform_points(prev.object_pose, model.points).unsqueeze(1)
    p1 = se3.transform_points(object_pose, model.points).unsqueeze(1)
    x0 = se3.transform_points(se3.inverse(prev.body_poses), p0)
    x1 = se3.transform_points(se3.inverse(body_poses), p1)
    phi0, phi1 = signed_distances(model, x0), signed_distances(model, x1)
    displacement = se3.rotate_vectors(body_poses, x0 - x1)
    normal = -se3.rotate_vectors(object_pose, model.normals)
    assert len(geometries) == model.n_bodies
    for m, (geometry, index) in enumerate(zip(geometries, model.touchable)):
        assert torch.allclose(geometry.phi_prev[:, 0], phi0[:, m, index], rtol=0, atol=1e-15)
        assert torch.allclose(geometry.phi_next[:, 0], phi1[:, m, index], rtol=0, atol=1e-15)
        assert torch.allclose(geometry.displacement[:, 0], displacement[:, m, index], rtol=0, atol=1e-16)
        assert torch.allclose(geometry.normal[:, 0], normal[:, index], rtol=0, atol=1e-15)
        assert torch.equal(geometry.area, model.areas[index])


def test_wrench_matches_cross_products():
    g = torch.Generator().manual_seed(2)
    forces = torch.randn(4, 2, 50, 3, generator=g, dtype=torch.float64)
    points = torch.randn(4, 1, 50, 3, generator=g, dtype=torch.float64)
    about = torch.randn(4, 2, 3, generator=g, dtype=torch.float64)
    lever = (points - about.unsqueeze(-2)).expand_as(forces)
    expected = torch.cat([forces.sum(-2), torch.linalg.cross(lever, forces, dim=-1).sum(-2)], dim=-1)
    assert torch.allclose(wrench(forces, points, about), expected, rtol=0, atol=1e-12)


def test_advance_forces_fills_the_cache_and_keeps_the_positional_fields():
    model, state, u = pushing()
    nxt = advance_forces(model, state, state.object_pose, se3.retract(state.body_poses, u))
    object_pose, body_poses, forces = nxt[:3]
    assert torch.equal(object_pose, state.object_pose) and nxt.phi is not None
    assert State(object_pose, body_poses, forces).phi is None


def test_compiled_step_falls_back_to_eager_when_compilation_fails():
    def broken_backend(graph, example_inputs):
        raise RuntimeError("no compiler here")

    model, state, u = pushing(batch=1)
    fast = CompiledStep(model, backend=broken_backend)
    with pytest.warns(RuntimeWarning, match="running eager"):
        out = fast(state, u)
    assert not fast.compiled and "no compiler here" in fast.fallback_reason
    expected = step(model, state, u)
    assert torch.equal(out.forces, expected.forces)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fast(state, u)  # warns once only


@pytest.mark.slow
def test_compiled_step_matches_eager():
    """Inductor, float32 (the fast path), one graph (fullgraph: the ellipsoid's solver loop included). Stated
    tolerance: forces within 1e-5 of the largest force, poses within 1e-6 m, signed distances within 1e-7 m,
    gradients within 1e-4 of the largest gradient entry. The third sample's action is NaN, as a planner's lost
    sample is: it stays NaN, and the others, their gradients and the compiled path are unaffected (the default
    options leave the kernels' index checks out). (About a minute: most of it compiling.)"""
    model, state, u = pushing(torch.float32, spacing=0.0125, batch=3)
    u[2] = torch.nan
    state = step(model, state, u)
    fast = CompiledStep(model, fullgraph=True)
    with torch.no_grad():
        eager, compiled = step(model, state, u), fast(state, u)
    assert fast.compiled
    assert torch.isnan(eager.object_pose[2]).any()
    for got, want in zip(compiled, eager):
        assert torch.equal(torch.isnan(got), torch.isnan(want))
    assert (compiled.forces[:2] - eager.forces[:2]).abs().max() <= 1e-5 * eager.forces[:2].abs().max()
    assert torch.allclose(compiled.object_pose[:2], eager.object_pose[:2], rtol=0, atol=1e-6)
    assert torch.allclose(compiled.phi[:2], eager.phi[:2], rtol=0, atol=1e-7)

    grads = []
    for fn in (lambda s, v: step(model, s, v), fast):
        leaf = u.detach().requires_grad_(True)
        out = fn(state, leaf)
        (g,) = torch.autograd.grad(out.forces[:2].sum() + out.object_pose[:2, :3].sum(), leaf)
        grads.append(g[:2])
    assert fast.compiled
    # inductor's backward once gave NaN for the unactuated body's actions of the finite samples (0 * NaN), and a
    # planner zeroes the whole gradient of a sample with a non-finite entry: each sample's descent must be its own
    assert torch.isfinite(grads[1]).all()
    assert (grads[1] - grads[0]).abs().max() <= 1e-4 * grads[0].abs().max()


def test_many_compiled_steps_in_one_process_all_stay_compiled(fresh_dynamo):
    """Dynamo's recompile limit (8 per code object) must not silently turn later instances eager: four models
    with two graphs each (the sub-step, and the start state's signed distances: 8 graphs) all run compiled
    (backend="eager": dynamo's capture, no code generation)."""
    model, state, u = pushing(batch=1)
    counters = torch._dynamo.utils.counters
    for k in range(4):
        fast = CompiledStep(replace(model, dt=model.dt * (1 + k / 10)), backend="eager")
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            first = fast(state, u)
            fast(first, u)
        assert fast.compiled
    assert counters["stats"]["unique_graphs"] >= 8


def test_a_compiled_step_past_the_recompile_limit_says_so(fresh_dynamo, monkeypatch):
    """Past dynamo's limit the step falls back to eager with a warning instead of silently, at the first batch size
    past it. Each batch size counts two graphs against the limit, which is lowered from dynamo's 8 to 4 here: the same
    path, past it at the third batch size instead of the fifth (each trace takes ~2 s)."""
    monkeypatch.setattr(torch._dynamo.config, "recompile_limit", 4)
    model, state, u = pushing(batch=1)
    fast = CompiledStep(model, backend="eager", dynamic=False)
    compiled = []
    with pytest.warns(RuntimeWarning, match="recompile"):
        for batch in range(1, 5):
            expanded = State(*(t.expand(batch, *t.shape[1:]) for t in state[:3]))
            fast(expanded, u.expand(batch, -1, -1))
            compiled.append(fast.compiled)
    assert compiled == [True, True, False, False]
    assert "recompile" in fast.fallback_reason.lower()


def test_actions_sliced_from_plans_of_any_horizon_reuse_one_graph(fresh_dynamo):
    """A planner passes ``u[:, k]`` of a ``(B, K, M, 6)`` plan: a view whose strides depend on ``K``. A one-sub-step
    model (the linearly implicit one) hands it to the graph as it is, so each horizon compiled the step anew (an
    open-loop plan of each episode's length passed dynamo's limit and ran eager); the step now takes every ``u`` in
    one layout."""
    model, state, u = pushing(batch=2)
    model = with_object_update(model, "linearly_implicit")
    counters = torch._dynamo.utils.counters
    fast = CompiledStep(model, backend="eager", dynamic=False)
    for horizon in (1, 6, 10, 40):
        plan = u.unsqueeze(1).expand(-1, horizon, -1, -1).contiguous()
        fast(state, plan[:, 0])
        if horizon == 1:
            graphs = counters["stats"]["unique_graphs"]
    assert fast.compiled and counters["stats"]["unique_graphs"] == graphs


def test_the_backward_graph_compiles_with_the_first_forward_step(fresh_dynamo):
    """The first step from a new signature compiles its backward graph too, under the first-step lock: compiled
    lazily at the first backward, outside the lock, it raced a second solver worker and dynamo failed."""
    from functorch.compile import make_boxed_func
    from torch._dynamo.backends.common import aot_autograd

    events = []

    def recorder(name):
        def compiler(graph, example_inputs):
            events.append(name)
            return make_boxed_func(graph.forward)
        return compiler

    model, state, u = pushing(batch=2)
    fast = CompiledStep(model, backend=aot_autograd(fw_compiler=recorder("forward"),
                                                    bw_compiler=recorder("backward")))
    leaf = u.clone().requires_grad_(True)
    out = fast(state, leaf)
    assert fast.compiled, fast.fallback_reason
    assert "backward" in events  # before any backward pass
    compiled = len(events)
    (grad,) = torch.autograd.grad(out.object_pose.sum() + out.forces.sum(), leaf)
    assert len(events) == compiled and torch.isfinite(grad).all()


def test_a_compiled_rollout_checks_stability_once_per_step_with_the_same_result(monkeypatch):
    """The start check of a step from the state the previous step returned is the end check already done."""
    import hydrosoft.dynamics as dynamics

    model, state, u = pushing()
    calls = []
    original = dynamics.substeps_needed
    monkeypatch.setattr(dynamics, "substeps_needed", lambda m, s: calls.append(s) or original(m, s))
    fast = CompiledStep(model, backend="eager")
    eager = compiled = state
    for _ in range(5):
        compiled = fast(compiled, u)
    assert len(calls) == 5 + 1
    compiled_again = fast(state, u)  # not the state it returned last: checked afresh
    assert len(calls) == 6 + 2
    monkeypatch.setattr(dynamics, "substeps_needed", original)
    for _ in range(5):
        eager = step(model, eager, u)
    # the same sub-step counts: equal to rounding (traced, the small products are spelled out, se3.small_matmul),
    # where one sub-step more per step moves the forces by 2e-5 N and the cube by 1e-4 m
    torch.testing.assert_close(compiled.forces, eager.forces, rtol=0, atol=1e-14)
    torch.testing.assert_close(compiled.object_pose, eager.object_pose, rtol=0, atol=1e-14)
    assert torch.isfinite(compiled_again.forces).all()


def test_threads_stepping_at_once_each_compile_their_own_copy_once(fresh_dynamo):
    """Solver workers call one CompiledStep from several threads at once. Four threads taking the first steps of a
    rollout together, two with gradients and two without, each step through a compiled copy of their own (a copy
    used by two at once failed its guards spuriously mid-run), compile it once for their grad mode, stay compiled
    and return the eager step's states. Later calls one after another, from another thread, reuse a copy, which
    compiles what it missed once: then no new graphs."""
    import threading

    model, state, u = pushing(batch=2)
    # in a step's own form, as the step puts it (its signed distances are a graph of their own, which the threads
    # would otherwise compile first, one after another, reaching the sub-step's copies no longer at once)
    state = stepped_form(model, state)
    counters = torch._dynamo.utils.counters
    alone = CompiledStep(model, backend="eager")
    before = counters["stats"]["unique_graphs"]
    for grad in (False, True):
        with torch.set_grad_enabled(grad):
            alone(alone(state, u), u)
    graphs_alone = counters["stats"]["unique_graphs"] - before

    fast = CompiledStep(replace(model, dt=model.dt * 1.01), backend="eager")
    expected = step(fast.model, step(fast.model, state, u), u)
    start, results, errors = threading.Barrier(4), [], []

    def rollout(grad: bool) -> None:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("error")
                with torch.set_grad_enabled(grad):
                    start.wait(timeout=60)
                    results.append(fast(fast(state, u), u))
        except BaseException as error:  # noqa: BLE001 - reported by the test
            errors.append(error)

    before = counters["stats"]["unique_graphs"]
    threads = [threading.Thread(target=rollout, args=(k % 2 == 1,)) for k in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=300)
    assert not errors and len(results) == 4, errors
    assert fast.compiled, fast.fallback_reason
    # each copy compiled its own grad mode, and some caught up on the other's signatures before a later step
    assert 2 * graphs_alone <= counters["stats"]["unique_graphs"] - before <= 4 * graphs_alone
    assert len(fast._copies.copies) == 4

    def later_rollouts() -> None:
        for grad in (False, True):
            with torch.set_grad_enabled(grad):
                results.append(fast(fast(state, u), u))

    for round_ in range(2):
        before = counters["stats"]["unique_graphs"]
        later = threading.Thread(target=later_rollouts)
        later.start()
        later.join(timeout=300)
        # the copy the later calls take catches up on what it missed (at most one instance's graphs), once
        assert counters["stats"]["unique_graphs"] - before <= (graphs_alone if round_ == 0 else 0)
    assert len(results) == 8 and len(fast._copies.copies) == 4
    for out in results:
        torch.testing.assert_close(out.forces.detach(), expected.forces, rtol=0, atol=1e-14)
        torch.testing.assert_close(out.object_pose.detach(), expected.object_pose, rtol=0, atol=1e-14)


@pytest.mark.parametrize("budget", [0.0, 1.0])
def test_the_activation_budget_keeps_the_step_and_its_gradient_and_is_not_left_set(budget, fresh_dynamo):
    """Compiled with AOT autograd at either activation budget (0: recompute the forward's intermediates in the
    backward), the step and its gradient are the eager ones; the budget applies while compiling only."""
    import torch._functorch.config as functorch_config

    model, state, u = pushing(batch=2)
    fast = CompiledStep(model, backend="aot_eager", activation_memory_budget=budget)
    default = functorch_config.activation_memory_budget
    results = []
    for fn in (fast, lambda s, v: step(model, s, v)):
        leaf = u.clone().requires_grad_(True)
        out = fn(state, leaf)
        (grad,) = torch.autograd.grad(out.forces.sum() + out.object_pose[:, :3].sum(), leaf)
        results.append((out.forces.detach(), grad))
    assert fast.compiled, fast.fallback_reason
    assert functorch_config.activation_memory_budget == default
    torch.testing.assert_close(results[0][0], results[1][0], rtol=0, atol=1e-12)
    torch.testing.assert_close(results[0][1], results[1][1], rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("task", ["pushing", "rotation", "rolling", "in_hand"])
def test_each_body_of_the_task_scenes_reads_its_points_as_a_slice(task):
    """The scene compiler orders the points so that each of two bodies' touchable points are consecutive: the step
    reads them as slices of exactly the touchable points."""
    model, _, _ = compile_scene(task_scene(task))
    for index, points in zip(model.touchable, model.point_sets):
        assert isinstance(points, slice)
        assert torch.equal(torch.arange(model.n_points)[points], index)


def test_a_third_body_off_the_order_reads_its_points_by_index():
    """Only the first two bodies' point sets are made consecutive; a body whose points are not stays a gather."""
    from hydrosoft.scene import _consecutive_order

    near = torch.tensor([[1, 1, 0, 0, 1, 0], [0, 1, 1, 0, 1, 0], [1, 0, 1, 1, 0, 0]], dtype=torch.bool)
    order = _consecutive_order(near)
    assert order.tolist() == [0, 1, 4, 2, 3, 5]
    rows = near[:, order]
    for row in rows[:2]:
        kept = row.nonzero().squeeze(-1)
        assert torch.equal(kept, torch.arange(int(kept[0]), int(kept[-1]) + 1))
    model, _, _ = compile_scene(task_scene("pushing"))
    scattered = torch.tensor([0, 2, 5])
    assert isinstance(replace(model, touchable=(scattered, model.touchable[1])).point_sets[0], torch.Tensor)


@pytest.mark.parametrize("update", ["explicit", "linearly_implicit"])
def test_sliced_and_gathered_point_sets_step_alike(update):
    """The step reads a body's points as a slice where they are consecutive; the same model with gathered indices
    takes the same steps, forces and gradients (float64, to rounding)."""
    model, state, u = pushing()
    model = with_object_update(model, update)
    gathered = with_gathered_points(model)
    assert all(isinstance(points, torch.Tensor) for points in gathered.point_sets)
    results = []
    for m in (model, gathered):
        leaf = u.clone().requires_grad_(True)
        x = state
        for _ in range(4):
            x = step(m, x, leaf)
        (grad,) = torch.autograd.grad(x.object_pose.sum() + x.forces.square().sum(), leaf)
        results.append((x, grad))
    (a, grad_a), (b, grad_b) = results
    assert torch.allclose(a.forces, b.forces, rtol=0, atol=1e-12)
    assert torch.allclose(a.object_pose, b.object_pose, rtol=0, atol=1e-15)
    assert torch.allclose(grad_a, grad_b, rtol=1e-10, atol=1e-12)
    assert grad_a.abs().max() > 0
