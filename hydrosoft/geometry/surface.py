"""Discretized surfaces of rigid objects: points, outward normals and areas.

A :class:`Surface` samples the boundary of a solid with points at the centres of small surface cells.
The cells tile the surface exactly, so the areas sum to the true area (exactly for the primitives,
whose faces are split into rectangles, congruent triangles, arc and annulus sectors). Everything is in
the object frame, whose origin is the solid's centre of mass (uniform density).

The factories return float64 tensors on the CPU; use :meth:`Surface.to` to change dtype or device.
``spacing`` (m) is the target distance between neighbouring points: cells have sides <= spacing.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

_F64 = torch.float64


@dataclass(frozen=True, eq=False)
class Surface:
    """Point discretization of a rigid solid's boundary (object frame, origin at the centre of mass).

    Attributes:
        points: ``(N, 3)`` cell centres on the surface (m).
        normals: ``(N, 3)`` outward unit normals.
        areas: ``(N,)`` cell areas (m^2).
        volume: volume of the solid (m^3).
        unit_inertia: ``(3, 3)`` inertia tensor per unit mass about the origin, uniform density (m^2).
    """

    points: Tensor
    normals: Tensor
    areas: Tensor
    volume: float
    unit_inertia: Tensor

    def __post_init__(self):
        n = self.points.shape[0]
        if self.points.shape != (n, 3) or self.normals.shape != (n, 3) or self.areas.shape != (n,):
            raise ValueError(
                f"inconsistent shapes: points {tuple(self.points.shape)}, normals "
                f"{tuple(self.normals.shape)}, areas {tuple(self.areas.shape)}"
            )
        if self.unit_inertia.shape != (3, 3):
            raise ValueError(f"unit_inertia must be (3, 3), got {tuple(self.unit_inertia.shape)}")

    @property
    def n_points(self) -> int:
        return self.points.shape[0]

    @property
    def total_area(self) -> float:
        """Sum of the cell areas (m^2)."""
        return float(self.areas.sum())

    @property
    def bounding_radius(self) -> float:
        """Largest distance of a point from the origin (m)."""
        return float(self.points.norm(dim=-1).max())

    def to(self, dtype: torch.dtype | None = None, device=None) -> "Surface":
        """The same surface with its tensors converted to ``dtype`` and/or moved to ``device``."""
        return Surface(
            points=self.points.to(dtype=dtype, device=device),
            normals=self.normals.to(dtype=dtype, device=device),
            areas=self.areas.to(dtype=dtype, device=device),
            volume=self.volume,
            unit_inertia=self.unit_inertia.to(dtype=dtype, device=device),
        )

    def subset(self, index: Tensor) -> "Surface":
        """The points selected by ``index`` (bool mask ``(N,)`` or long indices); the solid is unchanged."""
        return Surface(
            points=self.points[index],
            normals=self.normals[index],
            areas=self.areas[index],
            volume=self.volume,
            unit_inertia=self.unit_inertia,
        )


def _check_positive(**sizes: float) -> None:
    """ValueError naming the sizes (m) that are not positive finite numbers."""
    bad = {name: value for name, value in sizes.items() if not 0 < value < math.inf}
    if bad:
        raise ValueError(f"{', '.join(bad)}: must be positive finite lengths in metres, got {bad}")


def _cells(n: float, spacing: float) -> int:
    """Number of cells of side <= spacing along a length n (m)."""
    if not spacing > 0:
        raise ValueError(f"spacing must be positive, got {spacing}")
    return max(1, math.ceil(n / spacing - 1e-9))


def _centres(n: int) -> Tensor:
    """Cell centres ``(n,)`` of the unit interval split into n equal cells."""
    return (torch.arange(n, dtype=_F64) + 0.5) / n


def _rectangle(corner: Tensor, u: Tensor, v: Tensor, normal: Tensor, spacing: float):
    """Grid over the rectangle ``corner + a u + b v``, a, b in [0, 1] (u orthogonal to v), area exact."""
    nu, nv = _cells(float(u.norm()), spacing), _cells(float(v.norm()), spacing)
    a, b = torch.meshgrid(_centres(nu), _centres(nv), indexing="ij")
    points = corner + a.reshape(-1, 1) * u + b.reshape(-1, 1) * v
    areas = torch.full((nu * nv,), float(u.norm() * v.norm()) / (nu * nv), dtype=_F64)
    return points, normal.expand_as(points), areas


def _triangle(a: Tensor, b: Tensor, c: Tensor, normal: Tensor, spacing: float):
    """Centroids of the n^2 congruent triangles of the triangle abc split n times per edge."""
    n = _cells(float(max((b - a).norm(), (c - b).norm(), (a - c).norm())), spacing)
    i, j = torch.meshgrid(torch.arange(n, dtype=_F64), torch.arange(n, dtype=_F64), indexing="ij")
    up = (i + j <= n - 1).reshape(-1)
    down = (i + j <= n - 2).reshape(-1)
    i, j = i.reshape(-1), j.reshape(-1)
    bary = torch.cat(
        (torch.stack((i[up] + 1 / 3, j[up] + 1 / 3), -1), torch.stack((i[down] + 2 / 3, j[down] + 2 / 3), -1))
    ) / n
    points = a + bary[:, :1] * (b - a) + bary[:, 1:] * (c - a)
    area = 0.5 * float(torch.linalg.cross(b - a, c - a).norm()) / n**2
    return points, normal.expand_as(points), torch.full((len(points),), area, dtype=_F64)


def _assemble(parts, volume: float, unit_inertia: Tensor) -> Surface:
    points, normals, areas = zip(*parts)
    return Surface(torch.cat(points), torch.cat(normals), torch.cat(areas), volume, unit_inertia)


def _prism(polygon: list[tuple[float, float]], length: float, spacing: float) -> Surface:
    """Right prism along y (length in m, centred) over a convex polygon ``[(x, z), ...]`` (m, ccw in x-z).

    The polygon is shifted so that the origin is the centre of mass.
    """
    xz = torch.tensor(polygon, dtype=_F64)
    x0, z0 = xz.unbind(-1)
    x1, z1 = xz.roll(-1, 0).unbind(-1)
    cross = x0 * z1 - x1 * z0
    area = 0.5 * float(cross.sum())
    cx = float(((x0 + x1) * cross).sum()) / (6 * area)
    cz = float(((z0 + z1) * cross).sum()) / (6 * area)
    xz = xz - xz.new_tensor([cx, cz])
    x0, z0 = xz.unbind(-1)
    x1, z1 = xz.roll(-1, 0).unbind(-1)
    # Second moments of the centred cross-section (Green's theorem), per unit area.
    sxx = float((cross * (x0 * x0 + x0 * x1 + x1 * x1)).sum()) / (12 * area)
    szz = float((cross * (z0 * z0 + z0 * z1 + z1 * z1)).sum()) / (12 * area)
    sxz = float((cross * (x0 * z1 + 2 * x0 * z0 + 2 * x1 * z1 + x1 * z0)).sum()) / (24 * area)
    second = torch.tensor([[sxx, 0.0, sxz], [0.0, length**2 / 12, 0.0], [sxz, 0.0, szz]], dtype=_F64)
    unit_inertia = torch.trace(second) * torch.eye(3, dtype=_F64) - second

    half = length / 2
    vertices = torch.stack((xz[:, 0], torch.zeros_like(xz[:, 0]), xz[:, 1]), dim=-1)
    y = torch.tensor([0.0, 1.0, 0.0], dtype=_F64)
    edges = vertices.roll(-1, 0) - vertices
    parts = []
    for corner, edge in zip(vertices, edges):  # side faces, outward normal = edge turned clockwise in x-z
        normal = torch.stack((edge[2], edge.new_zeros(()), -edge[0])) / edge.norm()
        parts.append(_rectangle(corner - half * y, edge, length * y, normal, spacing))
    rectangle = len(vertices) == 4 and bool(((edges * edges.roll(-1, 0)).sum(-1).abs() < 1e-15).all())
    for side in (-1.0, 1.0):
        shift = side * half * y
        if rectangle:  # a grid, as on the sides
            parts.append(_rectangle(vertices[0] + shift, edges[0], -edges[3], side * y, spacing))
            continue
        for k in range(1, len(vertices) - 1):  # a fan of triangles, each split into congruent ones
            a, b, c = vertices[0], vertices[k], vertices[k + 1]
            parts.append(_triangle(a + shift, b + shift, c + shift, side * y, spacing))
    return _assemble(parts, area * length, unit_inertia)


def box(size: tuple[float, float, float] = (0.05, 0.05, 0.05), spacing: float = 0.005) -> Surface:
    """Box of edge lengths ``size = (x, y, z)`` (m), centred, axis-aligned."""
    if len(size) != 3:
        raise ValueError(f"size: must be 3 edge lengths (x, y, z) in metres, got {size}")
    sx, sy, sz = (float(s) for s in size)
    _check_positive(x=sx, y=sy, z=sz)
    return _prism([(-sx / 2, -sz / 2), (sx / 2, -sz / 2), (sx / 2, sz / 2), (-sx / 2, sz / 2)], sy, spacing)


def plate(
    length: float = 0.10, width: float = 0.10, thickness: float = 0.005, spacing: float = 0.005
) -> Surface:
    """Flat plate: ``length`` along x, ``width`` along y, ``thickness`` along z (m)."""
    _check_positive(length=length, width=width, thickness=thickness)
    return box((length, width, thickness), spacing)


def cube(side: float = 0.05, spacing: float = 0.005) -> Surface:
    """Cube of edge ``side`` (m)."""
    _check_positive(side=side)
    return box((side, side, side), spacing)


def triangle_prism(side: float = 0.05, length: float = 0.05, spacing: float = 0.005) -> Surface:
    """Prism along y (``length`` m) with an equilateral cross-section of edge ``side`` (m), one face at -z."""
    _check_positive(side=side, length=length)
    height = side * math.sqrt(3) / 2
    return _prism([(-side / 2, 0.0), (side / 2, 0.0), (0.0, height)], length, spacing)


def trapezoid_prism(
    bottom: float = 0.06,
    top: float = 0.03,
    height: float = 0.03,
    length: float = 0.05,
    spacing: float = 0.005,
) -> Surface:
    """Prism along y (``length`` m) with an isosceles trapezoid cross-section, the wide ``bottom`` face at -z.

    ``bottom`` and ``top`` are the widths (along x) of the two parallel faces, ``height`` their distance (m).
    """
    _check_positive(bottom=bottom, top=top, height=height, length=length)
    return _prism(
        [(-bottom / 2, 0.0), (bottom / 2, 0.0), (top / 2, height), (-top / 2, height)], length, spacing
    )


def cylinder(radius: float = 0.025, length: float = 0.10, spacing: float = 0.005) -> Surface:
    """Solid cylinder about z of ``radius`` and ``length`` (m), flat caps at ``z = ±length/2``, centred.

    The side is split into arc cells ``radius dtheta dz``; each cap into rings of annulus sectors
    ``dtheta (r1^2 - r0^2) / 2`` (the innermost ring into disc sectors), points at the sector centroids.
    """
    _check_positive(radius=radius, length=length)
    n_theta, n_z = _cells(2 * math.pi * radius, spacing), _cells(length, spacing)
    theta, z = torch.meshgrid(2 * math.pi * _centres(n_theta), length * (_centres(n_z) - 0.5), indexing="ij")
    radial = torch.stack((theta.cos(), theta.sin(), torch.zeros_like(theta)), dim=-1).reshape(-1, 3)
    side_points = radius * radial + torch.stack((0 * z, 0 * z, z), dim=-1).reshape(-1, 3)
    side_area = 2 * math.pi * radius * length / (n_theta * n_z)
    parts = [(side_points, radial, torch.full((n_theta * n_z,), side_area, dtype=_F64))]

    n_rings = _cells(radius, spacing)
    for ring in range(n_rings):
        r0, r1 = radius * ring / n_rings, radius * (ring + 1) / n_rings
        n_sec = max(3, _cells(math.pi * (r0 + r1), spacing))
        dtheta = 2 * math.pi / n_sec
        # Centroid radius of an annulus sector of angle dtheta.
        rc = 2 / 3 * (r1**3 - r0**3) / (r1**2 - r0**2) * math.sin(dtheta / 2) / (dtheta / 2)
        phi = dtheta * (torch.arange(n_sec, dtype=_F64) + 0.5)
        xy = rc * torch.stack((phi.cos(), phi.sin()), dim=-1)
        areas = torch.full((n_sec,), dtheta * (r1**2 - r0**2) / 2, dtype=_F64)
        for side in (-1.0, 1.0):
            points = torch.cat((xy, torch.full((n_sec, 1), side * length / 2, dtype=_F64)), dim=-1)
            normal = torch.tensor([0.0, 0.0, side], dtype=_F64).expand(n_sec, 3)
            parts.append((points, normal, areas))

    lateral = radius**2 / 4 + length**2 / 12
    unit_inertia = torch.diag(torch.tensor([lateral, lateral, radius**2 / 2], dtype=_F64))
    return _assemble(parts, math.pi * radius**2 * length, unit_inertia)


def from_mesh(mesh_or_path, spacing: float = 0.005) -> Surface:
    """Surface of a watertight triangle mesh (a ``trimesh.Trimesh`` or a mesh file path, e.g. STL/OBJ, in m).

    Faces are split until every edge is shorter than ``spacing``; points are the triangle centroids
    with the exact face normals and areas, translated so that the origin is the centre of mass.
    Raises ValueError if the mesh is not watertight.
    """
    import trimesh
    import trimesh.remesh

    if isinstance(mesh_or_path, (str, Path)):
        mesh = trimesh.load(mesh_or_path, force="mesh")
    else:
        mesh = mesh_or_path.copy()
    if not mesh.is_watertight:
        raise ValueError("from_mesh needs a watertight (closed, manifold) triangle mesh")
    if mesh.volume < 0:
        mesh.invert()
    _cells(1.0, spacing)  # validates spacing
    vertices, faces = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=spacing)
    tri = torch.as_tensor(vertices - mesh.center_mass, dtype=_F64)[torch.as_tensor(faces)]
    cross = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    double_area = cross.norm(dim=-1)
    keep = double_area > 0  # degenerate (zero-area) faces carry no surface
    tri, cross, double_area = tri[keep], cross[keep], double_area[keep]
    return Surface(
        points=tri.mean(dim=1),
        normals=cross / double_area.unsqueeze(-1),
        areas=double_area / 2,
        volume=float(mesh.volume),
        unit_inertia=torch.as_tensor(mesh.moment_inertia / mesh.mass, dtype=_F64),
    )
