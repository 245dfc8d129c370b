"""Kinematics of the simulated UR tool centre point (TCP): servo tracking, speed control, linear moves and stops.

A deliberately simple model, not UR's controller: the TCP is a free rigid body in the robot base frame whose
velocity is shaped by the active command and limited in speed and acceleration (``MotionLimits``). There are no
joints, no inverse kinematics and no singularities. One ``TcpMotion.step(dt_s)`` advances it by ``dt_s`` seconds.

- servo (``servoL``): first-order tracking of the latest target, ``v_des = error / tau`` with
  ``tau = lookahead_s * SERVO_REFERENCE_GAIN / gain`` (s), then the speed and acceleration limits. A higher gain
  tracks tighter, a longer lookahead smooths more, as on the real arm.
- speed (``speedL``): the twist ramps toward the commanded one at the commanded acceleration and is held (for
  ``time_s`` seconds when that is positive, then the TCP stops at the same acceleration).
- move (``moveL``): straight line in position with a slerp in orientation, trapezoidal profile at the commanded
  speed and acceleration; it ends exactly on the target.
- stop (``servoStop``, ``speedStop``, ``stopL``, protective stop, program end): the twist decays to zero at the
  given deceleration, then the TCP holds.

Poses are ``(7,)`` ``[x, y, z, qw, qx, qy, qz]`` (m, unit quaternion) in the base frame; twists ``(6,)`` are
``[vx, vy, vz, wx, wy, wz]`` (m/s, rad/s) in the base frame, the convention of RTDE ``actual_TCP_speed``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum

import numpy as np

from hydrosoft.drivers.ur.pose import check_pose, quat_conjugate, quat_from_rotvec, quat_multiply, rotvec_from_quat

SERVO_REFERENCE_GAIN = 300.0  # servoL gain at which tau equals the lookahead time
MIN_TAU_STEPS = 2.0  # tau is never shorter than this many steps, so the discrete tracker cannot overshoot
ARRIVED_M = 1e-9  # a linear move ends when less than this remains of its path (m)


class MotionMode(Enum):
    """What the TCP is doing."""

    HOLD = "hold"
    SERVO = "servo"
    SPEED = "speed"
    MOVE = "move"
    STOP = "stop"


@dataclass(frozen=True)
class MotionLimits:
    """Limits of the simulated TCP. Speeds in m/s and rad/s, accelerations in m/s^2 and rad/s^2."""

    max_speed_m_s: float = 1.0
    max_accel_m_s2: float = 5.0
    max_angular_speed_rad_s: float = 3.0
    max_angular_accel_rad_s2: float = 15.0
    protective_stop_decel_m_s2: float = 10.0

    def __post_init__(self) -> None:
        for name in ("max_speed_m_s", "max_accel_m_s2", "max_angular_speed_rad_s", "max_angular_accel_rad_s2",
                     "protective_stop_decel_m_s2"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"MotionLimits.{name} must be positive and finite, got {value}")


def _clip_norm(v: np.ndarray, limit: float) -> np.ndarray:
    norm = float(np.linalg.norm(v))
    return v if norm <= limit else v * (limit / norm)


def _approach(current: np.ndarray, target: np.ndarray, max_change: float) -> np.ndarray:
    """``current`` moved toward ``target`` by at most ``max_change`` (Euclidean)."""
    return current + _clip_norm(target - current, max_change)


def _slerp(q0: np.ndarray, q1: np.ndarray, fraction: float) -> np.ndarray:
    """Quaternion ``fraction`` of the way from ``q0`` to ``q1`` along the shorter arc."""
    delta = quat_multiply(q1, quat_conjugate(q0))
    return quat_multiply(quat_from_rotvec(fraction * rotvec_from_quat(delta)), q0)


class TcpMotion:
    """The simulated TCP: pose, twist and the active command. Not thread-safe; one owner steps it.

    Read ``pose()`` and ``twist()``; command with ``servo``, ``speed``, ``move``, ``stop``, ``hold``; advance with
    ``step(dt_s)``; ``impose_pose`` overwrites the pose (another simulator pushed the TCP) without changing the
    command. ``busy`` is False once a move or a stop has finished.
    """

    def __init__(self, pose: np.ndarray, limits: MotionLimits | None = None) -> None:
        pose = check_pose(pose)
        self.limits = limits or MotionLimits()
        self._position = pose[:3].copy()
        self._quat = pose[3:].copy()
        self._velocity = np.zeros(3)
        self._angular_velocity = np.zeros(3)
        self.mode = MotionMode.HOLD
        self._target = pose.copy()
        self._tau_s = 0.1
        self._twist_target = np.zeros(6)
        self._accel = 0.0
        self._remaining_s = math.inf
        self._move_start = pose.copy()
        self._move_length = 0.0
        self._move_done = 0.0
        self._move_speed = 0.0
        self._move_speed_limit = 0.0
        self._move_accel = 0.0

    # -- reading ---------------------------------------------------------------------------------------------

    def pose(self) -> np.ndarray:
        """TCP pose ``(7,)`` [m, wxyz] in the base frame (a copy)."""
        return np.concatenate((self._position, self._quat))

    def twist(self) -> np.ndarray:
        """TCP twist ``(6,)`` [m/s, rad/s] in the base frame (a copy)."""
        return np.concatenate((self._velocity, self._angular_velocity))

    @property
    def busy(self) -> bool:
        """True while a linear move or a stop is still under way."""
        return self.mode in (MotionMode.MOVE, MotionMode.STOP)

    # -- commands --------------------------------------------------------------------------------------------

    def hold(self) -> None:
        """Stand still at once (no deceleration): the state after a stop has finished."""
        self.mode = MotionMode.HOLD
        self._velocity[:] = 0.0
        self._angular_velocity[:] = 0.0

    def servo(self, target: np.ndarray, lookahead_s: float, gain: float) -> None:
        """Track ``target (7,)`` from now on (servoL); ``lookahead_s`` in s, ``gain`` dimensionless (UR 100-2000)."""
        self._target = check_pose(target)
        self._tau_s = max(lookahead_s, 1e-3) * SERVO_REFERENCE_GAIN / max(gain, 1.0)
        self.mode = MotionMode.SERVO

    def speed(self, twist: np.ndarray, accel_m_s2: float, time_s: float = 0.0) -> None:
        """Ramp to ``twist (6,)`` at ``accel_m_s2`` and hold it (speedL); for ``time_s`` s when that is > 0."""
        self._twist_target = np.asarray(twist, dtype=np.float64).copy()
        self._accel = max(accel_m_s2, 1e-6)
        self._remaining_s = time_s if time_s > 0.0 else math.inf
        self.mode = MotionMode.SPEED

    def move(self, target: np.ndarray, speed_m_s: float, accel_m_s2: float) -> None:
        """Move linearly to ``target (7,)`` at ``speed_m_s`` with ``accel_m_s2`` (moveL)."""
        target = check_pose(target)
        start = self.pose()
        length = float(np.linalg.norm(target[:3] - start[:3]))
        angle = float(np.linalg.norm(rotvec_from_quat(quat_multiply(target[3:], quat_conjugate(start[3:])))))
        speed = min(max(speed_m_s, 1e-6), self.limits.max_speed_m_s)
        # a rotation counts as the distance it takes at the angular speed limit, scaled to the linear speed
        self._move_length = max(length, angle * speed / self.limits.max_angular_speed_rad_s)
        self._move_start = start
        self._target = target
        self._move_done = 0.0
        self._move_speed = float(np.linalg.norm(self._velocity))
        self._move_speed_limit = speed
        self._move_accel = max(accel_m_s2, 1e-6)
        self.mode = MotionMode.MOVE

    def stop(self, decel_m_s2: float) -> None:
        """Decelerate to rest at ``decel_m_s2`` (m/s^2; angular at the same ratio of the limits), then hold."""
        if self.mode == MotionMode.HOLD:
            return
        self._accel = max(decel_m_s2, 1e-6)
        self.mode = MotionMode.STOP

    def impose_pose(self, pose: np.ndarray) -> None:
        """Overwrite the TCP pose ``(7,)`` (e.g. the physics pushed the tool); the active command continues."""
        pose = check_pose(pose)
        self._position = pose[:3].copy()
        self._quat = pose[3:].copy()

    # -- time ------------------------------------------------------------------------------------------------

    def step(self, dt_s: float) -> None:
        """Advance the TCP by ``dt_s`` seconds under the active command."""
        if dt_s <= 0.0:
            return
        if self.mode == MotionMode.MOVE:
            self._step_move(dt_s)
            return
        if self.mode == MotionMode.SERVO:
            self._step_servo(dt_s)
        elif self.mode == MotionMode.SPEED:
            self._step_speed(dt_s)
        elif self.mode == MotionMode.STOP:
            self._step_stop(dt_s)
        self._integrate(dt_s)

    def _angular_ratio(self) -> float:
        return self.limits.max_angular_accel_rad_s2 / self.limits.max_accel_m_s2

    def _step_servo(self, dt_s: float) -> None:
        lim = self.limits
        tau = max(self._tau_s, MIN_TAU_STEPS * dt_s)
        v_des = _clip_norm((self._target[:3] - self._position) / tau, lim.max_speed_m_s)
        rot_err = rotvec_from_quat(quat_multiply(self._target[3:], quat_conjugate(self._quat)))
        w_des = _clip_norm(rot_err / tau, lim.max_angular_speed_rad_s)
        self._velocity = _approach(self._velocity, v_des, lim.max_accel_m_s2 * dt_s)
        self._angular_velocity = _approach(self._angular_velocity, w_des, lim.max_angular_accel_rad_s2 * dt_s)

    def _step_speed(self, dt_s: float) -> None:
        lim = self.limits
        self._remaining_s -= dt_s
        if self._remaining_s <= 0.0:
            self.mode = MotionMode.STOP
            self._step_stop(dt_s)
            return
        v_des = _clip_norm(self._twist_target[:3], lim.max_speed_m_s)
        w_des = _clip_norm(self._twist_target[3:], lim.max_angular_speed_rad_s)
        self._velocity = _approach(self._velocity, v_des, self._accel * dt_s)
        self._angular_velocity = _approach(self._angular_velocity, w_des, self._accel * self._angular_ratio() * dt_s)

    def _step_stop(self, dt_s: float) -> None:
        self._velocity = _approach(self._velocity, np.zeros(3), self._accel * dt_s)
        self._angular_velocity = _approach(
            self._angular_velocity, np.zeros(3), self._accel * self._angular_ratio() * dt_s
        )
        if not self._velocity.any() and not self._angular_velocity.any():
            self.mode = MotionMode.HOLD

    def _step_move(self, dt_s: float) -> None:
        accel = self._move_accel
        remaining = self._move_length - self._move_done
        braking = math.sqrt(2.0 * accel * max(remaining, 0.0))
        self._move_speed = min(self._move_speed + accel * dt_s, self._move_speed_limit, braking)
        self._move_done = min(self._move_done + self._move_speed * dt_s, self._move_length)
        if self._move_length - self._move_done < ARRIVED_M:
            new_pose = self._target
        else:
            fraction = self._move_done / self._move_length
            new_pose = np.concatenate(
                (
                    self._move_start[:3] + fraction * (self._target[:3] - self._move_start[:3]),
                    _slerp(self._move_start[3:], self._target[3:], fraction),
                )
            )
        self._velocity = (new_pose[:3] - self._position) / dt_s
        self._angular_velocity = rotvec_from_quat(quat_multiply(new_pose[3:], quat_conjugate(self._quat))) / dt_s
        self._position = new_pose[:3].copy()
        self._quat = new_pose[3:].copy()
        if new_pose is self._target:
            self.hold()

    def _integrate(self, dt_s: float) -> None:
        self._position = self._position + self._velocity * dt_s
        if self._angular_velocity.any():
            self._quat = quat_multiply(quat_from_rotvec(self._angular_velocity * dt_s), self._quat)
            self._quat /= np.linalg.norm(self._quat)
