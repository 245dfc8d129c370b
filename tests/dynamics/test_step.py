"""The quasi-dynamic step on real geometry: analytic presses, gradients, stability, float32, pruning."""

from dataclasses import replace

import msgspec
import pytest
import torch

from hydrosoft.contact import Material, make
from hydrosoft.contact.cone import split_normal
from hydrosoft.dynamics import (Model, State, advance_forces, body_wrenches, object_wrench, press_in,
                                pressure_wrenches, step)
from hydrosoft.geometry import sdf, se3, surface
from hydrosoft.scene import SceneError, compile_scene
from hydrosoft.tasks.scenes import TASK_SCENES, task_scene

E, K, MU = 2e5, 6e4, 0.6


def plate_on_box_model(contact="nh", dtype=torch.float64, beta=None):
    """A 6x6 cm plate (its bottom face) above a compliant box whose top face is z = 0."""
    plate = surface.plate(length=0.06, width=0.06, thickness=0.004, spacing=0.004)
    params = {"beta": beta} if beta else {}
    return Model(
        points=plate.points, normals=plate.normals, areas=plate.areas,
        bodies=(sdf.Box((0.1, 0.1, 0.05)),), body_names=("pad",),
        material=Material(*(torch.tensor([v], dtype=torch.float64) for v in (E, K, MU))),
        actuated=torch.ones(1, dtype=torch.float64), contact=make(contact, **params), mass=0.1,
        inertia=0.1 * plate.unit_inertia, gravity=torch.zeros(3, dtype=torch.float64), dt=0.05, epsilon=1.0,
        planar=False,
    ).to(dtype), plate


def plate_pose(z, x=0.0, dtype=torch.float64):
    return torch.tensor([[x, 0.0, z + 0.002, 1.0, 0.0, 0.0, 0.0]], dtype=dtype)


BOX_POSE = torch.tensor([[[0.0, 0.0, -0.05, 1.0, 0.0, 0.0, 0.0]]], dtype=torch.float64)


def drive(model, poses, body_poses=BOX_POSE):
    state = State(poses[0], body_poses.to(model.dtype), torch.zeros(1, 1, model.n_points, 3, dtype=model.dtype))
    states = [state]
    for pose in poses[1:]:
        states.append(advance_forces(model, states[-1], pose, body_poses.to(model.dtype)))
    return states


@pytest.mark.parametrize("contact", ["nh", "pf"])
def test_plate_pressed_into_box_gives_E_area_depth(contact):
    model, plate = plate_on_box_model(contact)
    depth = 0.003
    states = drive(model, [plate_pose(z) for z in (0.001, -0.001, -depth)])
    bottom_area = 0.06 * 0.06
    normal = -se3.rotate_vectors(states[-1].object_pose, model.normals)
    f_n, _ = split_normal(states[-1].forces[:, 0], normal)
    normal_force = (f_n.unsqueeze(-1) * normal).sum((0, 1))
    assert normal_force[2].item() == pytest.approx(E * bottom_area * depth, rel=1e-2)
    assert normal_force[:2].abs().max() < 1e-9
    wrench = object_wrench(model, states[-1])
    assert torch.allclose(body_wrenches(model, states[-1])[0, 0, :3], -wrench[0, :3])
    if contact == "nh":  # no sliding friction from the side walls: the net force is the normal force
        assert wrench[0, 2].item() == pytest.approx(E * bottom_area * depth, rel=1e-2)


def test_press_in_equals_pressing_straight_down():
    model, _ = plate_on_box_model("nh")
    states = drive(model, [plate_pose(z) for z in (0.001, -0.0007, -0.0025)])
    pressed = press_in(model, states[-1].object_pose, BOX_POSE)
    assert torch.allclose(pressed.forces, states[-1].forces, rtol=1e-12, atol=1e-15)
    assert torch.equal(pressed.body_poses, BOX_POSE) and torch.equal(pressed.object_pose, states[-1].object_pose)


