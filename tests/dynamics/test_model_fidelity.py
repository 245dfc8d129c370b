"""Model fidelity: implicit PF friction, the co-rotating force state, the run-time stability check, the planar
support load."""

from __future__ import annotations

import math

import msgspec
import pytest
import torch
from torch import Tensor
from hypothesis import given, settings
from hypothesis import strategies as st

from hydrosoft.contact import wrench
from hydrosoft.dynamics import (
    STABLE_RATIO, State, UnstableStepError, _checked_step, _substep, advance_forces, stability_ratio, step,
    substeps_needed,
)
from hydrosoft.geometry import se3
from hydrosoft.scene import compile_scene
from hydrosoft.tasks.scenes import task_scene

F64 = torch.float64


def scene_model(task, contact="nh", spacing=None, **changes):
    scene = msgspec.structs.replace(task_scene(task), contact=contact, **changes)
    if spacing is not None:
        scene = msgspec.structs.replace(scene, object=msgspec.structs.replace(scene.object, spacing=spacing))
    return compile_scene(scene)[:2]


def substep_motions(model, state, u, steps):
    """Object pose after every sub-step of ``steps`` control steps under the constant control ``u`` (of the run a
    step keeps, when it re-runs itself with more sub-steps)."""
    poses = []
    for _ in range(steps):
        run = []

        def recording(s, u_sub, dt_sub):
            s = _substep(model, s, u_sub, dt_sub)
            run.append((float(dt_sub), s.object_pose[0].clone()))
            return s

        state, _ = _checked_step(model, state, u, recording)
        kept = round(model.dt / run[-1][0])
        poses += [pose for _, pose in run[-kept:]]
    return torch.stack(poses)


def planar_coordinate(poses, task):
    if task == "pushing":
        return poses[:, 0]
    return 2 * torch.atan2(poses[:, 6], poses[:, 3])


@pytest.mark.parametrize("contact", ["pf", "pff"])
@pytest.mark.parametrize("task", ["pushing", "rotation"])
@pytest.mark.parametrize("spacing", [None, 0.0084])
def test_path_independent_models_never_reverse_under_constant_bubble_motion(contact, task, spacing):
    """Constant bubble motion: the object's motion per sub-step never changes sign and settles to a steady speed
    (PF's friction is solved implicitly; explicit, it chattered +-3.5 mm per sub-step)."""
    model, state = scene_model(task, contact, spacing)
    u = torch.zeros(1, model.n_bodies, 6, dtype=F64)
    if task == "pushing":
        u[0, 0, 0] = 0.001
    else:
        u[0, 0, 5] = math.radians(1.0)
    x = planar_coordinate(substep_motions(model, state, u, 20), task)
    motion = torch.diff(torch.cat([planar_coordinate(state.object_pose, task), x]))
    tiny = 1e-9
    signs = torch.sign(torch.where(motion.abs() > tiny, motion, torch.zeros_like(motion)))
    assert not bool(((signs[1:] * signs[:-1]) < 0).any()), motion
    late = motion[-8:]
    per_substep = float(u[0, 0, 0 if task == "pushing" else 5]) / model.substeps
    if contact == "pf":  # PF's friction carries the object with the bubble, within 15 % of a steady speed
        assert float(late.max() - late.min()) <= 0.15 * float(late.abs().max()), late
        assert float(late.mean()) > 0.9 * per_substep
    else:  # no friction: at most a geometric drift as the membrane's edge presses on the object, never faster
        assert float(late.abs().max()) < per_substep, late


