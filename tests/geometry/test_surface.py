"""Tests of hydrosoft.geometry.surface: exact areas, outward normals, points on the surface, mass."""
import math

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial import ConvexHull

from hydrosoft.geometry import sdf, surface

F64 = torch.float64


def prism_vertices(polygon_xz, length):
    """3D vertices of a prism along y over a polygon in x-z (independent of the library's construction)."""
    return np.array([(x, y, z) for x, z in polygon_xz for y in (-length / 2, length / 2)])


def polytope_distance(vertices):
    """Max over the hull's face planes of n.x - d: 0 on the surface, < 0 inside, > 0 outside."""
    equations = torch.as_tensor(ConvexHull(vertices).equations)
    return lambda x: (x @ equations[:, :3].T + equations[:, 3]).amax(dim=-1)


h_tri = 0.05 * math.sqrt(3) / 2
z_tri = h_tri / 3  # centroid height of the triangle above its base
z_trap = 0.03 * (0.06 + 2 * 0.03) / (3 * (0.06 + 0.03))  # centroid height of the trapezoid

# name: (surface, exact area, exact volume, vertices about the centre of mass or None, sdf or None)
CASES = {
    "cube": (surface.cube(), 6 * 0.05**2, 0.05**3, None, sdf.Box((0.025,) * 3)),
    "box": (
        surface.box((0.04, 0.07, 0.013), spacing=0.004),
        2 * (0.04 * 0.07 + 0.04 * 0.013 + 0.07 * 0.013),
        0.04 * 0.07 * 0.013,
        None,
        sdf.Box((0.02, 0.035, 0.0065)),
    ),
    "plate": (
        surface.plate(),
        2 * 0.1 * 0.1 + 4 * 0.1 * 0.005,
        0.1 * 0.1 * 0.005,
        None,
        sdf.Box((0.05, 0.05, 0.0025)),
    ),
    "cylinder": (
        surface.cylinder(),
        2 * math.pi * 0.025 * 0.1 + 2 * math.pi * 0.025**2,
        math.pi * 0.025**2 * 0.1,
        None,
        sdf.Cylinder(0.025, 0.05),
    ),
    "cylinder_15mm": (
        surface.cylinder(radius=0.015, length=0.05, spacing=0.003),
        2 * math.pi * 0.015 * 0.05 + 2 * math.pi * 0.015**2,
        math.pi * 0.015**2 * 0.05,
        None,
        sdf.Cylinder(0.015, 0.025),
    ),
    "triangle_prism": (
        surface.triangle_prism(),
        3 * 0.05 * 0.05 + 2 * math.sqrt(3) / 4 * 0.05**2,
        math.sqrt(3) / 4 * 0.05**2 * 0.05,
        prism_vertices([(-0.025, -z_tri), (0.025, -z_tri), (0.0, h_tri - z_tri)], 0.05),
        None,
    ),
    "trapezoid_prism": (
        surface.trapezoid_prism(),
        (0.06 + 0.03 + 2 * math.hypot(0.015, 0.03)) * 0.05 + 2 * (0.06 + 0.03) / 2 * 0.03,
        (0.06 + 0.03) / 2 * 0.03 * 0.05,
        prism_vertices(
            [(-0.03, -z_trap), (0.03, -z_trap), (0.015, 0.03 - z_trap), (-0.015, 0.03 - z_trap)], 0.05
        ),
        None,
    ),
}


def distance_function(name):
    _, _, _, vertices, f = CASES[name]
    return f if f is not None else polytope_distance(vertices)


@pytest.mark.parametrize("name", list(CASES))
def test_areas_exact(name):
    s, area, volume, _, _ = CASES[name]
    assert s.points.dtype == F64 and s.n_points == len(s.points) == len(s.areas) == len(s.normals)
    assert (s.areas > 0).all()
    assert abs(s.total_area / area - 1) < 1e-9
    assert abs(s.volume / volume - 1) < 1e-12


@pytest.mark.parametrize("name", list(CASES))
def test_points_on_surface_and_normals_outward(name):
    s = CASES[name][0]
    f = distance_function(name)
    assert torch.allclose(s.normals.norm(dim=-1), torch.ones(s.n_points, dtype=F64), atol=1e-14)
    assert f(s.points).abs().max() < 1e-12
    assert (f(s.points + 1e-3 * s.normals) > 0).all()
    assert (f(s.points - 1e-3 * s.normals) < 0).all()


