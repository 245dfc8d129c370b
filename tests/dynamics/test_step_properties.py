"""Property tests of the step (issue 34, "still untested"): Newton's third law, no force without penetration, no
yaw from a symmetric push, grazing contact at 1e-12 m, a cube's edge and corner on the table and pressed into the
bubble, two tangent cylinders, and an object point at the bubble's centre."""

import math

import msgspec
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from hydrosoft.contact import ContactStep, Material, make
from hydrosoft.contact.cone import split_normal
from hydrosoft.dynamics import advance_forces, body_wrenches, step
from hydrosoft.geometry import se3
from hydrosoft.geometry.sdf import Ellipsoid
from hydrosoft.scene import compile_scene, parse_scene
from hydrosoft.tasks.scenes import task_scene

replace = msgspec.structs.replace


def coarse(task, **fields):
    scene = task_scene(task)
    return compile_scene(replace(scene, object=replace(scene.object, spacing=0.0125), **fields))


@settings(max_examples=10, deadline=None)
@given(push=st.lists(st.floats(-2e-3, 2e-3), min_size=3, max_size=3), turn=st.floats(-0.05, 0.05))
def test_every_step_keeps_newtons_third_law(push, turn):
    """The wrenches the object applies to the bodies are minus the wrench of the bodies' forces on it: the forces sum
    to zero and so do the torques, taken about the world origin."""
    model, state, _ = coarse("rolling")
    u = torch.zeros(1, model.n_bodies, 6, dtype=torch.float64)
    u[0, 0, :3], u[0, 0, 5] = torch.tensor(push, dtype=torch.float64), turn
    for _ in range(2):
        state = step(model, state, u)
    on_bodies = body_wrenches(model, state)[0]
    points = se3.transform_points(state.object_pose, model.points)[0]
    on_object = state.forces[0].sum(0)
    force = on_object.sum(0)
    torque = torch.linalg.cross(points, on_object).sum(0)
    body_origins = state.body_poses[0, :, :3]
    body_torque = (on_bodies[:, 3:] + torch.linalg.cross(body_origins, on_bodies[:, :3])).sum(0)
    scale = on_object.norm(dim=-1).sum()
    assert scale > 0
    assert (on_bodies[:, :3].sum(0) + force).abs().max() <= 1e-12 * scale
    assert (body_torque + torque).abs().max() <= 1e-12 * scale


@settings(max_examples=60, deadline=None)
@given(name=st.sampled_from(["nh", "pf", "pff", "nh_pressure_normal"]),
       phi_prev=st.lists(st.floats(-3e-3, 3e-3), min_size=5, max_size=5),
       phi_next=st.lists(st.floats(1e-15, 3e-3), min_size=5, max_size=5),
       seed=st.integers(0, 99))
def test_no_point_outside_a_body_carries_force(name, phi_prev, phi_next, seed):
    """Whatever the previous force and the motion, a point outside the body after the step (phi > 0) carries
    exactly zero force (smoothed NH is left out: its reset is smooth on purpose)."""
    g = torch.Generator().manual_seed(seed)
    normal = torch.nn.functional.normalize(torch.randn(1, 1, 5, 3, generator=g, dtype=torch.float64), dim=-1)
    geometry = ContactStep(phi_prev=torch.tensor(phi_prev, dtype=torch.float64).view(1, 1, 5),
                           phi_next=torch.tensor(phi_next, dtype=torch.float64).view(1, 1, 5),
                           displacement=1e-3 * torch.randn(1, 1, 5, 3, generator=g, dtype=torch.float64),
                           normal=normal, area=torch.full((5,), 1e-4, dtype=torch.float64))
    forces = torch.randn(1, 1, 5, 3, generator=g, dtype=torch.float64)
    material = Material(*(torch.tensor([v], dtype=torch.float64) for v in (1e5, 3e4, 0.5)))
    assert torch.count_nonzero(make(name).step(geometry, forces, material)) == 0


def test_a_push_through_the_centre_line_turns_nothing():
    """The pushing scene is mirror-symmetric about y = 0: a bubble push along x keeps the cube's yaw at 0 and its
    y at 0 (to 1e-12) over ten steps."""
    model, state, _ = compile_scene(task_scene("pushing"))
    u = torch.zeros(1, model.n_bodies, 6, dtype=torch.float64)
    u[0, 0, 0] = 2e-3
    start = state.object_pose
    for _ in range(10):
        state = step(model, state, u)
    assert state.object_pose[0, 0] - start[0, 0] > 5e-3
    assert abs(se3.yaw(state.object_pose).item()) < 1e-12 and abs(state.object_pose[0, 1].item()) < 1e-12


