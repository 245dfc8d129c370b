"""From a Soft Bubble's depth image to what the planner needs: per object point, its depth inside the membrane.

``membrane_deformation`` is the image the bubble camera publishes: the reference (undeformed) membrane's depth
minus the measured depth, along the optical axis (m; positive where the membrane is pushed towards the camera,
NaN where either image has no return).

``penetration_from_deformation`` reads it at the object's surface points, placed in the bubble frame by the sensed
object and arm poses. A point counts as touching when, where it projects into the image (bilinear interpolation
of the four pixels around it; a pixel without return makes the point unobserved):

- the membrane is displaced there by more than ``contact_threshold_m`` (above the depth noise), and
- the observed membrane lies at the point's own depth within ``depth_tolerance_m`` (so a point hidden behind
  the touching face, or one the pose estimate puts off the membrane, does not count).

A touching point's penetration is the depth inside the nominal ellipsoid (``-sdf``, m) of the observed membrane
point on that point's ray; every other point's is 0. This is ``hydrosoft.tactile.TactileObservation.penetration``
measured through the camera instead of from geometry (``hydrosoft.tactile.membrane_penetration``).

Accuracy, for the pushing scene's cube pressed 5 mm into the membrane, seen by a 160 x 120 camera with
fx = fy = 40 px and rendered with ``render.render_depth`` (``tests/drivers/bubble/test_bubble_deformation.py``):
from the uint16 image (0.1 mm counts) every touching point is within 0.04 mm of the geometric truth, points
shallower than ``contact_threshold_m`` read 0, and the net normal force ``sum E A d`` is within 0.5 %; with sim's
0.2 mm Gaussian depth noise, within 0.5 mm per point and 2 % in force (20 noise seeds), with no false contact.

Limits: only what the camera sees counts. Points outside its field of view read 0: config's default camera
(fx = fy = 90 px for 160 x 120, 83 x 67 deg) misses the rim of the contact patch, 26 %, 38 % and 27 % of the
normal force at the pushing, rotation and rolling scenes' own poses (33 % per bubble in in_hand); with
fx = fy = 40 px the loss is 0.7 %, 3.4 %, 1.3 % (and 1.7 %). Side faces hidden behind the pressed face read 0
even where they lie inside the nominal membrane (1.7 mm deep 2.5 mm below the rim in the rotation scene's 7 mm
press: most of its 3.4 %), and points of them within ``depth_tolerance_m`` of the rim take the rim's penetration.
"""

from __future__ import annotations

import functools

import numpy as np
import torch

from hydrosoft.drivers.bubble.render import PinholeDepth, as_pose, as_radii, reference_depth
from hydrosoft.geometry import se3
from hydrosoft.geometry.sdf import Ellipsoid

#: Membrane displacement below this is depth noise, not contact, m (about 2.5 sigma of sim's 0.2 mm noise).
CONTACT_THRESHOLD_M = 5e-4
#: A point touches only where the observed membrane lies within this of its depth along the optical axis, m.
DEPTH_TOLERANCE_M = 2e-3
#: Points closer to the camera plane than this, m, are not projected (they are behind it or at its centre).
MIN_POINT_DEPTH_M = 1e-6


def membrane_deformation(depth_m: np.ndarray, reference_m: np.ndarray) -> np.ndarray:
    """``reference - depth`` ``(H, W)`` float32 (m along the optical axis; positive = pushed towards the camera;
    NaN where either holds no return: NaN or <= 0). Both ``(H, W)`` in m. Raises ValueError when the shapes
    differ or are not 2-D."""
    depth = np.asarray(depth_m, dtype=np.float32)
    reference = np.asarray(reference_m, dtype=np.float32)
    if depth.ndim != 2 or depth.shape != reference.shape:
        raise ValueError(f"membrane_deformation: depth {depth.shape} and reference {reference.shape} must be the "
                         "same (H, W) image size")
    with np.errstate(invalid="ignore"):
        returned = (depth > 0) & (reference > 0)
        return np.where(returned, reference - depth, np.float32(np.nan)).astype(np.float32)


