"""Small numpy pose helpers for the drivers (OpenCV and the device SDKs speak numpy; ``hydrosoft.geometry.se3`` is the
torch twin).

A pose is a ``(7,)`` float64 array ``[x, y, z, qw, qx, qy, qz]``: a position in metres and a unit quaternion, the
pose of frame ``b`` in frame ``a`` when named ``T_a_b`` (it maps points from ``b`` to ``a``: ``p_a = R p_b + t``).
Quaternions returned here have ``qw >= 0``. Camera frames are OpenCV's: x right, y down, z forward.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

# A quaternion whose norm is further than this from 1 is a caller's mistake, not rounding.
UNIT_QUATERNION_TOLERANCE = 1e-3


def check_pose(pose: np.ndarray, name: str = "pose") -> np.ndarray:
    """Return ``pose`` as a float64 ``(7,)`` array with its quaternion normalised.

    Raises:
        ValueError: naming ``name``, when the shape is not ``(7,)``, a value is not finite or the quaternion's norm
            is further than ``UNIT_QUATERNION_TOLERANCE`` from 1.
    """
    array = np.asarray(pose, dtype=np.float64)
    if array.shape != (7,):
        raise ValueError(f"{name}: expected shape (7,) [x, y, z, qw, qx, qy, qz], got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name}: contains a non-finite value: {array.tolist()}")
    norm = float(np.linalg.norm(array[3:]))
    if abs(norm - 1.0) > UNIT_QUATERNION_TOLERANCE:
        raise ValueError(f"{name}: quaternion norm is {norm:.6f}, expected 1 (wxyz unit quaternion)")
    return np.concatenate([array[:3], array[3:] / norm])


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix ``(3, 3)`` of a unit quaternion ``q (4,)`` wxyz."""
    w, x, y, z = (np.asarray(q, dtype=np.float64) / _norm(q)).tolist()  # Python floats: the same IEEE doubles
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(4,)`` wxyz with ``qw >= 0`` of a rotation matrix ``R (3, 3)``."""
    rvec, _ = cv2.Rodrigues(np.asarray(R, dtype=np.float64))
    return rvec_to_quat(rvec.ravel())


def rvec_to_quat(rvec: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(4,)`` wxyz with ``qw >= 0`` of a rotation vector ``rvec (3,)`` (rad, OpenCV's rvec)."""
    rvec = np.asarray(rvec, dtype=np.float64).reshape(3)
    angle = _norm(rvec)
    if angle < 1e-12:
        return np.array([1.0, 0.0, 0.0, 0.0])
    q = np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * rvec / angle])
    return q if q[0] >= 0 else -q


def quat_to_rvec(q: np.ndarray) -> np.ndarray:
    """Rotation vector ``(3,)`` (rad, norm in [0, pi]) of a unit quaternion ``q (4,)`` wxyz."""
    q = np.asarray(q, dtype=np.float64) / _norm(q)
    if q[0] < 0:
        q = -q
    sin_half = _norm(q[1:])
    if sin_half < 1e-12:
        return 2.0 * q[1:]
    return 2.0 * np.arctan2(sin_half, q[0]) * q[1:] / sin_half


def pose_from_rt(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Pose ``(7,)`` from a rotation matrix ``R (3, 3)`` and a translation ``t (3,)`` (m)."""
    return np.concatenate([np.asarray(t, dtype=np.float64).reshape(3), matrix_to_quat(R)])


def pose_from_rvec_tvec(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """Pose ``(7,)`` from OpenCV's ``rvec, tvec`` (rad, m): the object's pose in the camera frame."""
    return np.concatenate([np.asarray(tvec, dtype=np.float64).reshape(3), rvec_to_quat(rvec)])


def rvec_tvec_from_pose(pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's ``rvec (3, 1)`` (rad) and ``tvec (3, 1)`` (m) of a pose ``(7,)``."""
    pose = np.asarray(pose, dtype=np.float64)
    return quat_to_rvec(pose[3:]).reshape(3, 1), pose[:3].reshape(3, 1).copy()


def compose(T_a_b: np.ndarray, T_b_c: np.ndarray) -> np.ndarray:
    """Pose ``T_a_c = T_a_b · T_b_c`` ``(7,)`` (apply ``T_b_c`` first)."""
    R_ab = quat_to_matrix(T_a_b[3:])
    R_ac = R_ab @ quat_to_matrix(T_b_c[3:])
    return pose_from_rt(R_ac, R_ab @ np.asarray(T_b_c[:3], dtype=np.float64) + T_a_b[:3])


def inverse(T_a_b: np.ndarray) -> np.ndarray:
    """Pose ``T_b_a (7,)``, the inverse of ``T_a_b``."""
    R_ba = quat_to_matrix(T_a_b[3:]).T
    return pose_from_rt(R_ba, -R_ba @ np.asarray(T_a_b[:3], dtype=np.float64))


def transform_points(T_a_b: np.ndarray, points_b: np.ndarray) -> np.ndarray:
    """Map points ``(..., 3)`` (m) from frame ``b`` to frame ``a``: ``R p + t``."""
    return np.asarray(points_b, dtype=np.float64) @ quat_to_matrix(T_a_b[3:]).T + np.asarray(T_a_b[:3])


def rotation_angle_rad(q_a: np.ndarray, q_b: np.ndarray) -> float:
    """Angle (rad, in [0, pi]) of the rotation taking unit quaternion ``q_a (4,)`` to ``q_b (4,)``."""
    dot = abs(float(np.dot(q_a, q_b)) / (_norm(q_a) * _norm(q_b)))
    return 2.0 * float(np.arccos(min(1.0, dot)))


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Pose ``T_world_camera (7,)`` of an OpenCV camera at ``eye (3,)`` looking at ``target (3,)`` (m, world frame).

    The camera's z axis points at the target; ``up (3,)`` is the world direction that appears towards the top of
    the image (the camera's ``-y``); it must not be parallel to the line of sight.

    Raises:
        ValueError: when ``eye == target`` or ``up`` is parallel to the line of sight.
    """
    eye, target, up = (np.asarray(v, dtype=np.float64).reshape(3) for v in (eye, target, up))
    forward = target - eye
    distance = float(np.linalg.norm(forward))
    if distance < 1e-9:
        raise ValueError("look_at: eye and target coincide")
    z = forward / distance
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        raise ValueError(f"look_at: up {up.tolist()} is parallel to the line of sight {z.tolist()}")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return pose_from_rt(np.column_stack([x, y, z]), eye)


def _norm(vector: np.ndarray) -> float:
    """``np.linalg.norm`` of a float64 vector, bit for bit (the square root of its dot with itself), without its
    dispatch: the pose helpers take several per call, the tag tracker hundreds per image. Other dtypes go to
    ``np.linalg.norm`` itself."""
    vector = np.asarray(vector)
    if vector.dtype != np.float64 or vector.ndim != 1:
        return float(np.linalg.norm(vector))
    vector = vector.ravel(order="K")  # as np.linalg.norm does: a strided vector is copied, the dot is the same
    return math.sqrt(float(vector.dot(vector)))
