"""Tests of hydrosoft.geometry.mesh_sdf: exact grid nodes, the stated interpolation, continuation and Lipschitz
bounds, finite gradients, float32, errors, and a mesh body pressed in a compiled scene like the Box case."""
import itertools
import math
import subprocess
import sys

import pytest
import torch
import trimesh

from hydrosoft.contact.cone import split_normal
from hydrosoft.dynamics import advance_forces
from hydrosoft.geometry import sdf, se3
from hydrosoft.geometry.mesh_sdf import MeshSDF
from hydrosoft.scene import compile_scene, parse_scene

F64 = torch.float64
H = 0.003
SPHERE_RADIUS, SPHERE_SUBDIVISIONS = 0.025, 2
TORUS = dict(major_radius=0.02, minor_radius=0.008, major_sections=48, minor_sections=24)


def torus_sdf(p):
    """Exact signed distance (m) of the smooth torus of TORUS."""
    radial = p[..., :2].norm(dim=-1) - TORUS["major_radius"]
    return torch.sqrt(radial**2 + p[..., 2] ** 2) - TORUS["minor_radius"]


def icosphere_sagitta(mesh):
    """Largest gap (m) between the sphere and the inscribed icosphere: radius minus the nearest face plane."""
    centre_to_plane = (mesh.face_normals * mesh.triangles[:, 0]).sum(-1)
    return SPHERE_RADIUS - float(centre_to_plane.min())


# (mesh SDF, exact SDF of the smooth solid, Hausdorff distance (m) between the mesh and that solid)
@pytest.fixture(scope="module")
def cases():
    box = trimesh.creation.box(extents=(0.04, 0.03, 0.02))
    sphere = trimesh.creation.icosphere(subdivisions=SPHERE_SUBDIVISIONS, radius=SPHERE_RADIUS)
    torus = trimesh.creation.torus(**TORUS)
    r_out = TORUS["major_radius"] + TORUS["minor_radius"]
    torus_gap = r_out * (1 - math.cos(math.pi / TORUS["major_sections"])) + TORUS["minor_radius"] * (
        1 - math.cos(math.pi / TORUS["minor_sections"])
    )  # chord sagittas of the two circles
    return {
        "box": (MeshSDF.from_mesh(box, resolution=H), sdf.Box((0.02, 0.015, 0.01)), 0.0),
        "icosphere": (MeshSDF.from_mesh(sphere, resolution=H), sdf.Sphere(SPHERE_RADIUS), icosphere_sagitta(sphere)),
        "torus": (MeshSDF.from_mesh(torus, resolution=H), torus_sdf, torus_gap),
    }


def grid_box(f):
    lo = torch.tensor(f.origin, dtype=F64)
    return lo, lo + f.spacing * (torch.tensor(f.grid.shape, dtype=F64) - 1)


def node_points(f):
    index = torch.meshgrid(*(torch.arange(n, dtype=F64) for n in f.grid.shape), indexing="ij")
    return grid_box(f)[0] + f.spacing * torch.stack(index, dim=-1)


def uniform(lo, hi, n, seed):
    g = torch.Generator().manual_seed(seed)
    return lo + (hi - lo) * torch.rand(n, 3, dtype=F64, generator=g)


@pytest.mark.parametrize("name", ["box", "icosphere", "torus"])
def test_grid_nodes_hold_the_exact_signed_distance(cases, name):
    f, exact, gap = cases[name]
    expected = exact(node_points(f))
    assert (f.grid - expected).abs().max() <= gap + 1e-15
    assert (f.grid < 0).any() and (f.grid > 0).any()
    clear = expected.abs() > gap + 1e-12
    assert torch.equal(f.grid[clear] < 0, expected[clear] < 0)


@pytest.mark.parametrize("name", ["box", "icosphere", "torus"])
def test_interpolation_error_and_sign_in_the_grid_box(cases, name):
    f, exact, gap = cases[name]
    assert f.error_bound == pytest.approx(math.sqrt(3) / 2 * H)
    lo, hi = grid_box(f)
    points = uniform(lo, hi, 20000, seed=1)
    phi, d = f(points), exact(points)
    assert (phi - d).abs().max() <= f.error_bound + gap + 1e-15
    near = d.abs() < 2 * H  # the band that matters for contact is covered well
    assert near.sum() > 1000 and (phi - d)[near].abs().max() <= f.error_bound + gap + 1e-15
    clear = d.abs() > f.error_bound + gap
    assert torch.equal(phi[clear] < 0, d[clear] < 0)


def test_interpolation_is_exact_where_the_distance_is_affine(cases):
    f, exact, _ = cases["box"]
    # Every node of the cells holding these points has the top face (z = 0.01) nearest: d = z - 0.01 there.
    points = uniform(torch.tensor([-0.008, -0.003, 0.007]), torch.tensor([0.008, 0.003, 0.018]), 2000, seed=2)
    assert torch.allclose(f(points), exact(points), rtol=0, atol=1e-15)


