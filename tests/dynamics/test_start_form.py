"""A rollout's start state in the form a step returns (``dynamics.stepped_form``): the same first step, outputs and
gradients, and one compiled sub-step per grad mode instead of two."""

import pytest
import torch

from hydrosoft.dynamics import CompiledStep, State, step, stepped_form, with_object_update
from hydrosoft.scene import compile_scene
from hydrosoft.tasks.scenes import task_scene

pytestmark = pytest.mark.slow  # the first step traced through aot_eager: about 30 s on 2 cores


def start(object_update: str, dtype=torch.float64, batch: int = 4):
    """The pushing scene's start state as a solver gets it (expanded to ``batch``, contiguous, no cache), with
    distinct bubble motions."""
    model, state, _ = compile_scene(task_scene("pushing"), dtype=dtype)
    model = with_object_update(model, object_update)
    x0 = State(*(t.expand(batch, *t.shape[1:]).contiguous() for t in state[:3]))
    g = torch.Generator().manual_seed(3)
    u = torch.zeros(batch, model.n_bodies, 6, dtype=dtype)
    u[:, 0, :3] = 1e-3 * torch.randn(batch, 3, generator=g, dtype=dtype) * torch.tensor([1.0, 1.0, 0.2], dtype=dtype)
    u[:, 0, 5] = 0.02 * torch.randn(batch, generator=g, dtype=dtype)
    return model, x0, u


def first_step(model, state, u, stepper=None):
    """The state after one step from ``state`` and the gradient of a sum of its outputs with respect to ``u``."""
    leaf = u.clone().requires_grad_(True)
    out = (stepper or (lambda s, a: step(model, s, a)))(state, leaf)
    loss = out.object_pose.square().sum() + out.forces.square().sum() + out.body_poses.sum()
    (grad,) = torch.autograd.grad(loss, leaf)
    return State(*(t.detach() for t in out)), grad


@pytest.mark.parametrize("object_update", ["explicit", "linearly_implicit"])
def test_the_first_step_from_a_start_state_in_the_stepped_form_is_the_old_one(object_update):
    """The start state with its signed distances cached, its forces coordinate-major and its tensors requiring
    grad steps to the state the old start state stepped to, with the same gradient with respect to the actions
    (to the rounding of sums over the points in another order), and so does the compiled step, which puts every
    start state in that form."""
    model, x0, u = start(object_update)
    formed = stepped_form(model, x0, grad=True)
    B, M, N, _ = x0.forces.shape
    assert x0.phi is None and formed.phi is not None and formed.forces.stride() == (M * 3 * N, 3 * N, 1, N)
    assert all(t.requires_grad for t in formed) and not any(t.requires_grad for t in x0[:3])
    old, old_grad = first_step(model, x0, u)
    for new, new_grad in (first_step(model, formed, u),
                          first_step(model, x0, u, CompiledStep(model, backend="aot_eager"))):
        for a, b in zip(new, old):
            torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-15)
        torch.testing.assert_close(new_grad, old_grad, rtol=1e-10, atol=1e-12)
    assert stepped_form(model, formed, grad=True) is formed  # already in form: the same object


def test_a_rollout_from_a_start_state_compiles_one_sub_step_per_grad_mode(fresh_dynamo):
    """A planner's rollouts, with and without gradients, from a start state: the step compiles for two input
    signatures (one per grad mode), as the precompiled build then builds two sub-step functions, not four (the start
    state's were the largest of the planner's cold build); the start state's signed distances are one small graph,
    without gradients, whatever the grad mode, evaluated once for the rollouts from one start state."""
    model, x0, u = start("linearly_implicit", dtype=torch.float32, batch=8)
    fast = CompiledStep(model, backend="eager")
    distances, calls = fast._distances, []
    fast._distances = lambda *poses: calls.append(poses) or distances(*poses)
    leaf = u.unsqueeze(1).expand(-1, 3, -1, -1).clone().requires_grad_(True)
    state = x0
    for k in range(3):
        state = fast(state, leaf[:, k])
    torch.autograd.grad(state.object_pose.sum(), leaf)
    with torch.no_grad():
        state = x0
        for k in range(3):
            state = fast(state, leaf[:, k])
    fast._distances = distances
    assert fast.compiled, fast.fallback_reason
    assert sorted(grad for grad, _ in fast._copies._examples) == [False, True]
    assert [grad for grad, _ in distances._copies._examples] == [False]
    assert len(calls) == 1  # once per start state: both rollouts started from this one


def test_the_stepped_form_keeps_a_gradient_through_the_start_state():
    """A caller that differentiates with respect to the start state's poses keeps that gradient: the signed
    distances are computed from its poses with gradients then."""
    model, x0, u = start("explicit", batch=2)
    pose = x0.object_pose.clone().requires_grad_(True)
    formed = stepped_form(model, x0._replace(object_pose=pose), grad=True)
    assert formed.object_pose is pose and formed.phi.grad_fn is not None
    (grad,) = torch.autograd.grad(step(model, formed, u).object_pose.sum(), pose)
    (expected,) = torch.autograd.grad(step(model, x0._replace(object_pose=pose), u).object_pose.sum(), pose)
    torch.testing.assert_close(grad, expected, rtol=1e-10, atol=1e-12)