@pytest.mark.parametrize("offset", [1e-12, 0.0, -1e-12])  # 0: exactly on the table plane (phi == 0)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_a_cube_grazing_the_table_by_1e_12_m_slides_with_finite_forces_and_gradients(offset, dtype):
    scene = task_scene("pushing")
    scene = replace(scene, object=replace(scene.object, pose=[0, 0, 0.025 - offset, 1, 0, 0, 0]))
    model, state, _ = compile_scene(scene, dtype=dtype)
    u = torch.zeros(1, model.n_bodies, 6, dtype=dtype, requires_grad=True)
    moved = u + torch.tensor([0.002, 0, 0, 0, 0, 0], dtype=dtype)
    for _ in range(3):
        state = step(model, state, moved)
    (g,) = torch.autograd.grad(state.forces.sum() + state.object_pose.sum(), u)
    assert torch.isfinite(state.forces).all() and torch.isfinite(g).all()


CUBE_CORNERS = torch.tensor([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=torch.float64)


def cube_turn(tilt, corner):
    """A cube's orientation (unit quaternion) with an edge (turned 45 deg about x) or, turned ``tilt`` more about y,
    a corner lowest and highest."""
    edge = se3.so3_exp(torch.tensor([math.pi / 4, 0.0, 0.0], dtype=torch.float64))
    return se3.quat_multiply(se3.so3_exp(torch.tensor([0.0, tilt, 0.0], dtype=torch.float64)), edge) if corner else edge


def tilted_cube(tilt, corner):
    """The rolling scene's table with a 5 cm cube standing on an edge (turned 45 deg about x) or a corner (also about
    y by atan(1/sqrt 2)), its lowest point 1 mm into the table; the bubble far above."""
    q = cube_turn(tilt, corner)
    lowest = se3.quat_rotate(q, CUBE_CORNERS * 0.025)[:, 2].min().item()
    scene = task_scene("rolling")
    bodies = [replace(b, pose=[0.0, 0.0, 0.2, 1.0, 0.0, 0.0, 0.0]) if b.actuated else b for b in scene.bodies]
    pose = [0.0, 0.0, -lowest - 1e-3, *q.tolist()]
    return compile_scene(replace(scene, bodies=bodies, object=replace(
        scene.object, shape="cube", params={"side": 0.05}, spacing=0.005, pose=pose)))


@pytest.mark.parametrize("corner", [False, True])
def test_a_cube_on_its_edge_or_corner_steps_with_forces_inside_the_cone(corner):
    model, state, _ = tilted_cube(math.atan(1 / math.sqrt(2)), corner)
    u = torch.zeros(1, model.n_bodies, 6, dtype=torch.float64)
    for _ in range(3):
        state = step(model, state, u)
        assert torch.isfinite(state.forces).all() and torch.isfinite(state.object_pose).all()
        normal = -se3.rotate_vectors(state.object_pose, model.normals).unsqueeze(1)
        f_n, f_t = split_normal(state.forces, normal)
        assert (f_n >= 0).all()
        assert (f_t.norm(dim=-1) <= model.material.mu.view(1, -1, 1) * f_n * (1 + 1e-9) + 1e-15).all()
    assert state.forces[..., 2].sum() > 0  # the table carries it


def cube_under_the_bubble(corner):
    """The rolling scene's bubble alone, 3 mm into a 5 cm cube held with an edge (turned 45 deg about x) or a corner
    (also about y by atan(1/sqrt 2)) pointing up into it; no table."""
    q = cube_turn(math.atan(1 / math.sqrt(2)), corner)
    highest = se3.quat_rotate(q, CUBE_CORNERS * 0.025)[:, 2].max().item()
    scene = task_scene("rolling")
    bubble = next(replace(b, pose=[0.0, 0.0, highest + 0.03 - 3e-3, 1.0, 0.0, 0.0, 0.0]) for b in scene.bodies
                  if b.name == "bubble")
    return compile_scene(replace(scene, bodies=[bubble], object=replace(
        scene.object, shape="cube", params={"side": 0.05}, spacing=0.005, pose=[0.0, 0.0, 0.0, *q.tolist()])))


@pytest.mark.parametrize("corner", [False, True])
def test_a_cube_edge_or_corner_pressed_into_the_bubble_and_dragged_keeps_forces_inside_the_cone(corner):
    """The bubble pressed 1.5 mm further onto the held cube's edge or corner, then dragged 2 mm along x: every
    point's force stays finite, pushes (f_n >= 0) and inside the cone. Pressed onto the edge, the net force is
    straight down: the patch is symmetric about the edge."""
    model, state, _ = cube_under_the_bubble(corner)
    moves = [(0.0, -5e-4)] * 3 + [(1e-3, 0.0)] * 2
    for k, (dx, dz) in enumerate(moves):
        poses = state.body_poses.clone()
        poses[..., 0] += dx
        poses[..., 2] += dz
        state = advance_forces(model, state, state.object_pose, poses)
        assert torch.isfinite(state.forces).all()
        normal = -se3.rotate_vectors(state.object_pose, model.normals).unsqueeze(1)
        f_n, f_t = split_normal(state.forces, normal)
        assert (f_n >= 0).all()
        assert (f_t.norm(dim=-1) <= model.material.mu.view(1, -1, 1) * f_n * (1 + 1e-9) + 1e-15).all()
        force = state.forces[0, 0].sum(0)
        assert force[2] < 0  # the bubble pushes the cube down
        if k == 2 and not corner:
            assert force[:2].norm() <= 1e-12 * force.norm()
    assert state.forces[0, 0, :, 0].sum() > 0  # dragged along +x, the bubble pulls the cube along


RADIUS = 0.025  # m, both cylinders
CONTACT_ANGLE = math.pi / 32  # rad: a row of the object's side points faces the other cylinder (cells of pi/16)


def tangent_cylinders(contact, gap):
    """A 25 mm cylinder (axis along y) and a compliant 25 mm cylinder parallel to it, ``gap`` (m) apart along the line
    between their axes, in the xz plane at CONTACT_ANGLE from x; a negative gap overlaps. Returns the compiled scene
    with its pressed-in start state."""
    d, q = 2 * RADIUS + gap, [math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0]
    return compile_scene(parse_scene(f"""
contact = "{contact}"
dt = 0.05
epsilon = 50.0
reach = 0.01
[object]
shape = "cylinder"
params = {{ radius = {RADIUS}, length = 0.1 }}
spacing = 0.005
mass = 0.2
pose = [0.0, 0.0, 0.0, {q[0]!r}, {q[1]!r}, 0.0, 0.0]
[[bodies]]
name = "roller"
sdf = "cylinder"
params = {{ radius = {RADIUS}, half_length = 0.06 }}
pose = [{d * math.cos(CONTACT_ANGLE)!r}, 0.0, {d * math.sin(CONTACT_ANGLE)!r}, {q[0]!r}, {q[1]!r}, 0.0, 0.0]
E = 1e5
K = 3e4
mu = 0.5
actuated = false
"""))


@pytest.mark.parametrize("contact", ["nh", "nh_pressure_normal", "pf", "pff"])
def test_tangent_cylinders_push_along_their_common_normal_and_not_at_all_1e_9_m_apart(contact):
    """Two parallel cylinders touching along a line. Overlapping by 1.5 mm (three rows of points) or by 1e-9 m, the
    force on the object is finite, along the line between the axes, with no torque about the object's axis and no
    twist (the patch is symmetric about that line), and the roller gets minus it. Exactly tangent, or 1e-9 m apart,
    no point carries any force."""
    common_normal = -torch.tensor([math.cos(CONTACT_ANGLE), 0.0, math.sin(CONTACT_ANGLE)], dtype=torch.float64)
    for gap in (-1.5e-3, -1e-9):
        model, state, _ = tangent_cylinders(contact, gap)
        assert torch.isfinite(state.forces).all()
        force = state.forces[0].sum((0, 1))
        along = force @ common_normal
        assert along > 0
        assert (force - along * common_normal).norm() <= 1e-9 * along
        points = se3.transform_points(state.object_pose, model.points)[0]
        torque = torch.linalg.cross(points, state.forces[0].sum(0)).sum(0)
        assert torque.norm() <= 1e-9 * along * RADIUS
        assert (body_wrenches(model, state)[0, 0, :3] + force).norm() <= 1e-12 * along
    rows = torch.count_nonzero(tangent_cylinders(contact, -1.5e-3)[1].forces.norm(dim=-1))
    assert rows > torch.count_nonzero(tangent_cylinders(contact, -1e-9)[1].forces.norm(dim=-1)) > 0
    for gap in (0.0, 1e-9):
        assert torch.count_nonzero(tangent_cylinders(contact, gap)[1].forces) == 0


def test_a_point_at_the_ellipsoids_centre_is_deepest_with_a_finite_gradient():
    """The centre is the one point where every direction is closest-point-ambiguous up to the shortest radius: its
    distance is minus that radius, and the gradient is finite."""
    bubble = Ellipsoid((0.06, 0.045, 0.03))
    centre = torch.zeros(1, 3, dtype=torch.float64, requires_grad=True)
    phi = bubble(centre)
    (g,) = torch.autograd.grad(phi.sum(), centre)
    assert phi.item() == pytest.approx(-0.03, abs=1e-15)
    assert torch.isfinite(g).all()