@pytest.mark.parametrize("task", ["pushing", "rolling"])
def test_pf_friction_gradient_is_the_derivative_of_the_converged_motion(task):
    """Two PF steps from a pressed state: d(object position)/d(bubble translation) by autograd (the implicit
    gradient of the friction solve) equals central finite differences. With a line search of four halvings the
    pushing solve stopped short of its minimiser, where the implicit gradient is 20x off."""
    model, state = scene_model(task, "pf")
    state = State(*(t.detach() for t in step(model, state, torch.zeros(1, model.n_bodies, 6, dtype=F64))[:3]))
    u0 = torch.zeros(1, model.n_bodies, 6, dtype=F64)
    u0[0, 0, :2] = torch.tensor([0.002, 0.0005], dtype=F64)

    def position(u):
        return step(model, step(model, state, u), u).object_pose[0, :3]

    jac = torch.autograd.functional.jacobian(position, u0)[:, 0, 0, :3]
    eps, fd = 1e-7, torch.zeros(3, 3, dtype=F64)
    for i in range(3):
        du = torch.zeros_like(u0)
        du[0, 0, i] = eps
        fd[:, i] = (position(u0 + du) - position(u0 - du)) / (2 * eps)
    assert float(fd.abs().max()) > 0.1
    assert torch.allclose(jac, fd, rtol=1e-5, atol=1e-5 * float(fd.abs().max())), (jac, fd)


def build_shear_then_turn(axis: int, angle_deg: float = 20.0):
    """In-hand grasp: shear built by lifting both bubbles 1 mm, then bubbles and cube turned rigidly together
    about world ``axis`` through the cube's centre in 10 kinematic increments."""
    model, state = scene_model("in_hand")
    lift = state.body_poses.clone()
    lift[..., 2] += 0.001
    state = advance_forces(model, state, state.object_pose, lift)
    before = state
    centre = state.object_pose[:, :3]
    for k in range(1, 11):
        delta = torch.zeros(1, 6, dtype=F64)
        delta[0, 3 + axis] = math.radians(angle_deg) / 10

        def turn(pose):
            R = se3.so3_exp(delta[:, 3:])
            moved = pose.clone()
            moved[..., :3] = se3.quat_rotate(R.expand(*pose.shape[:-1], 4), pose[..., :3] - centre.unsqueeze(-2) if pose.dim() == 3 else pose[..., :3] - centre) + (centre.unsqueeze(-2) if pose.dim() == 3 else centre)
            moved[..., 3:] = se3.quat_multiply(R.expand(*pose.shape[:-1], 4), pose[..., 3:])
            return moved

        state = advance_forces(model, state, turn(state.object_pose), turn(state.body_poses))
    rotation = se3.quat_to_matrix(se3.so3_exp(torch.tensor([[0.0] * 3], dtype=F64).index_fill(
        1, torch.tensor([axis]), math.radians(angle_deg))))[0]
    return model, before, state, rotation


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_forces_rotate_rigidly_with_a_body_and_the_object(axis):
    model, before, after, R = build_shear_then_turn(axis)
    assert float(before.forces[..., 2].sum()) > 0.1  # shear: the lifted bubbles drag the cube up
    assert torch.allclose(after.forces, before.forces @ R.mT, rtol=0, atol=1e-12)
    points = lambda s: se3.transform_points(s.object_pose, model.points)  # noqa: E731
    w_before = wrench(before.forces.sum(1), points(before), before.object_pose[:, :3])
    w_after = wrench(after.forces.sum(1), points(after), after.object_pose[:, :3])
    assert torch.allclose(w_after[:, :3], w_before[:, :3] @ R.mT, atol=1e-12)
    assert torch.allclose(w_after[:, 3:], w_before[:, 3:] @ R.mT, atol=1e-12)


def pressed_rolling(depth_m: float):
    model, state = scene_model("rolling")
    bubble = model.body_names.index("bubble")
    poses = state.body_poses.clone()
    poses[0, bubble, 2] -= depth_m
    return model, State(state.object_pose, poses, state.forces)


