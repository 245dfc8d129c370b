"""Signed distance of a watertight triangle mesh, sampled once on a regular grid and interpolated.

:meth:`MeshSDF.from_mesh` computes the exact signed distance of the mesh (metres, negative inside) at the nodes
of a regular grid of spacing ``h`` covering the mesh bounds plus a padding; calls interpolate it trilinearly.

Construction (float64, CPU, once):

* nearest triangles by an octree descent over the grid: a block of nodes inside the ball ``(c, r)`` keeps the
  triangles ``t`` of its parent's list with ``d(c, t) <= min_t' d(c, t') + 2 r`` (no other triangle can be
  nearest to a node of the block), down to single nodes, so far triangles are dropped early. These ``d`` come
  from dot products only (fast; error below ``3e-8`` of the grid box diagonal, covered by a slack 30 times
  larger);
* unsigned distance: the exact distance to the closest point of each node's remaining triangles (Voronoi
  regions of the triangle, Ericson, *Real-Time Collision Detection* 5.1.5), the smallest one;
* sign: the angle-weighted pseudo-normal of the nearest feature (face, edge or vertex; Baerentzen and Aanaes,
  2005), which is exact for a closed, consistently wound mesh.

Cost: about ``nodes * (triangles within ~2 h of each node's nearest)`` point-triangle tests; a sphere, whose
centre is equidistant from every triangle, is the worst case.

Evaluation (pure torch, differentiable, in the dtype and device of the points): trilinear interpolation inside
the grid box, and beyond it ``sqrt(a^2 + b^2)`` with ``a`` the distance to the box and ``b`` the interpolated
value at the nearest point of the box. Bounds, with ``d`` the exact signed distance of the mesh:

* **interpolation error** ``|phi - d| <= sqrt(3)/2 h`` in the grid box: the interpolant is a convex combination
  of the 8 node values with weights ``w_i``, and ``d`` is 1-Lipschitz, so
  ``|phi(p) - d(p)| <= sum w_i |x_i - p| <= sqrt(sum w_i |x_i - p|^2) = h sqrt(sum_k t_k (1 - t_k)) <=
  sqrt(3)/2 h`` (``t_k`` the cell coordinates, Jensen). ``phi`` is exact where ``d`` is affine over a cell
  (near the middle of flat faces). So the sign is right wherever ``|d| > sqrt(3)/2 h``.
* **outside the grid box** ``0 < phi <= d + sqrt(3)/2 h``: the mesh lies in the (convex) box, so for its
  nearest box point ``c``, every mesh point ``m`` has ``|p - m|^2 >= a^2 + |c - m|^2``, hence
  ``d(p) >= sqrt(a^2 + d(c)^2)``; ``phi`` is that lower bound with ``d(c)`` replaced by its interpolant. Points
  outside the box are outside the solid, and ``phi >= a > 0`` there.
* **Lipschitz constant** ``sqrt(3)``: in a cell, ``d phi / dx`` is a bilinear blend of node differences
  ``(d(x + h e_x) - d(x)) / h``, each in ``[-1, 1]``, and likewise for y, z, so ``|grad phi| <= sqrt(3)``; it is
  reached at a node next to a sharp convex vertex, where the three edge differences can all be 1 (over a flat
  face ``|grad phi| = 1``). Beyond the box ``|grad phi|^2 = (a^2 + b^2 |g_t|^2) / (a^2 + b^2) <= 2``, ``g_t``
  the at most 2 in-face components of the interpolant's gradient. ``phi`` is continuous, so it is
  ``sqrt(3)``-Lipschitz everywhere.

Gradients are finite everywhere, on grid nodes and cell faces (one-sided cell), on the box boundary and beyond.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from hydrosoft.geometry.se3 import safe_norm

_F64 = torch.float64
_PAIRS_PER_CHUNK = 1 << 18  # node-triangle pairs evaluated at once while building (~100 MB of temporaries)
_OCTANTS = torch.tensor([[i >> 2, (i >> 1) & 1, i & 1] for i in range(8)])  # child offsets, x-major


def _closest_on_triangles(p: Tensor, a: Tensor, ab: Tensor, ac: Tensor) -> tuple[Tensor, Tensor]:
    """Closest points ``(3, P)`` of triangles ``abc`` (given as ``a``, ``ab = b - a``, ``ac = c - a``, each
    ``(3, P)``, m) to points ``p (3, P)`` (m), and the feature ``(P,)`` holding each: 0, 1, 2 the vertices a, b,
    c; 3, 4, 5 the edges ab, bc, ca; 6 the face.

    Voronoi-region tests of Ericson's ClosestPtPointTriangle (coordinates first, for fast dot products);
    degenerate triangles give a point of the triangle (so a distance no smaller than the true one).
    """
    ap = p - a
    d1, d2 = (ab * ap).sum(0), (ac * ap).sum(0)
    ab_ab, ab_ac, ac_ac = (ab * ab).sum(0), (ab * ac).sum(0), (ac * ac).sum(0)
    d3, d4 = d1 - ab_ab, d2 - ab_ac  # (ab, ac) . (p - b)
    d5, d6 = d1 - ab_ac, d2 - ac_ac  # (ab, ac) . (p - c)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2

    def ratio(num: Tensor, den: Tensor) -> Tensor:
        return torch.where(den > 0, num / torch.where(den > 0, den, 1.0), 0.0)

    t_bc = ratio(d4 - d3, (d4 - d3) + (d5 - d6))
    tests = [  # by priority, highest first: (region, test, its v and w in q = a + v ab + w ac)
        (0, (d1 <= 0) & (d2 <= 0), 0.0, 0.0),
        (1, (d3 >= 0) & (d4 <= d3), 1.0, 0.0),
        (3, (vc <= 0) & (d1 >= 0) & (d3 <= 0), ratio(d1, d1 - d3), 0.0),
        (2, (d6 >= 0) & (d5 <= d6), 0.0, 1.0),
        (5, (vb <= 0) & (d2 >= 0) & (d6 <= 0), 0.0, ratio(d2, d2 - d6)),
        (4, (va <= 0) & (d4 >= d3) & (d5 >= d6), 1.0 - t_bc, t_bc),
    ]
    face = va + vb + vc
    feature = torch.full_like(d1, 6, dtype=torch.long)
    v, w = ratio(vb, face), ratio(vc, face)
    for region, hit, v_r, w_r in reversed(tests):
        feature = torch.where(hit, region, feature)
        v, w = torch.where(hit, v_r, v), torch.where(hit, w_r, w)
    return a + v * ab + w * ac, feature


def _pseudo_normals(vertices: Tensor, faces: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Face normals ``(F, 3)``, edge pseudo-normals ``(E, 3)`` (sum of the two face normals), angle-weighted
    vertex pseudo-normals ``(V, 3)`` and the edge index of each face's edges ab, bc, ca ``(F, 3)``.
    Unnormalized except the face normals (only their directions are used); zero-area faces add nothing."""
    tri = vertices[faces]
    cross = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area2 = cross.norm(dim=-1, keepdim=True)
    face_normal = torch.where(area2 > 0, cross / torch.where(area2 > 0, area2, 1.0), 0.0)
    vertex_normal = torch.zeros_like(vertices)
    for k in range(3):
        e1, e2 = tri[:, (k + 1) % 3] - tri[:, k], tri[:, (k + 2) % 3] - tri[:, k]
        angle = torch.atan2(torch.linalg.cross(e1, e2).norm(dim=-1), (e1 * e2).sum(-1))
        vertex_normal.index_add_(0, faces[:, k], angle.unsqueeze(-1) * face_normal)
    edges = torch.stack((faces, faces.roll(-1, dims=1)), dim=-1).sort(dim=-1).values.reshape(-1, 2)
    unique, face_edges = torch.unique(edges, dim=0, return_inverse=True)
    edge_normal = torch.zeros(len(unique), 3, dtype=vertices.dtype)
    edge_normal.index_add_(0, face_edges, face_normal.repeat_interleave(3, dim=0))
    return face_normal, edge_normal, vertex_normal, face_edges.view(-1, 3)


