"""Depth images of the Soft Bubble's membrane (``drivers.bubble.render``): the nominal ellipsoid, the object pushed
into it (checked against the object's own signed distance), the frame conventions, the uint16 encoding, the
errors and the time of a 160 x 120 frame."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
import torch

from hydrosoft.drivers.bubble.render import (
    PinholeDepth,
    _membrane_view,
    pixel_rays,
    reference_depth,
    render_depth,
    to_counts,
)
from hydrosoft.geometry import se3
from hydrosoft.geometry.sdf import Box, Cylinder, Sphere

RADII = (0.06, 0.045, 0.03)  # the tasks' bubble, m
LOOK_DOWN = (0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0)  # depth.axis "-z": the bubble frame turned 180 deg about x
LOOK_UP = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)  # depth.axis "+z"
CAMERA = PinholeDepth(160, 120, 40.0, 40.0, 79.5, 59.5)  # wide enough to see the whole contact patch
CENTRED = PinholeDepth(41, 31, 20.0, 20.0, 20.0, 15.0)  # pixel (20, 15) looks along the optical axis
CUBE = Box((0.025, 0.025, 0.025))
ROLLER = Cylinder(0.025, 0.05)
PRESSED_5MM = (0.0, 0.0, -0.05, 1.0, 0.0, 0.0, 0.0)  # the cube's top face 5 mm into the membrane's bottom


def points_in_bubble(camera: PinholeDepth, depth: np.ndarray, T_bubble_camera) -> torch.Tensor:
    """The pixels' points ``(H*W, 3)`` in the bubble frame (float64) of a depth image ``(H, W)``."""
    rays = pixel_rays(camera).reshape(-1, 3) * torch.from_numpy(depth.astype(np.float64)).reshape(-1, 1)
    return se3.transform_points(torch.tensor(T_bubble_camera, dtype=torch.float64), rays)


def random_pose(rng: np.random.Generator, depth_m: float) -> np.ndarray:
    """An object pose ``(7,)`` in the bubble frame ``depth_m`` below its centre: tilted up to 0.7 rad, shifted up
    to 1 cm."""
    q = se3.so3_exp(torch.tensor(rng.uniform(-0.7, 0.7, 3))).numpy()
    return np.concatenate([[rng.uniform(-0.01, 0.01), rng.uniform(-0.01, 0.01), -depth_m], q])


def pressing_pose(rng: np.random.Generator, solid, depths_m: tuple[float, float]) -> np.ndarray:
    """A ``random_pose`` between ``depths_m`` below the bubble's centre that keeps the object 5 mm or more clear of
    the camera (an object around the camera blinds it; that case has its own test)."""
    while True:
        pose = random_pose(rng, rng.uniform(*depths_m))
        camera = se3.transform_points(se3.inverse(torch.from_numpy(pose)), torch.zeros(1, 3, dtype=torch.float64))
        if solid(camera).item() > 0.005:
            return pose


# --- the nominal membrane ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("T_bubble_camera", [LOOK_DOWN, LOOK_UP])
def test_the_reference_image_lies_on_the_nominal_ellipsoid(T_bubble_camera):
    depth = reference_depth(CAMERA, RADII, T_bubble_camera)
    assert depth.shape == (120, 160) and depth.dtype == np.float32
    on_membrane = (points_in_bubble(CAMERA, depth, T_bubble_camera) / torch.tensor(RADII)).square().sum(-1)
    np.testing.assert_allclose(on_membrane.numpy(), 1.0, atol=1e-6)
    assert reference_depth(CENTRED, RADII, T_bubble_camera)[15, 20] == pytest.approx(0.03, abs=1e-9)


def test_the_reference_of_an_offset_camera_is_measured_from_the_camera():
    offset = (0.0, 0.0, 0.01, 0.0, 1.0, 0.0, 0.0)  # 1 cm up the bubble's z axis, looking down
    assert reference_depth(CENTRED, RADII, offset)[15, 20] == pytest.approx(0.04, abs=1e-9)


# --- the object pressed in ---------------------------------------------------------------------------------------


