"""From depth images to per-point penetration (``drivers.bubble.deformation``), checked against the geometric truth
``hydrosoft.tactile.membrane_penetration`` on the pushing scene: its cube pressed 5 mm into the bubble, rendered
with ``render_depth`` and encoded as the camera's uint16 counts, with and without sim's depth noise."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hydrosoft.drivers.bubble.deformation import (
    CONTACT_THRESHOLD_M,
    membrane_deformation,
    penetration_from_deformation,
)
from hydrosoft.drivers.bubble.render import PinholeDepth, reference_depth, render_depth, to_counts
from hydrosoft.geometry import se3, surface
from hydrosoft.geometry.sdf import Box, Ellipsoid
from hydrosoft.tactile import membrane_penetration
from hydrosoft.tasks import make_task

SCENE = make_task("pushing").scene
BUBBLE = next(body for body in SCENE.bodies if body.name == "bubble")
RADII = tuple(BUBBLE.params["radii"])
E_PA_M = BUBBLE.E
SIDE_M = SCENE.object.params["side"]
CUBE_POINTS = surface.cube(SIDE_M, SCENE.object.spacing)  # the planner's kind of points, 5 mm apart
LOOK_DOWN = (0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0)  # depth.axis "-z"
WIDE = PinholeDepth(160, 120, 40.0, 40.0, 79.5, 59.5)  # sees the whole contact patch of a 5-7 mm press
NARROW = PinholeDepth(160, 120, 90.0, 90.0, 79.5, 59.5)  # config.DepthConfig's default: 83 x 67 deg
DEPTH_SCALE_M = 1e-4
NOISE_M = 2e-4  # sim.depth_noise_m's default
#: The scene presses the membrane 5 mm into the cube's top face; this pose puts the top face 0.03 mm off a count
#: boundary and the cube 3 mm and 2 mm off the bubble's axis, so rounding and asymmetry both show.
PRESSED = np.array([0.003, -0.002, -0.05003, 1.0, 0.0, 0.0, 0.0])


def scene_pose_in_bubble() -> np.ndarray:
    """T_bubble_object ``(7,)`` of the pushing scene as written."""
    return se3.compose(se3.inverse(torch.tensor(BUBBLE.pose, dtype=torch.float64)),
                       torch.tensor(SCENE.object.pose, dtype=torch.float64)).numpy()


def truth(T_bubble_object: np.ndarray) -> np.ndarray:
    """The geometric penetration ``(N,)`` (m) of the cube's points in the nominal membrane."""
    pose = torch.from_numpy(T_bubble_object).unsqueeze(0)
    identity = torch.tensor([[[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]]], dtype=torch.float64)
    return membrane_penetration([Ellipsoid(RADII)], CUBE_POINTS.points.double(), pose, identity)[0, 0].numpy()


def points_in_bubble(T_bubble_object: np.ndarray) -> np.ndarray:
    return se3.transform_points(torch.from_numpy(T_bubble_object), CUBE_POINTS.points.double()).numpy()


def sensed_deformation(camera: PinholeDepth, T_bubble_object: np.ndarray, noise_m: float = 0.0,
                       seed: int = 0) -> np.ndarray:
    """What the bubble camera service publishes for the cube at ``T_bubble_object``: the rendered image, with
    Gaussian noise, as uint16 counts, back in metres, against the nominal reference."""
    depth = render_depth(camera, RADII, LOOK_DOWN, Box((SIDE_M / 2,) * 3), T_bubble_object)
    depth = depth + np.random.default_rng(seed).normal(0.0, noise_m, depth.shape).astype(np.float32)
    measured = to_counts(depth, DEPTH_SCALE_M).astype(np.float32) * np.float32(DEPTH_SCALE_M)
    return membrane_deformation(measured, reference_depth(camera, RADII, LOOK_DOWN))


def normal_force_n(penetration: np.ndarray) -> float:
    """Net normal force ``sum E A d`` (N) of a penetration ``(N,)`` (m): the estimator's eq. 22-24 magnitude."""
    return float((E_PA_M * CUBE_POINTS.areas.double().numpy() * penetration).sum())


# --- the deformation image ---------------------------------------------------------------------------------------


def test_the_deformation_is_the_reference_minus_the_depth_and_nan_without_return():
    reference = np.full((2, 3), 0.03, np.float32)
    depth = np.array([[0.03, 0.025, 0.0], [np.nan, 0.031, 0.0299]], np.float32)
    deformation = membrane_deformation(depth, reference)
    assert deformation.dtype == np.float32
    np.testing.assert_allclose(deformation, [[0.0, 0.005, np.nan], [np.nan, -0.001, 0.0001]], atol=1e-7)
    with pytest.raises(ValueError, match="same"):
        membrane_deformation(depth, reference[:, :2])


def test_the_scene_presses_the_cube_5mm_into_the_membrane_as_the_tests_do():
    np.testing.assert_allclose(scene_pose_in_bubble(), [0.0, 0.0, -0.05, 1.0, 0.0, 0.0, 0.0], atol=1e-9)
    assert np.linalg.norm(PRESSED[:3] - scene_pose_in_bubble()[:3]) < 0.004


# --- penetration against the geometric truth ---------------------------------------------------------------------