def _distances(p: Tensor, tri: Tensor) -> Tensor:
    """Distances ``(P,)`` (m) of points ``p (3, P)`` to triangles ``tri (12, P)`` (rows: a, ab, ac, ab.ab, ab.ac,
    ac.ac), from dot products only: the face projection if it falls in the triangle, else the nearest of the
    three edges. Cancellation in ``|p - a|^2 - ...`` limits the accuracy to about ``3e-8 |p - a|``."""
    a, ab, ac, (ab_ab, ab_ac, ac_ac) = tri[0:3], tri[3:6], tri[6:9], tri[9:12]
    ap = p - a
    d1, d2, ap2 = (ab * ap).sum(0), (ac * ap).sum(0), (ap * ap).sum(0)

    def segment(start2: Tensor, along: Tensor, length2: Tensor) -> Tensor:
        """Squared distance to a segment from |p - start|^2, (p - start).edge and |edge|^2."""
        t = torch.where(length2 > 0, along / torch.where(length2 > 0, length2, 1.0), 0.0).clamp(0.0, 1.0)
        return start2 - t * (2 * along - t * length2)

    det = ab_ab * ac_ac - ab_ac * ab_ac
    v, w = ac_ac * d1 - ab_ac * d2, ab_ab * d2 - ab_ac * d1  # barycentrics of the projection, times det
    inside = (det > 0) & (v >= 0) & (w >= 0) & (v + w <= det)
    face = ap2 - (v * d1 + w * d2) / torch.where(det > 0, det, 1.0)
    edges = torch.minimum(segment(ap2, d1, ab_ab), segment(ap2, d2, ac_ac))
    bc_bc = ac_ac - 2 * ab_ac + ab_ab
    edges = torch.minimum(edges, segment(ap2 - 2 * d1 + ab_ab, d2 - d1 - ab_ac + ab_ab, bc_bc))
    return torch.where(inside, face, edges).clamp_min(0.0).sqrt()