def test_smoothed_nh_step_gradcheck():
    model, _ = plate_on_box_model("snh", beta=2e3)
    model = replace(model, points=model.points[::9], normals=model.normals[::9], areas=model.areas[::9], epsilon=200.0)
    pose = plate_pose(-0.001)
    bodies = BOX_POSE.clone()
    forces = press_in(model, pose, bodies).forces

    def f(u, object_pose):
        s = step(model, State(object_pose, bodies, forces), u)
        return s.object_pose, s.forces

    u = torch.tensor([[[1e-3, -5e-4, -2e-4, 0.01, 0.0, 0.02]]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(f, (u, pose.requires_grad_(True)), eps=1e-7, atol=1e-6, rtol=1e-4)


def test_exact_nh_step_gradients_finite():
    model, _ = plate_on_box_model("nh")
    model = replace(model, epsilon=200.0)
    pose = plate_pose(-0.001)
    u = torch.zeros(1, 1, 6, dtype=torch.float64, requires_grad=True)
    s = press_in(model, pose, BOX_POSE.clone())
    for _ in range(5):
        s = step(model, s, u + torch.tensor([1e-3, 0, 5e-4, 0, 0, 0.01], dtype=torch.float64))
    (g,) = torch.autograd.grad(s.object_pose.sum() + s.forces.sum(), u)
    assert torch.isfinite(g).all() and g.abs().sum() > 0


def test_float32_rollout_tracks_float64_over_press_shear_release():
    """200 steps: press 3 mm, shear 6 mm, release. Stated tolerance: forces within 1e-3 of the peak force."""
    results = {}
    for dtype in (torch.float64, torch.float32):
        model, _ = plate_on_box_model("nh", dtype)
        path = ([0.001 - 0.004 * k / 50 for k in range(51)], [0.0] * 51)
        zs = path[0] + [-0.003] * 100 + [-0.003 + 0.005 * k / 49 for k in range(50)]
        xs = [0.0] * 51 + [0.006 * k / 99 for k in range(100)] + [0.006] * 50
        states = drive(model, [plate_pose(z, x, dtype) for z, x in zip(zs, xs)])
        results[dtype] = torch.stack([s.forces.sum((1, 2)) for s in states]).double()
    reference = results[torch.float64]
    peak = reference.abs().max()
    assert (results[torch.float32] - reference).abs().max() <= 1e-3 * peak


def test_stiff_scene_substeps_or_raises_with_the_bound():
    scene = task_scene("pushing")
    stiff = msgspec.structs.replace(scene, epsilon=1.0)
    model, _, report = compile_scene(stiff)
    assert report.substeps > 1
    with pytest.raises(SceneError, match=r"h\^2/epsilon \* lambda_max"):
        compile_scene(msgspec.structs.replace(stiff, max_substeps=1))


def test_substepped_stiff_rollout_stays_bounded():
    scene = msgspec.structs.replace(task_scene("pushing"), epsilon=1.0)
    model, state, report = compile_scene(scene)
    u = torch.zeros(1, model.n_bodies, 6, dtype=torch.float64)
    u[0, model.body_names.index("bubble"), 0] = 0.002
    for _ in range(20):
        state = step(model, state, u)
    assert torch.isfinite(state.forces).all()
    assert state.forces.abs().max() < 100.0


def test_planar_model_holds_height_and_tilt():
    model, state, report = compile_scene(task_scene("pushing"))
    assert report.planar
    u = torch.zeros(1, model.n_bodies, 6, dtype=torch.float64)
    u[0, model.body_names.index("bubble")] = torch.tensor([0.002, 0.001, 0.0, 0.0, 0.0, 0.02])
    start = state.object_pose.clone()
    for _ in range(10):
        state = step(model, state, u)
    assert state.object_pose[0, 2] == start[0, 2]
    assert torch.allclose(state.object_pose[0, 4:6], torch.zeros(2, dtype=torch.float64), atol=1e-12)
    assert (state.object_pose[0, :2] - start[0, :2]).norm() > 1e-4


@pytest.mark.parametrize("task", TASK_SCENES)
def test_pruned_model_matches_full_model(task):
    scene = task_scene(task)
    pruned, s_pruned, report = compile_scene(scene)
    full, s_full, full_report = compile_scene(scene, prune=False)
    assert report.points_kept <= full_report.points_kept
    move = torch.zeros(8, 1, 6, dtype=torch.float64)
    move[:, 0, :3] = torch.tensor([0.001, 0.0005, -0.0003])
    move[:, 0, 5] = 0.01
    for k in range(8):
        u_p = torch.zeros(1, pruned.n_bodies, 6, dtype=torch.float64)
        u_f = torch.zeros(1, full.n_bodies, 6, dtype=torch.float64)
        u_p[:, 0] = move[k]
        u_f[:, full.body_names.index(pruned.body_names[0])] = move[k]
        s_pruned, s_full = step(pruned, s_pruned, u_p), step(full, s_full, u_f)
        assert torch.allclose(s_pruned.object_pose, s_full.object_pose, rtol=0, atol=1e-9)
        net_p = s_pruned.forces.sum((1, 2))
        net_f = s_full.forces.sum((1, 2))
        assert torch.allclose(net_p, net_f, rtol=0, atol=1e-9)


def test_compile_report_names_what_was_left_out():
    _, _, report = compile_scene(task_scene("in_hand"))
    assert "table" in report.bodies_dropped
    assert "table" in report.summary()


def test_float32_dynamics_tracks_float64_over_press_shear_release():
    """200 quasi-dynamic steps of the pushing scene: press 2 mm, shear 30 mm, release.
    Stated tolerance: object position within 0.1 mm, net bubble force within 1% of its peak."""
    traces = {}
    for dtype in (torch.float64, torch.float32):
        model, state, _ = compile_scene(task_scene("pushing"), dtype=dtype)
        bubble = model.body_names.index("bubble")
        positions, forces = [], []
        for k in range(200):
            u = torch.zeros(1, model.n_bodies, 6, dtype=dtype)
            if k < 20:
                u[0, bubble, 2] = -1e-4
            elif k < 170:
                u[0, bubble, 0] = 2e-4
            else:
                u[0, bubble, 2] = 5e-4
            state = step(model, state, u)
            positions.append(state.object_pose[0, :3].double())
            forces.append(state.forces[0, bubble].sum(0).double())
        traces[dtype] = torch.stack(positions), torch.stack(forces)
    (p64, f64), (p32, f32) = traces[torch.float64], traces[torch.float32]
    assert (p64[-1, :2] - p64[0, :2]).norm() > 0.005  # the object really moved
    assert (f64[-1]).norm() < 1e-9  # released
    assert (p32 - p64).abs().max() < 1e-4
    assert (f32 - f64).abs().max() < 0.01 * f64.norm(dim=-1).max()


@pytest.mark.parametrize("task", ["pushing", "in_hand"])
def test_pressure_wrenches_are_the_pressure_field_step_from_rest_at_the_same_poses(task):
    """The pose-to-wrench query equals PFF's contact update from a force-free state at unchanged poses, for every
    body of a pruned scene (the pushing scene's bubble on its own points; in-hand's two bubbles), and PF's (no slip,
    so no friction); a batch of distinct poses, float64, to rounding. A planar scene's support body is left out:
    the step sets its normal force from the vertical load, the query from its pressure field."""
    for contact in ("pff", "pf"):
        scene = msgspec.structs.replace(task_scene(task), contact=contact)
        model, state, _ = compile_scene(scene)
        g = torch.Generator().manual_seed(2)
        twist = torch.zeros(4, model.n_bodies, 6, dtype=torch.float64)
        twist[..., :3] = 1e-3 * torch.randn(4, model.n_bodies, 3, generator=g, dtype=torch.float64)
        twist[..., 3:] = 0.02 * torch.randn(4, model.n_bodies, 3, generator=g, dtype=torch.float64)
        twist = twist * model.actuated.view(1, -1, 1)
        bodies = se3.retract(state.body_poses.expand(4, -1, -1), twist)
        objects = state.object_pose.expand(4, -1)
        query = pressure_wrenches(model, objects, bodies)
        rest = State(objects, bodies, torch.zeros(4, *state.forces.shape[1:], dtype=torch.float64))
        reference = body_wrenches(model, advance_forces(model, rest, objects, bodies))
        if model.planar and model.support is not None:  # the support's normal force is set from the load instead
            keep = [m for m in range(model.n_bodies) if m != model.support]
            query, reference = query[:, keep], reference[:, keep]
        assert query[..., :3].norm(dim=-1).min() > 0.1  # every body presses on the object
        torch.testing.assert_close(query, reference, rtol=0, atol=1e-12)
