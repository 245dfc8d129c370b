"""The numpy pose helpers agree with hydrosoft.geometry.se3 (torch) and OpenCV's conventions."""

import numpy as np
import pytest
import torch

from hydrosoft.drivers import poses
from hydrosoft.geometry import se3


def random_pose(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    return np.concatenate([rng.uniform(-1, 1, 3), q / np.linalg.norm(q)])


def same_pose(a: np.ndarray, b: np.ndarray) -> bool:
    """Equal position, and equal rotation up to the quaternion's sign."""
    return np.allclose(a[:3], b[:3], atol=1e-9) and min(np.abs(a[3:] - b[3:]).max(), np.abs(a[3:] + b[3:]).max()) < 1e-9


def test_compose_inverse_transform_match_torch():
    rng = np.random.default_rng(0)
    for _ in range(20):
        a, b = random_pose(rng), random_pose(rng)
        points = rng.normal(size=(5, 3))
        ta, tb = torch.tensor(a), torch.tensor(b)
        assert same_pose(poses.compose(a, b), se3.compose(ta, tb).numpy())
        assert same_pose(poses.inverse(a), se3.inverse(ta).numpy())
        np.testing.assert_allclose(poses.transform_points(a, points),
                                   se3.transform_points(ta, torch.tensor(points)).numpy(), atol=1e-12)


def test_rvec_round_trip_and_matrix_match_opencv():
    import cv2

    rng = np.random.default_rng(1)
    for _ in range(20):
        pose = random_pose(rng)
        rvec, tvec = poses.rvec_tvec_from_pose(pose)
        R_cv, _ = cv2.Rodrigues(rvec)
        np.testing.assert_allclose(R_cv, poses.quat_to_matrix(pose[3:]), atol=1e-12)
        back = poses.pose_from_rvec_tvec(rvec, tvec)
        assert back[3] >= 0 and same_pose(back, pose)
    assert poses.rotation_angle_rad(np.array([1.0, 0, 0, 0]), np.array([0.0, 1, 0, 0])) == pytest.approx(np.pi)


def test_look_at_points_z_at_target_and_up_to_image_top():
    T = poses.look_at([1.0, 0.0, 0.5], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0])
    R = poses.quat_to_matrix(T[3:])
    forward = np.array([-1.0, 0.0, -0.5]) / np.linalg.norm([1.0, 0.0, 0.5])
    np.testing.assert_allclose(R[:, 2], forward, atol=1e-12)
    assert R[:, 1] @ np.array([0.0, 0.0, 1.0]) < 0  # image y (down) points away from world up
    np.testing.assert_allclose(np.linalg.det(R), 1.0)
    with pytest.raises(ValueError, match="parallel"):
        poses.look_at([0, 0, 1], [0, 0, 0], [0, 0, 1])


@pytest.mark.parametrize("bad, message", [
    (np.zeros(6), "shape"),
    (np.array([0, 0, 0, 1, 0, 0, np.nan]), "non-finite"),
    (np.array([0, 0, 0, 2.0, 0, 0, 0]), "norm"),
])
def test_check_pose_names_the_problem(bad, message):
    with pytest.raises(ValueError, match=f"T_x.*{message}"):
        poses.check_pose(bad, "T_x")


def test_norm_is_numpys_bit_for_bit():
    """The helpers' quick norm gives ``np.linalg.norm``'s value exactly: float64 vectors (contiguous or a matrix's
    column), float32 ones (their own precision) and Python lists."""
    rng = np.random.default_rng(3)
    for _ in range(2000):
        vector = rng.normal(size=int(rng.integers(1, 8))) * 10.0 ** int(rng.integers(-8, 9))
        column = rng.normal(size=(4, 4))[:, 1]
        for value in (vector, column, vector.astype(np.float32), vector.tolist()):
            assert poses._norm(value) == float(np.linalg.norm(value))


def test_rotation_helpers_of_a_non_unit_quaternion_normalise_it():
    rng = np.random.default_rng(4)
    for _ in range(50):
        q = rng.normal(size=4)
        unit = q / np.linalg.norm(q)
        np.testing.assert_allclose(poses.quat_to_matrix(3.0 * q), poses.quat_to_matrix(unit), rtol=0, atol=1e-15)
        np.testing.assert_allclose(poses.quat_to_rvec(0.5 * q), poses.quat_to_rvec(unit), rtol=0, atol=1e-15)
        assert abs(poses.rotation_angle_rad(2.0 * q, unit)) < 1e-7