def _signed_distance_grid(vertices: Tensor, faces: Tensor, origin: Tensor, h: float, shape: tuple) -> Tensor:
    """Exact signed distance ``shape`` (m, negative inside) of the closed, outward-wound mesh
    (``vertices (V, 3)`` m float64, ``faces (F, 3)``) at the nodes ``origin + h * (i, j, k)``.

    Octree descent (module docstring) with the fast :func:`_distances`, whose error ``slack`` covers; the
    triangles left at each node are then compared exactly.
    """
    a, b, c = vertices[faces].permute(1, 2, 0)  # each (3, F)
    ab, ac = b - a, c - a
    tri = torch.cat((a, ab, ac, (ab * ab).sum(0, True), (ab * ac).sum(0, True), (ac * ac).sum(0, True)))
    n = torch.tensor(shape)
    slack = 1e-6 * h * math.hypot(*(s - 1 for s in shape))  # grid box diagonal / 1e6: > 30 * _distances error
    size = 1 << math.ceil(math.log2(max(shape)))
    blocks = torch.zeros(1, 3, dtype=torch.long)  # block coordinates at the current size
    pair_block, pair_tri = torch.zeros(len(faces), dtype=torch.long), torch.arange(len(faces))
    while size > 1:
        size //= 2
        children = (blocks.unsqueeze(1) * 2 + _OCTANTS).reshape(-1, 3)
        valid = (children * size < n).all(-1)
        child_of = torch.full((len(children),), -1, dtype=torch.long)
        child_of[valid] = torch.arange(int(valid.sum()))
        blocks = children[valid]
        lo, hi = blocks * size, torch.minimum((blocks + 1) * size, n) - 1
        centre = (origin + h * (lo + hi).to(_F64) / 2).T
        reach = slack + h * (hi - lo).to(_F64).norm(dim=-1)  # twice the block radius, + slack
        # Chunks of whole parents (pairs are grouped by block), so a child's minimum is complete in its chunk;
        # a chunk's children are then a contiguous range of ids.
        ends = torch.bincount(pair_block, minlength=len(child_of) // 8).cumsum(0)
        targets = torch.arange(0, int(ends[-1]), _PAIRS_PER_CHUNK // 8)[1:]
        bounds = torch.cat((ends.new_zeros(1), ends[torch.searchsorted(ends, targets)], ends[-1:])).unique()
        kept_block, kept_tri = [], []
        for start, stop in zip(bounds[:-1].tolist(), bounds[1:].tolist()):
            child = child_of.view(-1, 8).index_select(0, pair_block[start:stop])
            ok = child >= 0
            child, t = child.masked_select(ok), pair_tri[start:stop].unsqueeze(-1).expand(ok.shape).masked_select(ok)
            d = _distances(centre.index_select(1, child), tri.index_select(1, t))
            first = int(child.min())
            d_min = torch.full((int(child.max()) - first + 1,), math.inf, dtype=_F64)
            d_min.scatter_reduce_(0, child - first, d, "amin")
            keep = d <= d_min[child - first] + reach.index_select(0, child)
            kept_block.append(child.masked_select(keep))
            kept_tri.append(t.masked_select(keep))
        pair_block, order = torch.cat(kept_block).sort(stable=True)
        pair_tri = torch.cat(kept_tri).index_select(0, order)

    # Leaves: each node's candidates are within slack of its nearest; take the exactly nearest one.
    p = origin.unsqueeze(-1) + h * blocks.index_select(0, pair_block).T.to(_F64)
    g = tri.index_select(1, pair_tri)
    q, feature = _closest_on_triangles(p, g[0:3], g[3:6], g[6:9])
    distance = (p - q).norm(dim=0)
    d_min = torch.full((len(blocks),), math.inf, dtype=_F64).scatter_reduce_(0, pair_block, distance, "amin")
    pick = (distance == d_min.index_select(0, pair_block)).nonzero().squeeze(-1)  # grouped by node
    first = torch.ones_like(pick, dtype=torch.bool)
    first[1:] = pair_block[pick[1:]] != pair_block[pick[:-1]]
    pick = pick[first]
    node, t, feature, toward = pair_block[pick], pair_tri[pick], feature[pick], (p - q)[:, pick].T
    face_normal, edge_normal, vertex_normal, face_edges = _pseudo_normals(vertices, faces)
    k = feature.unsqueeze(-1)
    normal = torch.where(
        k < 3,
        vertex_normal[faces[t].gather(1, k.clamp_max(2)).squeeze(-1)],
        edge_normal[face_edges[t].gather(1, (k - 3).clamp(0, 2)).squeeze(-1)],
    )
    normal = torch.where(k == 6, face_normal[t], normal)
    signed = torch.where((toward * normal).sum(-1) < 0, -distance[pick], distance[pick])
    grid = torch.empty(shape, dtype=_F64)
    grid[tuple(blocks[node].unbind(-1))] = signed
    return grid


def _load(mesh_or_path):
    """A watertight, outward-wound copy of a ``trimesh.Trimesh`` or of the mesh in a file; ValueError if the
    file does not load as a triangle mesh or the mesh is not closed and consistently wound."""
    import trimesh

    if isinstance(mesh_or_path, (str, Path)):
        if not Path(mesh_or_path).is_file():
            raise ValueError(f"mesh file {mesh_or_path} does not exist")
        try:
            mesh = trimesh.load(mesh_or_path, force="mesh")
        except Exception as err:  # trimesh raises many kinds for unreadable or unknown formats
            raise ValueError(f"cannot load mesh file {mesh_or_path}: {err}") from err
        where = f"mesh file {mesh_or_path}"
    else:
        mesh = mesh_or_path.copy()
        where = "the mesh"
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError(f"{where} holds no triangles")
    if not (mesh.is_watertight and mesh.is_winding_consistent):
        raise ValueError(f"{where} is not watertight (closed, manifold, consistently wound): its SDF is undefined")
    if mesh.volume < 0:
        mesh.invert()
    return mesh


@dataclass(frozen=True, eq=False)
class MeshSDF:
    """Signed distance of a watertight mesh from a grid of exact samples (see the module docstring).

    Attributes:
        grid: ``(nx, ny, nz)`` float64 signed distances (m, negative inside) at the nodes
            ``origin + spacing * (i, j, k)``, each axis >= 2 nodes.
        origin: the node ``(0, 0, 0)`` (m, body frame = the mesh's own coordinates).
        spacing: node spacing ``h`` (m), the same on every axis.
        bounding_radius: radius (m) of a ball about the body origin containing the solid.

    ``lipschitz = sqrt(3)``; ``error_bound`` = ``sqrt(3)/2 * spacing`` bounds ``|phi - d|`` in the grid box (both
    for grids of exact samples, as :meth:`from_mesh` builds).
    Compares and hashes by identity, so it can sit in a ``dynamics.Model``. Converted copies of the grid are
    kept per dtype and device of the points it is called on.
    """

    grid: Tensor = field(repr=False)
    origin: tuple[float, float, float]
    spacing: float
    bounding_radius: float
    lipschitz = math.sqrt(3.0)
    _grids: dict = field(default_factory=dict, init=False, repr=False)

    def __post_init__(self):
        if self.grid.dtype != _F64 or self.grid.dim() != 3 or min(self.grid.shape) < 2:
            raise ValueError(f"grid must be a float64 (nx, ny, nz) tensor, each >= 2, got "
                             f"{self.grid.dtype} {tuple(self.grid.shape)}")
        if not bool(torch.isfinite(self.grid).all()):
            raise ValueError("grid values must be finite")
        if not 0.0 < self.spacing < math.inf:
            raise ValueError(f"spacing must be positive and finite, got {self.spacing}")
        object.__setattr__(self, "origin", tuple(float(o) for o in self.origin))
        object.__setattr__(self, "spacing", float(self.spacing))
        object.__setattr__(self, "bounding_radius", float(self.bounding_radius))
        if len(self.origin) != 3:
            raise ValueError(f"origin must be 3 numbers (m), got {self.origin}")

    @classmethod
    def from_mesh(cls, mesh_or_path, resolution: float = 0.002, padding: float = 0.01) -> "MeshSDF":
        """Sample the exact signed distance of a watertight mesh (a ``trimesh.Trimesh`` or a file path, e.g.
        STL/OBJ, in m) on a grid of spacing ``resolution`` (m) over its bounds grown by ``padding`` (m) on every
        side (then centred: the node counts are rounded up). The mesh keeps its own coordinates.

        Raises ValueError for a missing or unreadable file, a mesh that is not watertight, or a non-positive
        resolution or padding. Cost: about ``nodes * (triangles near each node)`` point-triangle tests.
        """
        h, pad = float(resolution), float(padding)
        if not (0.0 < h < math.inf and 0.0 < pad < math.inf):
            raise ValueError(f"resolution and padding must be positive and finite (m), got {resolution}, {padding}")
        mesh = _load(mesh_or_path)
        vertices = torch.as_tensor(mesh.vertices, dtype=_F64)
        faces = torch.as_tensor(mesh.faces, dtype=torch.long)
        lo, hi = vertices.amin(0) - pad, vertices.amax(0) + pad
        counts = torch.ceil((hi - lo) / h - 1e-9).long() + 1
        origin = (lo + hi) / 2 - h * (counts - 1).to(_F64) / 2
        shape = tuple(counts.tolist())
        grid = _signed_distance_grid(vertices, faces, origin, h, shape)
        return cls(grid, tuple(origin.tolist()), h, float(vertices.norm(dim=-1).max()))

    @classmethod
    def from_spec(cls, path: str, resolution: float = 0.002, padding: float = 0.01) -> "MeshSDF":
        """``from_mesh`` with the scene's parameter names: ``sdf = "mesh"``, ``params = { path = ..., ... }``."""
        return cls.from_mesh(path, resolution=resolution, padding=padding)

    @property
    def error_bound(self) -> float:
        """Bound (m) of ``|phi - d|`` in the grid box, ``d`` the exact signed distance: ``sqrt(3)/2 * spacing``."""
        return math.sqrt(3.0) / 2 * self.spacing

    def _grid_like(self, points: Tensor) -> Tensor:
        key = (points.dtype, points.device)
        if key not in self._grids:
            self._grids[key] = self.grid.to(dtype=points.dtype, device=points.device)
        return self._grids[key]

    def __call__(self, points: Tensor) -> Tensor:
        """Signed distance ``(...)`` (m) of points ``(..., 3)`` (m, body frame)."""
        grid = self._grid_like(points)
        nx, ny, nz = grid.shape
        lo = points.new_tensor(self.origin)
        hi = lo + self.spacing * points.new_tensor([nx - 1, ny - 1, nz - 1])
        clamped = torch.minimum(torch.maximum(points, lo), hi)
        u = (clamped - lo) / self.spacing
        cell = torch.minimum(u.detach().floor(), points.new_tensor([nx - 2, ny - 2, nz - 2])).clamp_min(0)
        # a NaN coordinate reads cell 0 (its weight t is NaN, so is the distance): a NaN cast to an index is out of
        # range (compiled, it raised; unchecked, it would read outside the grid)
        cell = torch.nan_to_num(cell, nan=0.0)
        t = u - cell
        index = cell.long()
        flat = (index[..., 0] * ny + index[..., 1]) * nz + index[..., 2]
        offsets = (_OCTANTS.to(points.device) * torch.tensor([ny * nz, nz, 1], device=points.device)).sum(-1)
        corners = grid.reshape(-1)[flat.unsqueeze(-1) + offsets].unflatten(-1, (2, 2, 2))
        tx, ty, tz = t.unbind(-1)
        corners = torch.lerp(corners[..., 0, :, :], corners[..., 1, :, :], tx[..., None, None])
        corners = torch.lerp(corners[..., 0, :], corners[..., 1, :], ty[..., None])
        inside = torch.lerp(corners[..., 0], corners[..., 1], tz)
        outward = points - clamped
        beyond = safe_norm(torch.cat((outward, inside.unsqueeze(-1)), dim=-1))
        return torch.where((outward != 0).any(-1), beyond, inside)