def test_a_cube_pressed_5mm_reads_as_the_geometric_penetration_on_every_touching_point():
    expected = truth(PRESSED)
    measured = penetration_from_deformation(sensed_deformation(WIDE, PRESSED), WIDE, RADII, LOOK_DOWN,
                                            points_in_bubble(PRESSED))
    assert measured.shape == expected.shape and (measured >= 0).all()
    seen = expected > CONTACT_THRESHOLD_M + 2 * DEPTH_SCALE_M  # clearly deeper than the noise threshold
    assert seen.sum() > 60
    np.testing.assert_allclose(measured[seen], expected[seen], atol=1e-4)  # within one depth count
    assert (measured[expected == 0] == 0).all()  # the bottom and side faces, hidden or clear of the membrane
    assert normal_force_n(measured) == pytest.approx(normal_force_n(expected), rel=0.03)


def test_with_sims_depth_noise_every_touching_point_is_within_a_millimetre_and_the_force_within_10_percent():
    expected = truth(PRESSED)
    points = points_in_bubble(PRESSED)
    for seed in range(3):
        measured = penetration_from_deformation(sensed_deformation(WIDE, PRESSED, NOISE_M, seed), WIDE, RADII,
                                                LOOK_DOWN, points)
        touching = measured > 0
        assert (expected[touching] > 0).all()  # no false contact
        assert np.abs(measured - expected)[touching].max() < 1e-3
        assert (touching[expected > 1e-3]).all()  # nothing 1 mm deep is missed
        assert normal_force_n(measured) == pytest.approx(normal_force_n(expected), rel=0.10)


def test_a_cube_clear_of_the_membrane_reads_zero_through_the_noise():
    clear = PRESSED + np.array([0.0, 0.0, -0.006, 0.0, 0.0, 0.0, 0.0])  # top face 1 mm below the membrane
    assert truth(clear).max() == 0
    for seed in range(3):
        deformation = sensed_deformation(WIDE, clear, NOISE_M, seed)
        assert np.nanmax(np.abs(deformation)) > CONTACT_THRESHOLD_M  # some pixels' noise passes the threshold
        measured = penetration_from_deformation(deformation, WIDE, RADII, LOOK_DOWN, points_in_bubble(clear))
        assert (measured == 0).all()


def test_the_penetration_is_measured_not_taken_from_the_pose_estimate():
    """Points the pose estimate puts 1 mm farther from the camera still read the membrane the camera sees along
    their rays: within 0.4 mm of the true penetration (their rays meet the top face up to 4 % nearer the
    centre), not the estimate's 1 mm less."""
    deformation = sensed_deformation(WIDE, PRESSED)
    estimate = PRESSED + np.array([0.0, 0.0, -0.001, 0.0, 0.0, 0.0, 0.0])
    measured = penetration_from_deformation(deformation, WIDE, RADII, LOOK_DOWN, points_in_bubble(estimate))
    on_top = CUBE_POINTS.normals[:, 2].numpy() > 0.5
    deep = on_top & (truth(PRESSED) > 2e-3)
    np.testing.assert_allclose(measured[deep], truth(PRESSED)[deep], atol=4e-4)
    assert (truth(estimate)[deep] < measured[deep] - 8e-4).all()


def test_points_beyond_the_depth_tolerance_or_outside_the_view_read_zero():
    """A pose estimate 3 mm off puts the points off the observed membrane; the default narrow camera (config's
    fx = 90 px) does not see the rim of the contact patch, so those points read zero (no measurement)."""
    deformation = sensed_deformation(WIDE, PRESSED)
    far = PRESSED + np.array([0.0, 0.0, -0.003, 0.0, 0.0, 0.0, 0.0])
    assert (penetration_from_deformation(deformation, WIDE, RADII, LOOK_DOWN, points_in_bubble(far)) == 0).all()
    expected = truth(PRESSED)
    narrow = penetration_from_deformation(sensed_deformation(NARROW, PRESSED), NARROW, RADII, LOOK_DOWN,
                                          points_in_bubble(PRESSED))
    points = points_in_bubble(PRESSED)
    outside = np.abs(points[:, 0] / -points[:, 2]) > NARROW.cx / NARROW.fx  # beyond the image's left/right edge
    assert (expected[outside] > 1e-3).any() and (narrow[outside] == 0).all()
    assert normal_force_n(narrow) < 0.95 * normal_force_n(expected)  # 11 % of the force is out of view


def test_an_explicit_reference_is_used_and_bad_inputs_are_refused():
    deformation = sensed_deformation(WIDE, PRESSED)
    points = points_in_bubble(PRESSED)
    nominal = penetration_from_deformation(deformation, WIDE, RADII, LOOK_DOWN, points)
    reference = reference_depth(WIDE, RADII, LOOK_DOWN)
    np.testing.assert_array_equal(
        penetration_from_deformation(deformation, WIDE, RADII, LOOK_DOWN, points, reference_m=reference), nominal)
    shifted = penetration_from_deformation(deformation, WIDE, RADII, LOOK_DOWN, points, reference_m=reference + 1e-3)
    assert shifted.max() < nominal.max() - 8e-4  # the membrane seen 1 mm farther out: 1 mm less deep
    with pytest.raises(ValueError, match="deformation image"):
        penetration_from_deformation(deformation[:, :-1], WIDE, RADII, LOOK_DOWN, points)
    with pytest.raises(ValueError, match="reference image"):
        penetration_from_deformation(deformation, WIDE, RADII, LOOK_DOWN, points, reference_m=reference[1:])
    with pytest.raises(ValueError, match="points_bubble"):
        penetration_from_deformation(deformation, WIDE, RADII, LOOK_DOWN, points[:, :2])
    with pytest.raises(ValueError, match="norm"):
        penetration_from_deformation(deformation, WIDE, RADII, (0, 0, 0, 0.5, 0, 0, 0), points)