@pytest.mark.parametrize("name", ["box", "icosphere", "torus"])
def test_outside_the_grid_box_a_positive_lower_bound(cases, name):
    f, exact, gap = cases[name]
    lo, hi = grid_box(f)
    points = uniform(lo - 0.1, hi + 0.1, 20000, seed=3)
    points = points[((points < lo) | (points > hi)).any(-1)]
    phi = f(points)
    assert (phi > 0).all()
    assert (phi - exact(points)).max() <= f.error_bound + gap + 1e-15
    # Continuous across the box boundary.
    on_box = torch.maximum(torch.minimum(points, hi), lo)
    step = on_box + 1e-7 * (points - on_box) / (points - on_box).norm(dim=-1, keepdim=True)
    assert (f(step) - f(on_box)).abs().max() <= f.lipschitz * 1e-7 * (1 + 1e-6)


def special_points(f):
    """Grid nodes, cell-face centres, points on the box boundary, box corners, points beyond it, the origin."""
    lo, hi = grid_box(f)
    nodes = node_points(f).reshape(-1, 3)[::7]
    faces = nodes + torch.tensor([0.5, 0.5, 0.0], dtype=F64) * f.spacing
    on_x, on_z = nodes.clone(), nodes.clone()
    on_x[:, 0], on_z[:, 2] = hi[0], lo[2]
    corners = lo + (hi - lo) * torch.tensor(list(itertools.product((0.0, 1.0), repeat=3)), dtype=F64)
    beyond = torch.cat([2 * corners, 3 * torch.diag(hi), 3 * torch.diag(lo), torch.zeros(1, 3, dtype=F64)])
    return torch.cat([nodes, faces, on_x, on_z, corners, beyond])


@pytest.mark.parametrize("name", ["box", "icosphere", "torus"])
def test_gradients_finite_and_within_the_lipschitz_bound(cases, name):
    f, _, _ = cases[name]
    assert f.lipschitz == pytest.approx(math.sqrt(3))
    lo, hi = grid_box(f)
    points = torch.cat([special_points(f), uniform(lo - 0.05, hi + 0.05, 5000, seed=4)]).requires_grad_(True)
    (grad,) = torch.autograd.grad(f(points).sum(), points)
    assert torch.isfinite(grad).all()
    assert grad.norm(dim=-1).max() <= f.lipschitz * (1 + 1e-9)
    assert grad.norm(dim=-1).max() >= 0.99  # not trivially flat
    a, b = uniform(lo - 0.02, hi + 0.02, 20000, seed=5), uniform(lo - 0.02, hi + 0.02, 20000, seed=6)
    b = a + (b - a) * torch.rand(20000, 1, dtype=F64, generator=torch.Generator().manual_seed(7)) * 0.1
    ratio = (f(a) - f(b)).abs() / (a - b).norm(dim=-1)
    assert ratio.max() <= f.lipschitz * (1 + 1e-9)


@pytest.mark.parametrize("name", ["box", "icosphere", "torus"])
def test_float32_tracks_float64(cases, name):
    f, _, _ = cases[name]
    lo, hi = grid_box(f)
    points = torch.cat([special_points(f), uniform(lo - 0.02, hi + 0.02, 5000, seed=8)])
    p32 = points.float().requires_grad_(True)
    phi32 = f(p32)
    assert phi32.dtype == torch.float32 and phi32.shape == points.shape[:-1]
    assert (phi32.double() - f(p32.detach().double())).abs().max() <= 1e-7
    assert (phi32.double() - f(points)).abs().max() <= 1e-6  # float32 rounding of the points (~5e-9 m) included
    (grad,) = torch.autograd.grad(phi32.sum(), p32)
    assert torch.isfinite(grad).all()


def test_batched_shapes_and_identity_semantics(cases):
    f, exact, _ = cases["box"]
    points = uniform(torch.full((3,), -0.03), torch.full((3,), 0.03), 24, seed=9).reshape(2, 3, 4, 3)
    assert f(points).shape == (2, 3, 4)
    assert torch.equal(f(points), f(points.reshape(-1, 3)).reshape(2, 3, 4))
    assert f(torch.zeros(0, 3, dtype=F64)).shape == (0,)
    same = MeshSDF(f.grid, f.origin, f.spacing, f.bounding_radius)
    assert f == f and f != same and len({f, same}) == 2  # identity eq and hash, as a Model's bodies need
    assert f.bounding_radius == pytest.approx(math.sqrt(0.02**2 + 0.015**2 + 0.01**2))


def test_non_finite_points_give_non_finite_distances_eager_and_compiled(cases):
    f, _, _ = cases["box"]
    points = torch.tensor([[0.0, 0.0, 0.0], [math.nan, 0.0, 0.0], [0.001, math.inf, 0.0], [0.0, 0.0, math.nan],
                           [0.005, -0.004, 0.003]], dtype=F64)
    compiled = torch.compile(f.__call__, dynamic=False)  # inductor checks its indices: a NaN cell raised here
    for phi in (f(points), compiled(points)):
        assert torch.isnan(phi[[1, 3]]).all() and phi[2] == math.inf
        torch.testing.assert_close(phi[[0, 4]], f(points[[0, 4]]), rtol=1e-12, atol=1e-15)


