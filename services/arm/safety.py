"""The arm commander's safety rules as pure functions: target checks (workspace box, straight path, orientation),
speed-limited interpolation, the force limit's retreat rule, the watchdog.

Poses are ``(7,)`` ``[x, y, z, qw, qx, qy, qz]`` (m, unit quaternion) of the TCP in the robot base frame (the
hydrosoft world frame). Times are ``time.monotonic_ns()`` stamps, limits come from ``config.LimitsConfig``. Nothing
here touches a socket, a driver or a clock, so every rule has a unit test that shows it firing
(``tests/services/test_safety.py``).
"""

from __future__ import annotations

import math

import numpy as np

from hydrosoft.services.bus.config import LimitsConfig

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
#: Above the force limit a target counts as a retreat when its displacement points within 60 deg of the contact
#: force on the bubble (cosine 0.5): it moves the bubble mostly away from what presses on it, never further in.
RETREAT_MIN_COSINE = 0.5
#: A retreat moves at least this far (m; less is no move at all) and turns the tool at most this much (rad): a turn
#: while pressed could press one side of the membrane further in.
RETREAT_MIN_DISTANCE_M = 1e-4
RETREAT_MAX_TURN_RAD = math.radians(2.0)


def check_target(pose, limits: LimitsConfig, nominal_tcp=None) -> str | None:
    """Why the TCP target ``pose (7,)`` (m, wxyz, base frame) must be refused, or None when it is acceptable: a
    wrong shape, a non-finite value, a quaternion that is not unit length, a position outside the workspace box
    ``limits.workspace_min .. workspace_max`` (m), and (given the arm's ``nominal_tcp (4,)`` wxyz) an orientation
    outside ``limits.max_tilt_deg`` / ``yaw_range_deg`` (``outside_orientation``)."""
    array = np.asarray(pose, dtype=np.float64)
    if array.shape != (7,):
        return f"target has shape {array.shape}, expected (7,) [x, y, z, qw, qx, qy, qz]"
    if not np.all(np.isfinite(array)):
        return f"target has a non-finite value: {array.tolist()}"
    norm = float(np.linalg.norm(array[3:]))
    if abs(norm - 1.0) > UNIT_QUATERNION_TOLERANCE:
        return f"target quaternion norm is {norm:.9f}, expected 1"
    reason = outside_workspace(array[:3], limits)
    if reason is None and nominal_tcp is not None:
        reason = outside_orientation(array[3:], nominal_tcp, limits)
    return reason


def check_path(start, target, limits: LimitsConfig, nominal_tcp) -> str | None:
    """Why the straight move from the measured TCP pose ``start (7,)`` to an acceptable ``target (7,)`` (m, wxyz,
    base frame) must be refused, or None. The box is convex, so the straight line lies inside it exactly when its
    start does; the orientation is checked at the start too (a tool already tilted past the limit is not moved
    on)."""
    start = np.asarray(start, dtype=np.float64)
    reason = outside_workspace(start[:3], limits) or outside_orientation(start[3:], nominal_tcp, limits)
    return None if reason is None else f"the path starts outside the limits: {reason}"


def tilt_and_yaw_deg(quat, nominal_tcp) -> tuple[float, float]:
    """The orientation ``quat (4,)`` (wxyz, base frame) relative to ``nominal_tcp (4,)``: the tilt (deg, in
    [0, 180]) between the two tool z axes, and the yaw (deg, in (-180, 180]): the turn about the nominal z axis
    (the twist part of the relative rotation)."""
    relative = quat_multiply(quat_conjugate(np.asarray(nominal_tcp, dtype=np.float64)), np.asarray(quat, np.float64))
    w, x, y, z = relative
    z_axis_z = 1.0 - 2.0 * (x * x + y * y)  # the tool z axis in the nominal frame, its z component
    tilt = math.degrees(math.acos(max(-1.0, min(1.0, z_axis_z))))
    yaw = math.degrees(2.0 * math.atan2(z, w)) if (w, z) != (0.0, 0.0) else 180.0
    yaw = (yaw + 180.0) % 360.0 - 180.0
    return tilt, (180.0 if yaw == -180.0 else yaw)


