"""The arm commander's safety rules as pure functions: target checks, speed-limited interpolation, the watchdog.

Poses are ``(7,)`` ``[x, y, z, qw, qx, qy, qz]`` (m, unit quaternion) of the TCP in the robot base frame (the
hydrosoft world frame). Times are ``time.monotonic_ns()`` stamps, limits come from ``config.LimitsConfig``. Nothing
here touches a socket, a driver or a clock, so every rule has a unit test that shows it firing
(``tests/services/test_safety.py``).
"""

from __future__ import annotations

import math

import numpy as np

from hydrosoft.services.config import LimitsConfig

#: A target quaternion whose norm is further than this from 1 is refused (the bus already rejects worse).
UNIT_QUATERNION_TOLERANCE = 1e-6
#: Below this angle (rad) two orientations count as equal and slerp returns the target.
SAME_ORIENTATION_RAD = 1e-9
#: The TCP is moving when its speed exceeds either of these (m/s, rad/s): above the noise of RTDE's
#: actual_TCP_speed at rest, far below any commanded motion.
MOVING_SPEED_M_S = 0.002
MOVING_ANGULAR_SPEED_RAD_S = 0.01
#: The watchdog's reason when there is no target to servo to.
NO_TARGET = "no target"


def check_target(pose, limits: LimitsConfig) -> str | None:
    """Why the TCP target ``pose (7,)`` (m, wxyz, base frame) must be refused, or None when it is acceptable: a
    wrong shape, a non-finite value, a quaternion that is not unit length, a position outside the workspace box
    ``limits.workspace_min .. workspace_max`` (m)."""
    array = np.asarray(pose, dtype=np.float64)
    if array.shape != (7,):
        return f"target has shape {array.shape}, expected (7,) [x, y, z, qw, qx, qy, qz]"
    if not np.all(np.isfinite(array)):
        return f"target has a non-finite value: {array.tolist()}"
    norm = float(np.linalg.norm(array[3:]))
    if abs(norm - 1.0) > UNIT_QUATERNION_TOLERANCE:
        return f"target quaternion norm is {norm:.9f}, expected 1"
    return outside_workspace(array[:3], limits)


def outside_workspace(position, limits: LimitsConfig) -> str | None:
    """Why the TCP ``position (3,)`` (m, base frame) lies outside the workspace box ``limits.workspace_min ..
    workspace_max``, or None when it lies inside (borders included)."""
    array = np.asarray(position, dtype=np.float64)
    lo, hi = np.asarray(limits.workspace_min), np.asarray(limits.workspace_max)
    if np.any(array < lo) or np.any(array > hi):
        return (f"target position {np.round(array, 4).tolist()} m is outside the workspace box "
                f"{list(limits.workspace_min)} .. {list(limits.workspace_max)} m")
    return None


def rotation_angle_rad(q0: np.ndarray, q1: np.ndarray) -> float:
    """Angle (rad, in [0, pi]) of the rotation from unit quaternion ``q0 (4,)`` to ``q1 (4,)`` (wxyz)."""
    return 2.0 * math.acos(min(1.0, abs(float(np.dot(q0, q1)))))


def slerp(q0: np.ndarray, q1: np.ndarray, fraction: float) -> np.ndarray:
    """The unit quaternion ``(4,)`` a ``fraction`` in [0, 1] of the way from ``q0 (4,)`` to ``q1 (4,)`` along the
    shorter arc (constant angular rate in ``fraction``)."""
    if np.dot(q0, q1) < 0:
        q1 = -q1
    half_angle = math.acos(min(1.0, float(np.dot(q0, q1))))
    if 2.0 * half_angle < SAME_ORIENTATION_RAD:
        return q1.copy()
    q = (math.sin((1.0 - fraction) * half_angle) * q0 + math.sin(fraction * half_angle) * q1) / math.sin(half_angle)
    return q / np.linalg.norm(q)


def interpolate(current, target, dt_s: float, limits: LimitsConfig) -> np.ndarray:
    """The next servo pose ``(7,)`` from ``current (7,)`` towards ``target (7,)`` (m, wxyz, base frame).

    It moves at most ``limits.max_speed_m_s * dt_s`` (m) in position and ``limits.max_angular_speed_rad_s * dt_s``
    (rad) in orientation. Position (along the straight line) and orientation (slerp) advance by one shared fraction
    of the remaining way, so the TCP stays on the straight path and both arrive together; the binding limit sets
    the fraction. Returns ``target`` once it is within one step.
    """
    current, target = np.asarray(current, dtype=np.float64), np.asarray(target, dtype=np.float64)
    distance_m = float(np.linalg.norm(target[:3] - current[:3]))
    angle_rad = rotation_angle_rad(current[3:], target[3:])
    fraction = 1.0
    if distance_m > 0.0:
        fraction = min(fraction, limits.max_speed_m_s * dt_s / distance_m)
    if angle_rad > 0.0:
        fraction = min(fraction, limits.max_angular_speed_rad_s * dt_s / angle_rad)
    if fraction >= 1.0:
        return target.copy()
    return np.concatenate([current[:3] + fraction * (target[:3] - current[:3]),
                           slerp(current[3:], target[3:], fraction)])


def is_moving(tcp_speed) -> bool:
    """Whether a TCP twist ``(6,)`` [m/s, rad/s] is above ``MOVING_SPEED_M_S`` or ``MOVING_ANGULAR_SPEED_RAD_S``."""
    twist = np.asarray(tcp_speed, dtype=np.float64)
    return bool(np.linalg.norm(twist[:3]) > MOVING_SPEED_M_S or np.linalg.norm(twist[3:]) > MOVING_ANGULAR_SPEED_RAD_S)


def watchdog(now_ns: int, target_deadline_ns: int | None, heartbeat_stamp_ns: int | None,
             state_stamp_ns: int | None, force_n: float | None, limits: LimitsConfig) -> str | None:
    """Why the arm must stop at ``now_ns``, or None when it may servo on. The rules, in order:

    - no target (``target_deadline_ns`` None), or ``now_ns`` past the target's deadline;
    - the planner's heartbeat never seen (None) or stamped more than ``limits.heartbeat_timeout_s`` ago;
    - the driver's state not advancing: last seen to advance (``state_stamp_ns``) more than
      ``limits.state_timeout_s`` ago, or never;
    - the contact force unknown (``force_n`` None: no fresh F/T reading, so the limit cannot be kept) or above
      ``limits.max_force_n`` (N).
    """
    if target_deadline_ns is None:
        return NO_TARGET
    if now_ns > target_deadline_ns:
        return f"target deadline passed {(now_ns - target_deadline_ns) * 1e-9:.3f} s ago"
    if heartbeat_stamp_ns is None:
        return "no planner heartbeat"
    heartbeat_age_s = (now_ns - heartbeat_stamp_ns) * 1e-9
    if heartbeat_age_s > limits.heartbeat_timeout_s:
        return f"planner heartbeat {heartbeat_age_s:.3f} s old (limit {limits.heartbeat_timeout_s} s)"
    if state_stamp_ns is None:
        return "no arm state"
    state_age_s = (now_ns - state_stamp_ns) * 1e-9
    if state_age_s > limits.state_timeout_s:
        return f"arm state not advancing for {state_age_s:.3f} s (limit {limits.state_timeout_s} s)"
    if force_n is None:
        return "no fresh F/T reading"
    if not force_n <= limits.max_force_n:
        return f"contact force {force_n:.1f} N above the limit {limits.max_force_n} N"
    return None