def test_bad_meshes_files_and_parameters(tmp_path):
    box = trimesh.creation.box(extents=(0.03, 0.03, 0.03))
    with pytest.raises(ValueError, match="watertight"):
        MeshSDF.from_mesh(trimesh.Trimesh(box.vertices, box.faces[1:], process=False))
    with pytest.raises(ValueError, match="does not exist"):
        MeshSDF.from_mesh(tmp_path / "missing.stl")
    garbage = tmp_path / "garbage.stl"
    garbage.write_bytes(b"\x00\x01 not a mesh")
    with pytest.raises(ValueError, match="garbage.stl"):
        MeshSDF.from_mesh(garbage)
    for resolution, padding in [(0.0, 0.01), (-1e-3, 0.01), (math.nan, 0.01), (1e-3, 0.0)]:
        with pytest.raises(ValueError, match="resolution and padding"):
            MeshSDF.from_mesh(box, resolution=resolution, padding=padding)
    with pytest.raises(ValueError, match="float64"):
        MeshSDF(torch.zeros(2, 2, 2), (0.0, 0.0, 0.0), 0.01, 1.0)


def test_inverted_mesh_keeps_the_sign(cases):
    f, exact, _ = cases["box"]
    inverted = trimesh.creation.box(extents=(0.04, 0.03, 0.02))
    inverted.invert()
    assert torch.allclose(MeshSDF.from_mesh(inverted, resolution=H).grid, f.grid, rtol=0, atol=1e-15)


def test_from_spec_reads_the_mesh_file(tmp_path, cases):
    f, _, _ = cases["box"]
    path = tmp_path / "box.stl"
    trimesh.creation.box(extents=(0.04, 0.03, 0.02)).export(path)
    loaded = sdf.from_spec("mesh", path=str(path), resolution=H)
    assert isinstance(loaded, MeshSDF) and loaded.spacing == H
    assert torch.allclose(loaded.grid, f.grid, rtol=0, atol=1e-8)  # STL stores float32 vertices
    with pytest.raises(ValueError, match="bad parameters"):
        sdf.from_spec("mesh", resolution=H)
    with pytest.raises(ValueError, match="does not exist"):
        sdf.from_spec("mesh", path=str(tmp_path / "nope.stl"))


SCENE = """
contact = "nh"
dt = 0.05
epsilon = 1.0
gravity = [0.0, 0.0, 0.0]
[object]
shape = "plate"
params = {{ length = 0.06, width = 0.06, thickness = 0.004 }}
spacing = 0.004
mass = 0.1
pose = [0.0, 0.0, 0.003, 1.0, 0.0, 0.0, 0.0]
[[bodies]]
name = "pad"
sdf = "{kind}"
params = {params}
pose = [0.0, 0.0, -0.01, 1.0, 0.0, 0.0, 0.0]
E = 2e5
K = 6e4
mu = 0.6
"""


def pressed_plate(kind, params, depth):
    """Compile the scene (a 6x6 cm plate above a 8x8x2 cm pad whose top face is z = 0), press the plate's bottom
    face ``depth`` (m) into the pad and return (model, final state)."""
    model, state, _ = compile_scene(parse_scene(SCENE.format(kind=kind, params=params)))
    for z in (-0.001, -depth):
        pose = torch.tensor([[0.0, 0.0, z + 0.002, 1.0, 0.0, 0.0, 0.0]], dtype=F64)
        state = advance_forces(model, state, pose, state.body_poses)
    return model, state


def test_mesh_body_in_a_scene_presses_like_the_box(tmp_path):
    path = tmp_path / "pad.stl"
    trimesh.creation.box(extents=(0.08, 0.08, 0.02)).export(path)
    depth, E = 0.003, 2e5
    model, state = pressed_plate("mesh", f'{{ path = "{path}", resolution = 0.004 }}', depth)
    assert isinstance(model.bodies[0], MeshSDF)
    normal = -se3.rotate_vectors(state.object_pose, model.normals)
    f_n, _ = split_normal(state.forces[:, 0], normal)
    normal_force = (f_n.unsqueeze(-1) * normal).sum((0, 1))
    assert normal_force[2].item() == pytest.approx(E * 0.06 * 0.06 * depth, rel=1e-2)
    assert normal_force[:2].abs().max() < 1e-9
    box_model, box_state = pressed_plate("box", "{ half_extents = [0.04, 0.04, 0.01] }", depth)
    # Equal up to the STL's float32 vertices (top face moved by ~2e-10 m, 1e-7 of the depth).
    assert torch.allclose(state.forces.sum((1, 2)), box_state.forces.sum((1, 2)), rtol=1e-6, atol=1e-12)


def test_importing_the_module_does_not_import_trimesh():
    code = "import sys, hydrosoft.geometry.mesh_sdf; sys.exit('trimesh' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], check=False).returncode == 0