def outside_orientation(quat, nominal_tcp, limits: LimitsConfig) -> str | None:
    """Why the TCP orientation ``quat (4,)`` (wxyz, base frame) is outside the limits about the arm's
    ``nominal_tcp (4,)``, or None: a tilt above ``limits.max_tilt_deg`` (a flipped tool is 180 deg) or a yaw
    outside ``limits.yaw_range_deg``."""
    tilt, yaw = tilt_and_yaw_deg(quat, nominal_tcp)
    if tilt > limits.max_tilt_deg:
        return f"tool tilted {tilt:.1f} deg from its nominal axis (limit {limits.max_tilt_deg} deg)"
    low, high = limits.yaw_range_deg
    if not low <= yaw <= high:
        return f"tool yaw {yaw:.1f} deg outside {low} .. {high} deg"
    return None


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    """The inverse rotation of unit quaternion ``q (4,)`` (wxyz)."""
    return np.array([q[0], -q[1], -q[2], -q[3]])


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The Hamilton product ``a * b`` of quaternions ``(4,)`` (wxyz): rotation ``b`` then ``a``."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw])


def rotate(q: np.ndarray, vector) -> np.ndarray:
    """``vector (3,)`` rotated by unit quaternion ``q (4,)`` (wxyz)."""
    return quat_multiply(quat_multiply(q, np.concatenate([[0.0], np.asarray(vector, np.float64)])),
                         quat_conjugate(q))[1:]


def retreat_refusal(current, target, force_tcp) -> str | None:
    """Why the move from the measured TCP pose ``current (7,)`` to ``target (7,)`` (m, wxyz, base frame) is not a
    retreat from the contact, or None when it is one. ``force_tcp (3,)`` (N) is the contact force on the bubble in
    the TCP frame (the F/T sensor's axes are the TCP's): it points away from what presses on the bubble. A retreat
    moves at least ``RETREAT_MIN_DISTANCE_M`` within ``acos(RETREAT_MIN_COSINE)`` of that direction and turns the
    tool by at most ``RETREAT_MAX_TURN_RAD``."""
    current, target = np.asarray(current, np.float64), np.asarray(target, np.float64)
    away = rotate(current[3:], force_tcp)
    move = target[:3] - current[:3]
    distance = float(np.linalg.norm(move))
    strength = float(np.linalg.norm(away))
    if distance < RETREAT_MIN_DISTANCE_M or strength == 0.0:
        return "the target does not move away from the contact"
    cosine = float(np.dot(move, away)) / (distance * strength)
    if cosine < RETREAT_MIN_COSINE:
        return (f"the target moves {math.degrees(math.acos(max(-1.0, min(1.0, cosine)))):.0f} deg off the direction "
                f"away from the contact (at most {math.degrees(math.acos(RETREAT_MIN_COSINE)):.0f} deg)")
    turn = rotation_angle_rad(current[3:], target[3:])
    if turn > RETREAT_MAX_TURN_RAD:
        return f"the target turns the tool {math.degrees(turn):.1f} deg while pressed"
    return None


def clamped_deadline_ns(deadline_ns: int, arrived_ns: int, limits: LimitsConfig) -> int:
    """A target's deadline (``time.monotonic_ns()``) clamped to at most ``limits.max_target_lead_s`` after its
    arrival ``arrived_ns``: a target is one plan step, never a standing order."""
    return min(deadline_ns, arrived_ns + int(limits.max_target_lead_s * 1e9))


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
             state_stamp_ns: int | None, force_n: float | None, limits: LimitsConfig,
             plan_done_ns: int | None = None) -> str | None:
    """Why the arm must stop at ``now_ns``, or None when it may servo on. The rules, in order:

    - no target (``target_deadline_ns`` None), or ``now_ns`` past the target's deadline;
    - the plan behind the target completed (``plan_done_ns``) more than ``limits.max_plan_age_s`` ago (a hung
      solve while the planner's heartbeat task still beats);
    - the planner's heartbeat never seen (None) or stamped more than ``limits.heartbeat_timeout_s`` ago;
    - the driver's state not advancing: last seen to advance (``state_stamp_ns``) more than
      ``limits.state_timeout_s`` ago, or never;
    - the contact force unknown (``force_n`` None: no fresh F/T reading, so the limit cannot be kept).

    The force limit itself (``limits.max_force_n``, with its retreat and release) is ``ServoLogic``'s: it depends on
    the target's direction, not only on the time.
    """
    if target_deadline_ns is None:
        return NO_TARGET
    if now_ns > target_deadline_ns:
        return f"target deadline passed {(now_ns - target_deadline_ns) * 1e-9:.3f} s ago"
    if plan_done_ns is not None and (plan_age_s := (now_ns - plan_done_ns) * 1e-9) > limits.max_plan_age_s:
        return f"no plan completed for {plan_age_s:.3f} s (limit {limits.max_plan_age_s} s)"
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
    return None
