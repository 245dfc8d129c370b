"""UR rotation vectors against the stack's quaternions, at the driver's edge."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from hydrosoft.drivers.ur.pose import (
    check_pose,
    pose_to_ur,
    quat_from_rotvec,
    quat_multiply,
    rotvec_from_quat,
    ur_to_pose,
)

finite = st.floats(-1.0, 1.0, allow_nan=False)


@given(axis=st.tuples(finite, finite, finite), angle=st.floats(0.0, math.pi - 1e-6))
def test_rotvec_round_trip(axis, angle):
    axis = np.array(axis)
    if np.linalg.norm(axis) < 1e-3:
        axis = np.array([0.0, 0.0, 1.0])
    rotvec = angle * axis / np.linalg.norm(axis)
    quat = quat_from_rotvec(rotvec)
    assert abs(np.linalg.norm(quat) - 1.0) < 1e-12
    np.testing.assert_allclose(rotvec_from_quat(quat), rotvec, atol=1e-9)
    np.testing.assert_allclose(rotvec_from_quat(-quat), rotvec, atol=1e-9)  # q and -q: the same rotation


def test_tool_down_pose_and_small_angles():
    np.testing.assert_allclose(ur_to_pose([0.3, -0.2, 0.4, 0.0, math.pi, 0.0]), [0.3, -0.2, 0.4, 0, 0, 1, 0],
                               atol=1e-15)
    tiny = np.array([1e-9, -2e-9, 3e-9])
    np.testing.assert_allclose(rotvec_from_quat(quat_from_rotvec(tiny)), tiny, rtol=1e-12)
    np.testing.assert_array_equal(rotvec_from_quat(np.array([1.0, 0, 0, 0])), np.zeros(3))


def test_quaternion_product_composes_rotations():
    quarter_z = quat_from_rotvec([0.0, 0.0, math.pi / 2])
    np.testing.assert_allclose(rotvec_from_quat(quat_multiply(quarter_z, quarter_z)), [0, 0, math.pi], atol=1e-12)


def test_pose_to_ur_round_trip_and_renormalises():
    ur = np.array([0.1, 0.2, 0.3, 0.4, -0.5, 0.6])
    np.testing.assert_allclose(pose_to_ur(ur_to_pose(ur)), ur, atol=1e-12)
    pose = ur_to_pose(ur)
    pose[3:] *= 1.0 + 5e-7
    np.testing.assert_allclose(np.linalg.norm(check_pose(pose)[3:]), 1.0, atol=1e-15)


@pytest.mark.parametrize(
    ("pose", "message"),
    [
        (np.zeros(6), r"shape \(7,\)"),
        (np.array([0, 0, np.nan, 1, 0, 0, 0]), "non-finite"),
        (np.array([0, 0, 0, 1.1, 0, 0, 0]), "norm is 1.1"),
    ],
)
def test_check_pose_names_the_problem(pose, message):
    with pytest.raises(ValueError, match=message):
        check_pose(pose)