@pytest.mark.parametrize("name", list(CASES))
def test_divergence_theorem(name):
    """Volume = (1/3) sum (p . n) A, exact for cells on planar and cylindrical faces."""
    s, _, volume, _, _ = CASES[name]
    assert abs(float(((s.points * s.normals).sum(-1) * s.areas).sum()) / 3 / volume - 1) < 1e-9
    # a closed surface has zero vector area
    assert (s.normals * s.areas[:, None]).sum(0).abs().max() < 1e-15


@pytest.mark.parametrize("name", list(CASES))
def test_spacing(name):
    s = CASES[name][0]
    spacing = 0.003 if name == "cylinder_15mm" else 0.004 if name == "box" else 0.005
    d = torch.cdist(s.points, s.points)
    d.fill_diagonal_(math.inf)
    nearest = d.min(dim=1).values
    assert nearest.max() <= spacing * (1 + 1e-9)
    assert nearest.mean() >= 0.4 * spacing
    assert s.areas.max() <= spacing**2 * (1 + 1e-9)


def test_finer_spacing_gives_more_points_same_area():
    coarse, fine = surface.cylinder(spacing=0.01), surface.cylinder(spacing=0.0025)
    assert fine.n_points > 10 * coarse.n_points
    assert abs(fine.total_area - coarse.total_area) < 1e-15


@pytest.mark.parametrize("name", ["triangle_prism", "trapezoid_prism"])
def test_prism_mass_properties_match_trimesh(name):
    s, _, _, vertices, _ = CASES[name]
    hull = trimesh.convex.convex_hull(vertices)
    assert np.allclose(hull.center_mass, 0, atol=1e-15)  # the library put the origin at the centre of mass
    assert np.isclose(hull.volume, s.volume, rtol=1e-12)
    assert np.allclose(s.unit_inertia.numpy(), hull.moment_inertia / hull.mass, rtol=1e-9, atol=1e-15)


def test_orientation_of_prisms():
    tri = surface.triangle_prism()
    down = tri.normals[:, 2] < -0.99
    assert abs(float(tri.areas[down].sum()) - 0.05 * 0.05) < 1e-15  # one rectangular face down
    assert torch.allclose(tri.points[down, 2], torch.full((int(down.sum()),), -z_tri, dtype=F64))
    assert tri.points[:, 1].abs().max() <= 0.025 + 1e-15  # axis along y
    trap = surface.trapezoid_prism()
    down = trap.normals[:, 2] < -0.99
    assert abs(float(trap.areas[down].sum()) - 0.06 * 0.05) < 1e-15  # the wide face down


def test_unit_inertia_closed_forms():
    expected = 0.05**2 / 6 * torch.eye(3, dtype=F64)
    assert torch.allclose(surface.cube(side=0.05).unit_inertia, expected, atol=1e-18)
    sx, sy, sz = 0.04, 0.07, 0.013
    expected = torch.diag(torch.tensor([sy**2 + sz**2, sx**2 + sz**2, sx**2 + sy**2], dtype=F64)) / 12
    assert torch.allclose(surface.box((sx, sy, sz)).unit_inertia, expected, atol=1e-18)
    c = surface.cylinder(radius=0.025, length=0.1)
    lateral = 0.025**2 / 4 + 0.1**2 / 12
    expected = torch.diag(torch.tensor([lateral, lateral, 0.025**2 / 2], dtype=F64))
    assert torch.allclose(c.unit_inertia, expected, atol=1e-18)
    # the cylinder's closed form against a fine polygonal cylinder
    mesh = trimesh.creation.cylinder(radius=0.025, height=0.1, sections=512)
    assert np.allclose(c.unit_inertia.numpy(), mesh.moment_inertia / mesh.mass, rtol=1e-3)


