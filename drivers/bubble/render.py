"""Depth images of a Soft Bubble's membrane: the nominal ellipsoid, pushed in where an object presses into it.

The depth camera sits inside the bubble and sees the inside of its membrane. Each pixel's ray (pinhole model,
OpenCV axes: x right, y down, z forward) leaves the camera, which lies inside the nominal ellipsoid, and meets the
membrane where it exits the ellipsoid (closed form). Where the rigid object lies inside the nominal membrane along
that ray, the membrane is wrapped onto the object's surface, so the ray stops at the object: depth =
min(membrane exit, first object hit). Depths are along the optical axis (z), in metres. This is the simulated
sensor (sim_world renders it); a real bubble's depth camera gives the same image.

The object is its hydrosoft solid (``hydrosoft.geometry.sdf.Box`` for a cube or plate, ``Cylinder``), which
each ray enters and leaves in closed form (slabs and a quadric), so the rendering is exact to float64 rounding
before the float32 result (a few nm at the bubble's 3-6 cm depths). (Sphere tracing the same SDFs was tried
first: after 64 steps 0.07 % of the pixels of tilted cubes, rays grazing a face, were still short of the surface
by up to 8 mm, and a tilted cube took ~27 ms a frame against ~3 ms for the closed form.) Shapes without such a
solid (prisms, meshes) are not rendered.

Assumptions: the membrane wraps the object exactly (no bridging between the contact patch and the free membrane,
no membrane thickness); one ray per pixel centre (no anti-aliasing at the contact patch's rim). An object that
reaches the camera itself gives depth 0 (no return) on the rays that start inside it.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import torch

from hydrosoft.geometry import se3
from hydrosoft.geometry.sdf import Box, Cylinder

#: A unit quaternion's norm may differ from 1 by this much (float32 rounding in a message, as the bus allows).
QUATERNION_TOLERANCE = 1e-5
#: Stands in for a ray direction component that is exactly 0 (parallel to a slab): the slab's bounds move to
#: +-1e300, beyond any depth, with the signs of the ray's position in the slab.
PARALLEL_DIRECTION = 1e-300


@dataclass(frozen=True)
class PinholeDepth:
    """A depth camera's pinhole model: image ``width`` x ``height`` (px), focal lengths ``fx``, ``fy`` (px) and
    principal point ``cx``, ``cy`` (px, from the top-left pixel's centre). Raises ValueError when a size or focal
    length is not positive or a value is not finite."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        if not (isinstance(self.width, int) and isinstance(self.height, int) and self.width > 0 and self.height > 0):
            raise ValueError(f"PinholeDepth: width and height must be positive integers, got {self.width} x "
                             f"{self.height}")
        values = (self.fx, self.fy, self.cx, self.cy)
        if not all(math.isfinite(v) for v in values) or not (self.fx > 0 and self.fy > 0):
            raise ValueError(f"PinholeDepth: fx, fy must be positive and cx, cy finite, got fx={self.fx} "
                             f"fy={self.fy} cx={self.cx} cy={self.cy}")


def pixel_rays(camera: PinholeDepth) -> torch.Tensor:
    """Ray directions ``(H, W, 3)`` float64 in the camera frame with unit z: the point at depth ``z`` (m) on pixel
    ``(u, v)``'s ray is ``z * rays[v, u]``. Cached per camera: do not modify the result."""
    return _pixel_rays(camera)


@functools.lru_cache(maxsize=8)
def _pixel_rays(camera: PinholeDepth) -> torch.Tensor:
    u = torch.arange(camera.width, dtype=torch.float64)
    v = torch.arange(camera.height, dtype=torch.float64)
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    return torch.stack([(uu - camera.cx) / camera.fx, (vv - camera.cy) / camera.fy, torch.ones_like(uu)], dim=-1)


def as_pose(pose, name: str) -> torch.Tensor:
    """``pose`` (7 numbers ``[x, y, z, qw, qx, qy, qz]``, m and a unit quaternion) as a float64 tensor ``(7,)``
    with its quaternion normalised. Raises ValueError naming ``name`` for another shape, a non-finite value or a
    quaternion further than ``QUATERNION_TOLERANCE`` from unit length."""
    array = np.array(pose, dtype=np.float64)  # a copy: the quaternion is normalised in place
    if array.shape != (7,) or not np.isfinite(array).all():
        raise ValueError(f"{name}: a pose is 7 finite numbers [x, y, z, qw, qx, qy, qz], got {array.tolist()}")
    norm = float(np.linalg.norm(array[3:]))
    if abs(norm - 1.0) > QUATERNION_TOLERANCE:
        raise ValueError(f"{name}: quaternion {array[3:].tolist()} has norm {norm:.9f}, not 1")
    array[3:] /= norm
    return torch.from_numpy(array)


def as_radii(radii) -> tuple[float, float, float]:
    """The membrane's ellipsoid radii ``(a, b, c)`` (m) as floats. Raises ValueError unless 3 positive finite
    numbers."""
    values = tuple(float(r) for r in radii)
    if len(values) != 3 or not all(0.0 < r < math.inf for r in values):
        raise ValueError(f"membrane radii must be 3 positive finite lengths (m), got {radii!r}")
    return values


def membrane_exit_depth(origin: torch.Tensor, rays: torch.Tensor, radii: tuple[float, float, float]) -> torch.Tensor:
    """Ray parameter ``(...)`` at which rays ``origin + t * rays`` (``origin (3,)`` strictly inside the ellipsoid
    of ``radii`` (m), ``rays (..., 3)``, its frame) leave it: the larger root of ``|(o + t d) / r|^2 = 1``."""
    r = origin.new_tensor(radii)
    o, d = origin / r, rays / r
    a = d.square().sum(-1)
    half_b = (o * d).sum(-1)
    c = o.square().sum() - 1.0
    return (-half_b + torch.sqrt(half_b * half_b - a * c)) / a


def _camera_in_membrane(camera: PinholeDepth, radii, T_bubble_camera) -> tuple[torch.Tensor, torch.Tensor,
                                                                              torch.Tensor]:
    """The checked camera pose ``(7,)``, its pixel rays ``(H*W, 3)`` in the bubble frame and their membrane exit
    depth ``(H*W,)`` (m along the optical axis). Cached per camera, membrane and pose (``_membrane_view``): a bubble's
    depth camera renders every frame from the same ones, and they were 60 % of a frame's CPU; do not modify them."""
    pose = as_pose(T_bubble_camera, "T_bubble_camera")
    return _membrane_view(camera, as_radii(radii), tuple(pose.tolist()))


@functools.lru_cache(maxsize=8)
def _membrane_view(camera: PinholeDepth, radii: tuple[float, float, float],
                   T_bubble_camera: tuple[float, ...]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    pose = torch.tensor(T_bubble_camera, dtype=torch.float64)
    if float((pose[:3] / pose.new_tensor(radii)).square().sum()) >= 1.0:
        raise ValueError(f"T_bubble_camera: the camera at {pose[:3].tolist()} m is not inside the membrane of "
                         f"radii {radii} m")
    rays = pixel_rays(camera).reshape(-1, 3) @ se3.quat_to_matrix(pose[3:]).T
    return pose, rays, membrane_exit_depth(pose[:3], rays, radii)


def reference_depth(camera: PinholeDepth, radii, T_bubble_camera) -> np.ndarray:
    """The undeformed membrane's depth image ``(H, W)`` float32 (m along the optical axis).

    camera: the pinhole model. radii: ``(3,)`` the nominal membrane ellipsoid's radii (m, bubble frame).
    T_bubble_camera: ``(7,)`` the camera's pose in the bubble frame (inside the membrane). Raises ValueError for
    bad radii or pose."""
    _, _, exit_depth = _camera_in_membrane(camera, radii, T_bubble_camera)
    return exit_depth.reshape(camera.height, camera.width).float().numpy()


def render_depth(camera: PinholeDepth, radii, T_bubble_camera, object_sdf: Box | Cylinder,
                 T_bubble_object) -> np.ndarray:
    """The membrane's depth image ``(H, W)`` float32 (m along the optical axis) with an object pressed into it.

    camera: the pinhole model. radii: ``(3,)`` the nominal membrane ellipsoid's radii (m, bubble frame).
    T_bubble_camera: ``(7,)`` the camera's pose in the bubble frame (inside the membrane). object_sdf: the object's
    solid, a ``hydrosoft.geometry.sdf.Box`` or ``Cylinder`` (object frame). T_bubble_object: ``(7,)`` the object's
    pose in the bubble frame. Each pixel holds min(membrane exit, first object hit) (module docstring). Raises
    ValueError for bad radii or poses, TypeError for another solid."""
    camera_pose, rays, exit_depth = _camera_in_membrane(camera, radii, T_bubble_camera)
    T_object_bubble = se3.inverse(as_pose(T_bubble_object, "T_bubble_object"))
    origin = se3.transform_points(T_object_bubble, camera_pose[:3].unsqueeze(0))[0]
    directions = rays @ se3.quat_to_matrix(T_object_bubble[3:]).T
    enter, leave = solid_interval(object_sdf, origin, directions)
    hit = (enter <= leave) & (leave > 0) & (enter < exit_depth)
    depth = torch.where(hit, enter.clamp_min(0.0), exit_depth)
    return depth.reshape(camera.height, camera.width).float().numpy()


def solid_interval(solid: Box | Cylinder, origin: torch.Tensor, directions: torch.Tensor) -> tuple[torch.Tensor,
                                                                                                   torch.Tensor]:
    """Where rays ``origin (3,) + t * directions (P, 3)`` (object frame, m) enter and leave ``solid``: ray
    parameters ``(P,)`` each; a ray misses it where ``enter > leave``. The solid is the intersection of slabs
    ``|x_i| <= h_i`` (a ``Box``) or of the slab ``|z| <= half_length`` and the infinite cylinder
    ``x^2 + y^2 <= radius^2`` (a ``Cylinder``); each part is entered and left in closed form. Raises TypeError for
    another solid."""
    if isinstance(solid, Box):
        return _slabs(origin, directions, origin.new_tensor(solid.half_extents))
    if isinstance(solid, Cylinder):
        slab_enter, slab_leave = _slabs(origin[2:], directions[:, 2:], origin.new_tensor([solid.half_length]))
        tube_enter, tube_leave = _tube(origin[:2], directions[:, :2], solid.radius)
        return torch.maximum(tube_enter, slab_enter), torch.minimum(tube_leave, slab_leave)
    raise TypeError(f"render_depth renders Box and Cylinder objects (hydrosoft.geometry.sdf), not "
                    f"{type(solid).__name__}")


def _slabs(origin: torch.Tensor, directions: torch.Tensor, half_widths: torch.Tensor) -> tuple[torch.Tensor,
                                                                                             torch.Tensor]:
    """Ray parameters ``(P,)`` where rays ``origin (k,) + t * directions (P, k)`` enter and leave the
    intersection of the slabs ``|x_i| <= half_widths[i]`` (k of them)."""
    directions = torch.where(directions == 0, PARALLEL_DIRECTION, directions)
    lower = (-half_widths - origin) / directions
    upper = (half_widths - origin) / directions
    return torch.minimum(lower, upper).amax(-1), torch.maximum(lower, upper).amin(-1)


def _tube(origin: torch.Tensor, directions: torch.Tensor, radius: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Ray parameters ``(P,)`` where rays ``origin (2,) + t * directions (P, 2)`` (the components across the
    axis) enter and leave the infinite cylinder ``x^2 + y^2 <= radius^2``; a ray along the axis is inside it
    everywhere or nowhere."""
    a = directions.square().sum(-1)
    half_b = directions @ origin
    c = float(origin.square().sum()) - radius**2
    along_axis = a == 0
    a = torch.where(along_axis, 1.0, a)
    discriminant = half_b * half_b - a * c
    root = torch.sqrt(discriminant.clamp_min(0.0))
    crosses = ~along_axis & (discriminant > 0)
    inside = along_axis & (c <= 0)
    enter = torch.where(crosses, (-half_b - root) / a, torch.where(inside, -math.inf, math.inf))
    leave = torch.where(crosses, (-half_b + root) / a, torch.where(inside, math.inf, -math.inf))
    return enter, leave


def to_counts(depth_m: np.ndarray, scale_m: float) -> np.ndarray:
    """A depth image ``(H, W)`` in metres as uint16 counts of ``scale_m`` (m per count), rounded; 0 = no return
    (NaN, <= 0 or beyond 65535 counts). Raises ValueError unless ``scale_m`` is positive and finite."""
    if not (math.isfinite(scale_m) and scale_m > 0):
        raise ValueError(f"to_counts: scale_m must be a positive length (m per count), got {scale_m!r}")
    with np.errstate(invalid="ignore"):
        counts = np.round(np.nan_to_num(np.asarray(depth_m, dtype=np.float64), nan=0.0, posinf=0.0) / scale_m)
    return np.where((counts > 0) & (counts <= np.iinfo(np.uint16).max), counts, 0).astype(np.uint16)