def test_a_cube_pressed_5mm_flattens_the_membrane_to_its_top_face_and_leaves_the_rest():
    reference = reference_depth(CAMERA, RADII, LOOK_DOWN)
    depth = render_depth(CAMERA, RADII, LOOK_DOWN, CUBE, PRESSED_5MM)
    points = points_in_bubble(CAMERA, depth, LOOK_DOWN).reshape(120, 160, 3).numpy()
    on_top = (np.abs(points[..., 0]) < 0.025) & (np.abs(points[..., 1]) < 0.025) & (reference > 0.025)
    assert on_top.sum() > 3000  # the flat patch covers a good part of the image
    np.testing.assert_allclose(depth[on_top], 0.025, atol=1e-7)  # the top face: 2.5 cm along the optical axis
    np.testing.assert_array_equal(depth[~on_top], reference[~on_top])
    assert (depth <= reference).all()
    np.testing.assert_allclose(reference[59:61, 79:81] - depth[59:61, 79:81], 0.005, atol=1e-5)  # at the centre


@pytest.mark.parametrize("solid, depths_m", [(CUBE, (0.045, 0.056)), (ROLLER, (0.04, 0.05)),
                                             (Box((0.05, 0.04, 0.0025)), (0.022, 0.03))],
                         ids=["cube", "cylinder", "plate"])
def test_the_rendered_membrane_stops_on_the_objects_surface_and_never_passes_through_it(solid, depths_m):
    """Against the object's exact signed distance: every pixel that is not the nominal membrane sees a surface
    point of the object, and nothing of the object lies in front of any pixel's depth."""
    rng = np.random.default_rng(7)
    reference = torch.from_numpy(reference_depth(CAMERA, RADII, LOOK_DOWN).astype(np.float64)).reshape(-1)
    rays = points_in_bubble(CAMERA, np.ones((120, 160), np.float32), LOOK_DOWN)
    fractions = torch.linspace(0.0, 1.0, 41, dtype=torch.float64)[:-1]
    pressed = 0
    for _ in range(4):
        pose = pressing_pose(rng, solid, depths_m)
        depth = torch.from_numpy(render_depth(CAMERA, RADII, LOOK_DOWN, solid, pose).astype(np.float64)).reshape(-1)
        to_object = se3.inverse(torch.from_numpy(pose))
        touched = depth < reference - 1e-7
        seen = solid(se3.transform_points(to_object, depth.unsqueeze(-1) * rays))
        assert seen[touched].abs().max() < 1e-6  # on the surface
        assert (seen[~touched] >= -1e-6).all()  # where the membrane is nominal, the object is not in front of it
        before = (fractions.view(-1, 1, 1) * depth.view(1, -1, 1) * rays).reshape(-1, 3)
        assert solid(se3.transform_points(to_object, before)).min() > -1e-6
        pressed += int(touched.sum())
    assert pressed > 8000  # the poses do press in


def test_a_cylinder_standing_on_the_optical_axis_is_seen_along_its_axis():
    standing = (0.0, 0.0, -0.07, 1.0, 0.0, 0.0, 0.0)  # axis along the bubble's z: the cap 2 cm from the camera
    depth = render_depth(CENTRED, RADII, LOOK_DOWN, Cylinder(0.01, 0.05), standing)
    assert depth[15, 20] == pytest.approx(0.02, abs=1e-9)
    assert (depth < reference_depth(CENTRED, RADII, LOOK_DOWN)).sum() > 1


def test_the_image_follows_the_camera_axes_an_object_at_bubble_plus_x_is_right_plus_y_is_up_in_the_image():
    """depth.axis "-z": camera x = bubble x, camera y = -bubble y (OpenCV: x right, y down)."""
    moved = (0.015, 0.01, -0.05, 1.0, 0.0, 0.0, 0.0)
    pushed = render_depth(CAMERA, RADII, LOOK_DOWN, CUBE, moved) < reference_depth(CAMERA, RADII, LOOK_DOWN) - 1e-6
    rows, cols = np.nonzero(pushed)
    assert cols.mean() > CAMERA.cx + 5 and rows.mean() < CAMERA.cy - 5