def penetration_from_deformation(deformation: np.ndarray, camera: PinholeDepth, radii, T_bubble_camera,
                                 points_bubble: np.ndarray, *, reference_m: np.ndarray | None = None,
                                 contact_threshold_m: float = CONTACT_THRESHOLD_M,
                                 depth_tolerance_m: float = DEPTH_TOLERANCE_M) -> np.ndarray:
    """Depth ``(N,)`` float64 (m, >= 0) of each object point inside the nominal membrane, as the deformation image
    shows it (module docstring); 0 where a point is not seen touching.

    Args:
        deformation: ``(H, W)`` m, ``membrane_deformation`` of the camera's image (NaN = no return).
        camera: the depth camera's pinhole model (``H, W`` = its ``height, width``).
        radii: ``(3,)`` the nominal membrane ellipsoid's radii, m, bubble frame.
        T_bubble_camera: ``(7,)`` the camera's pose in the bubble frame.
        points_bubble: ``(N, 3)`` the object's surface points in the bubble frame, m.
        reference_m: ``(H, W)`` the undeformed membrane's depth image the deformation was taken against, m;
            None: the nominal membrane's (``render.reference_depth``, what sim renders).
        contact_threshold_m, depth_tolerance_m: the contact tests' limits, m.

    Raises:
        ValueError: for images of another size than the camera's, points not ``(N, 3)`` finite, bad radii or pose.
    """
    radii = as_radii(radii)
    camera_pose = as_pose(T_bubble_camera, "T_bubble_camera")
    shape = (camera.height, camera.width)
    deformation = torch.as_tensor(np.asarray(deformation, dtype=np.float64))
    if deformation.shape != shape:
        raise ValueError(f"penetration_from_deformation: deformation image {tuple(deformation.shape)} is not the "
                         f"camera's {shape}")
    if reference_m is None:
        reference = _nominal_reference(camera, radii, tuple(camera_pose.tolist()))
    else:
        reference = torch.as_tensor(np.asarray(reference_m, dtype=np.float64))
        if reference.shape != shape:
            raise ValueError(f"penetration_from_deformation: reference image {tuple(reference.shape)} is not the "
                             f"camera's {shape}")
    points = np.asarray(points_bubble, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or not np.isfinite(points).all():
        raise ValueError(f"penetration_from_deformation: points_bubble must be finite (N, 3), got {points.shape}")
    in_camera = se3.transform_points(se3.inverse(camera_pose), torch.from_numpy(points))
    z = in_camera[:, 2]
    ahead = z > MIN_POINT_DEPTH_M
    ray = in_camera / torch.where(ahead, z, 1.0).unsqueeze(-1)
    u = camera.fx * ray[:, 0] + camera.cx
    v = camera.fy * ray[:, 1] + camera.cy
    shown = _bilinear(deformation, u, v)
    observed_z = _bilinear(reference, u, v) - shown
    touching = (ahead & torch.isfinite(observed_z) & (shown > contact_threshold_m)
                & ((observed_z - z).abs() <= depth_tolerance_m))
    surface = se3.transform_points(camera_pose, torch.nan_to_num(observed_z).unsqueeze(-1) * ray)
    depth_inside = torch.relu(-Ellipsoid(radii)(surface))
    return torch.where(touching, depth_inside, torch.zeros_like(depth_inside)).numpy()


def _bilinear(image: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """``image (H, W)`` at continuous pixel coordinates ``u, v (N,)`` (px, pixel centres at integers), bilinear
    over the four surrounding pixels; NaN outside the image or where one of them is NaN."""
    height, width = image.shape
    inside = (u >= 0) & (u <= width - 1) & (v >= 0) & (v <= height - 1)
    u, v = u.clamp(0, width - 1), v.clamp(0, height - 1)
    u0, v0 = u.floor().long(), v.floor().long()
    u1, v1 = (u0 + 1).clamp_max(width - 1), (v0 + 1).clamp_max(height - 1)
    a, b = u - u0, v - v0
    top = image[v0, u0] * (1 - a) + image[v0, u1] * a
    bottom = image[v1, u0] * (1 - a) + image[v1, u1] * a
    value = top * (1 - b) + bottom * b
    return torch.where(inside, value, torch.full_like(value, float("nan")))


@functools.lru_cache(maxsize=8)
def _nominal_reference(camera: PinholeDepth, radii: tuple[float, float, float],
                       T_bubble_camera: tuple[float, ...]) -> torch.Tensor:
    """The nominal membrane's depth image ``(H, W)`` float64 (m), cached per camera, membrane and pose."""
    return torch.from_numpy(reference_depth(camera, radii, T_bubble_camera).astype(np.float64))