def test_to_subset_and_properties():
    s = surface.cube()
    s32 = s.to(dtype=torch.float32)
    assert s32.points.dtype == s32.normals.dtype == s32.areas.dtype == s32.unit_inertia.dtype == torch.float32
    assert s32.volume == s.volume
    top = s.normals[:, 2] > 0.5
    sub = s.subset(top)
    assert sub.n_points == int(top.sum()) == 100
    assert abs(sub.total_area - 0.05**2) < 1e-15
    idx = torch.tensor([0, 5, 7])
    assert torch.equal(s.subset(idx).points, s.points[idx])
    assert sub.unit_inertia is s.unit_inertia and sub.volume == s.volume
    assert math.isclose(s.bounding_radius, float(s.points.norm(dim=-1).max()))
    assert s.bounding_radius < math.sqrt(3) * 0.025
    with pytest.raises(ValueError, match="inconsistent shapes"):
        surface.Surface(s.points, s.normals[:-1], s.areas, s.volume, s.unit_inertia)
    with pytest.raises(ValueError, match="spacing"):
        surface.cube(spacing=0.0)
    with pytest.raises(ValueError, match="positive"):
        surface.box((0.01, -0.02, 0.01))
    with pytest.raises(ValueError, match="positive"):
        surface.triangle_prism(side=-0.05)
    with pytest.raises(ValueError, match="positive"):
        surface.cylinder(radius=0.0)


# ----------------------------------------------------------------------------------------------------
# Meshes
# ----------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("from_file", [False, True])
def test_from_mesh_box(tmp_path, from_file):
    mesh = trimesh.creation.box(extents=(0.04, 0.06, 0.02))
    path = tmp_path / "box.stl"
    mesh.export(path)
    s = surface.from_mesh(path if from_file else mesh, spacing=0.005)
    tol = 1e-6 if from_file else 1e-12  # STL stores float32 coordinates
    f = sdf.Box((0.02, 0.03, 0.01))
    assert abs(s.total_area / (2 * (0.04 * 0.06 + 0.04 * 0.02 + 0.06 * 0.02)) - 1) < tol
    assert abs(s.volume / (0.04 * 0.06 * 0.02) - 1) < tol
    assert f(s.points).abs().max() < 0.1 * tol
    assert (f(s.points + 1e-4 * s.normals) > 0).all() and (f(s.points - 1e-4 * s.normals) < 0).all()
    expected = torch.diag(torch.tensor([0.06**2 + 0.02**2, 0.04**2 + 0.02**2, 0.04**2 + 0.06**2], dtype=F64))
    expected = expected / 12
    assert torch.allclose(s.unit_inertia, expected, rtol=tol, atol=0)
    assert s.areas.max() <= 0.5 * 0.005**2 * (1 + 1e-6)  # triangles with edges < spacing
    assert s.n_points >= 2 * s.total_area / 0.005**2


def test_from_mesh_icosphere_is_centred(tmp_path):
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.03)
    offset = np.array([0.01, -0.02, 0.03])
    shifted = mesh.copy()
    shifted.apply_translation(offset)
    path = tmp_path / "ball.stl"
    shifted.export(path)
    s = surface.from_mesh(path, spacing=0.004)
    reference = surface.from_mesh(mesh, spacing=0.004)
    assert torch.allclose(s.points, reference.points, atol=1e-8)  # STL stores float32 coordinates
    assert abs(reference.total_area / mesh.area - 1) < 1e-12 and abs(s.total_area / mesh.area - 1) < 1e-6
    assert abs(reference.volume / mesh.volume - 1) < 1e-12 and abs(s.volume / mesh.volume - 1) < 1e-6
    assert ((s.points * s.normals).sum(-1) > 0).all()  # outward on a convex body about its centre
    assert s.bounding_radius <= 0.03 + 1e-12
    assert np.allclose(s.unit_inertia.numpy(), mesh.moment_inertia / mesh.mass, rtol=1e-6, atol=1e-12)
    assert np.allclose(s.unit_inertia.numpy(), 0.4 * 0.03**2 * np.eye(3), rtol=0.05, atol=1e-12)  # a ball


def test_from_mesh_inverted_mesh_gets_outward_normals():
    mesh = trimesh.creation.box(extents=(0.03, 0.03, 0.03))
    mesh.invert()
    s = surface.from_mesh(mesh, spacing=0.01)
    assert ((s.points * s.normals).sum(-1) > 0).all()
    assert s.volume > 0


def test_from_mesh_rejects_open_mesh(tmp_path):
    mesh = trimesh.creation.box(extents=(0.03, 0.03, 0.03))
    open_mesh = trimesh.Trimesh(mesh.vertices, mesh.faces[1:], process=False)
    with pytest.raises(ValueError, match="watertight"):
        surface.from_mesh(open_mesh, spacing=0.01)
    path = tmp_path / "open.stl"
    open_mesh.export(path)
    with pytest.raises(ValueError, match="watertight"):
        surface.from_mesh(path, spacing=0.01)