def test_an_object_clear_of_the_membrane_leaves_the_reference_and_one_around_the_camera_blinds_it():
    clear = (0.0, 0.0, -0.0551, 1.0, 0.0, 0.0, 0.0)  # top face 0.1 mm below the membrane's lowest point
    np.testing.assert_array_equal(render_depth(CAMERA, RADII, LOOK_DOWN, CUBE, clear),
                                  reference_depth(CAMERA, RADII, LOOK_DOWN))
    around = (0.0, 0.0, -0.02, 1.0, 0.0, 0.0, 0.0)  # the cube contains the camera
    depth = render_depth(CAMERA, RADII, LOOK_DOWN, CUBE, around)
    assert (depth == 0).all() and (to_counts(depth, 1e-4) == 0).all()  # no return


def test_a_160x120_frame_renders_within_30ms_on_one_core():
    rng = np.random.default_rng(3)
    poses = [random_pose(rng, 0.05) for _ in range(5)]
    render_depth(CAMERA, RADII, LOOK_DOWN, CUBE, poses[0])
    times_s = []
    for pose in poses:
        tic_s = time.perf_counter()
        render_depth(CAMERA, RADII, LOOK_DOWN, CUBE, pose)
        times_s.append(time.perf_counter() - tic_s)
    assert torch.get_num_threads() == 1 and sorted(times_s)[2] < 0.030, times_s


def test_frames_of_one_camera_reuse_its_membrane_view_and_render_what_a_fresh_one_renders():
    rng = np.random.default_rng(5)
    poses = [random_pose(rng, 0.05) for _ in range(3)]
    camera = PinholeDepth(64, 48, 16.0, 16.0, 31.5, 23.5)  # a camera no other test renders with
    _membrane_view.cache_clear()
    frames = [render_depth(camera, RADII, LOOK_DOWN, CUBE, pose) for pose in poses]
    assert _membrane_view.cache_info().misses == 1  # the rays and membrane exit depths: once, not per frame
    for pose, frame in zip(poses, frames):
        _membrane_view.cache_clear()
        np.testing.assert_array_equal(frame, render_depth(camera, RADII, LOOK_DOWN, CUBE, pose))


# --- encoding and errors ---------------------------------------------------------------------------------------


def test_to_counts_rounds_to_the_depth_unit_and_marks_no_return_as_zero():
    depth = np.array([[0.02504, 0.02506, np.nan], [0.0, -0.01, 7.0]], dtype=np.float32)
    np.testing.assert_array_equal(to_counts(depth, 1e-4), [[250, 251, 0], [0, 0, 0]])  # 7 m: beyond 65535 counts
    assert to_counts(depth, 1e-4).dtype == np.uint16
    with pytest.raises(ValueError, match="scale_m"):
        to_counts(depth, 0.0)


@pytest.mark.parametrize("pose, text", [
    ((0.0, 0.0, 0.0, 0.9, 0.0, 0.0, 0.0), "norm"),
    ((0.0, 0.0, math.nan, 1.0, 0.0, 0.0, 0.0), "7 finite numbers"),
    ((0.0, 0.0, 0.0, 1.0), "7 finite numbers"),
    ((0.0, 0.0, 0.05, 1.0, 0.0, 0.0, 0.0), "not inside the membrane"),
])
def test_bad_camera_poses_are_refused_with_their_reason(pose, text):
    with pytest.raises(ValueError, match=text):
        render_depth(CAMERA, RADII, pose, CUBE, PRESSED_5MM)


def test_bad_radii_intrinsics_and_solids_are_refused():
    with pytest.raises(ValueError, match="radii"):
        reference_depth(CAMERA, (0.06, -0.045, 0.03), LOOK_DOWN)
    with pytest.raises(ValueError, match="fx, fy must be positive"):
        PinholeDepth(160, 120, 0.0, 40.0, 79.5, 59.5)
    with pytest.raises(ValueError, match="positive integers"):
        PinholeDepth(0, 120, 40.0, 40.0, 79.5, 59.5)
    with pytest.raises(TypeError, match="Box and Cylinder"):
        render_depth(CAMERA, RADII, LOOK_DOWN, Sphere(0.02), PRESSED_5MM)