def pressing_deeper(model) -> tuple[State, Tensor]:
    """The rolling scene settled one step, then the bubble driven 15 mm deeper over 10 steps: ``(the start of the
    press, the action of each of its steps)``."""
    _, state = pressed_rolling(0.0)
    state = step(model, state, torch.zeros(1, model.n_bodies, 6, dtype=F64))
    u = torch.zeros(1, model.n_bodies, 6, dtype=F64)
    u[0, model.body_names.index("bubble"), 2] = -0.0015
    return State(*state[:3]), u


def pressed_deeper(model) -> State:
    """The state at the end of ``pressing_deeper``'s 10 steps."""
    deep, u = pressing_deeper(model)
    for _ in range(10):
        deep = step(model, deep, u)
    return deep


def test_the_rolling_scene_pressed_15_mm_deeper_sub_steps_more_and_settles():
    model, _ = pressed_rolling(0.0)
    state, u = pressing_deeper(model)
    z = substep_motions(model, state, u, 10)[:, 2]
    deep = pressed_deeper(model)
    assert substeps_needed(model, deep) > model.substeps
    assert float(stability_ratio(model, deep)) > STABLE_RATIO * model.substeps
    dz = torch.diff(z)
    flips = (dz[1:] * dz[:-1] < 0) & (dz[1:].abs() > 1e-5) & (dz[:-1].abs() > 1e-5)
    assert not bool(flips.any()), dz


def test_a_press_beyond_max_substeps_raises_naming_the_bound():
    model, _ = pressed_rolling(0.0)
    stiff = compile_scene(msgspec.structs.replace(task_scene("rolling"), max_substeps=model.substeps))[0]
    deep = pressed_deeper(model)
    with pytest.raises(UnstableStepError, match="max_substeps"):
        step(stiff, deep, torch.zeros(1, stiff.n_bodies, 6, dtype=F64))


@settings(max_examples=12, deadline=None)
@given(st.floats(-1.0, 1.0), st.floats(0.0, 1.0), st.integers(1, 3))
def test_no_state_past_the_bound_passes(x, down, steps):
    """Any action within the rolling bounds, plus up to 15 mm of extra press: every step ends within the stability
    bound of the sub-steps it took, or raises."""
    model, state = pressed_rolling(0.015 * down)
    u = torch.zeros(1, model.n_bodies, 6, dtype=F64)
    u[0, model.body_names.index("bubble"), 0] = 0.003 * x
    for _ in range(steps):
        used = []

        def counting(s, u_sub, dt_sub):
            used.append(float(dt_sub))
            return _substep(model, s, u_sub, dt_sub)

        try:
            state, _ = _checked_step(model, state, u, counting)
        except UnstableStepError:
            return
        n = round(model.dt / used[-1])
        assert bool(torch.isfinite(state.object_pose).all())
        assert float(stability_ratio(model, state)) <= STABLE_RATIO * n + 1e-9


@pytest.mark.parametrize("contact", ["nh", "pf", "pff"])
def test_planar_table_carries_the_weight_plus_the_bubbles_downward_load(contact):
    model, state = scene_model("pushing", contact)
    u = torch.zeros(1, model.n_bodies, 6, dtype=F64)
    u[0, 0, 0] = 0.004
    u[0, 0, 2] = -0.0005
    table = model.support
    assert model.body_names[table] == "table"
    for _ in range(6):
        state = step(model, state, u)
        normal = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
        table_n = float((state.forces[:, table] @ normal).sum())
        bubble_down = -float(state.forces[:, 0, :, 2].sum())
        assert bubble_down > 1.0
        assert table_n == pytest.approx(model.mass * 9.81 + bubble_down, rel=0, abs=1e-9)
        f_t = state.forces[0, table, :, :2]
        f_n = state.forces[0, table, :, 2]
        assert bool((f_t.norm(dim=-1) <= model.material.mu[table] * f_n + 1e-12).all())
    if contact != "pff":  # dragged fast, the cube slides on the table: friction at its limit mu (W + L)
        limit = float(model.material.mu[table]) * table_n
        assert float(f_t.sum(0).norm()) == pytest.approx(limit, rel=1e-6)
