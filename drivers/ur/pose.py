"""Pose conventions at the UR edge: UR's ``[x, y, z, rx, ry, rz]`` against the stack's ``[x, y, z, qw, qx, qy, qz]``.

UR poses (RTDE ``actual_TCP_pose``, URScript ``p[...]``) are a position in metres and a rotation vector (axis times
angle, rad) in the robot base frame. The stack uses ``(7,)`` float64 ``[x, y, z, qw, qx, qy, qz]`` (Hamilton
quaternion, scalar first, as ``hydrosoft.geometry.se3``). The conversions are exact up to float64 rounding, use a
Taylor series near zero angle, and return rotation vectors with angle in ``[0, pi]`` (the quaternion is taken with
``qw >= 0``), as the controller reports them.
"""

from __future__ import annotations

import math

import numpy as np

from hydrosoft.drivers.poses import check_pose

SMALL_ANGLE_RAD = 1e-6  # below this the sin(t/2)/t series replaces the closed form (error < 1e-25)


def quat_from_rotvec(rotvec: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(4,)`` wxyz of the rotation vector ``rotvec (3,)`` (rad)."""
    rotvec = np.asarray(rotvec, dtype=np.float64)
    angle = float(np.linalg.norm(rotvec))
    if angle < SMALL_ANGLE_RAD:
        half_sinc = 0.5 - angle * angle / 48.0  # sin(t/2)/t
    else:
        half_sinc = math.sin(0.5 * angle) / angle
    return np.concatenate(([math.cos(0.5 * angle)], half_sinc * rotvec))


def rotvec_from_quat(quat: np.ndarray) -> np.ndarray:
    """Rotation vector ``(3,)`` (rad, angle in ``[0, pi]``) of the unit quaternion ``quat (4,)`` wxyz."""
    quat = np.asarray(quat, dtype=np.float64)
    if quat[0] < 0.0:
        quat = -quat
    vec = quat[1:]
    sin_half = float(np.linalg.norm(vec))
    angle = 2.0 * math.atan2(sin_half, float(quat[0]))
    if angle < SMALL_ANGLE_RAD:
        return 2.0 * vec / float(quat[0])
    return (angle / sin_half) * vec


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product ``a * b`` of two ``(4,)`` wxyz quaternions (rotation ``b`` first, then ``a``)."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ]
    )


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    """Conjugate (inverse of a unit quaternion) of ``q (4,)`` wxyz."""
    return np.array([q[0], -q[1], -q[2], -q[3]])


def ur_to_pose(ur_pose) -> np.ndarray:
    """Stack pose ``(7,)`` [x, y, z, qw, qx, qy, qz] (m, unit quaternion) of a UR pose ``(6,)`` [m, rotvec rad]."""
    ur_pose = np.asarray(ur_pose, dtype=np.float64)
    if ur_pose.shape != (6,):
        raise ValueError(f"a UR pose has shape (6,) [x, y, z, rx, ry, rz], got {ur_pose.shape}")
    return np.concatenate((ur_pose[:3], quat_from_rotvec(ur_pose[3:])))


def pose_to_ur(pose: np.ndarray) -> np.ndarray:
    """UR pose ``(6,)`` [x, y, z, rx, ry, rz] (m, rotvec rad) of a checked stack pose ``(7,)`` (see ``check_pose``)."""
    pose = check_pose(pose)
    return np.concatenate((pose[:3], rotvec_from_quat(pose[3:])))

