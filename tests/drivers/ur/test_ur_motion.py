"""The simulated TCP's kinematics: servo tracking, speed control, linear moves and stops."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hydrosoft.drivers.ur.motion import MotionLimits, MotionMode, TcpMotion
from hydrosoft.drivers.ur.pose import quat_from_rotvec, rotvec_from_quat, quat_multiply, quat_conjugate

DT_S = 0.002
START = np.array([0.3, -0.2, 0.4, 0.0, 0.0, 1.0, 0.0])


def run(motion: TcpMotion, seconds: float) -> list[np.ndarray]:
    twists = []
    for _ in range(round(seconds / DT_S)):
        motion.step(DT_S)
        twists.append(motion.twist())
    return twists


def angle_between(qa, qb) -> float:
    return float(np.linalg.norm(rotvec_from_quat(quat_multiply(qa, quat_conjugate(qb)))))


def test_servo_converges_within_the_limits():
    limits = MotionLimits(max_speed_m_s=0.5, max_accel_m_s2=4.0)
    motion = TcpMotion(START, limits)
    target = START.copy()
    target[:3] += [0.1, -0.05, 0.02]
    target[3:] = quat_multiply(quat_from_rotvec([0.0, 0.0, 0.3]), START[3:])
    motion.servo(target, lookahead_s=0.05, gain=300.0)
    twists = run(motion, 1.5)
    assert np.linalg.norm(motion.pose()[:3] - target[:3]) < 1e-4
    assert angle_between(motion.pose()[3:], target[3:]) < 1e-4
    speeds = np.linalg.norm(np.array(twists)[:, :3], axis=1)
    assert speeds.max() <= 0.5 + 1e-12
    assert np.abs(np.diff(speeds)).max() <= 4.0 * DT_S + 1e-12


def test_higher_gain_tracks_faster():
    errors = []
    for gain in (300.0, 1200.0):
        motion = TcpMotion(START)
        target = START.copy()
        target[0] += 0.005  # small enough that the speed and acceleration limits never bind
        motion.servo(target, lookahead_s=0.1, gain=gain)
        run(motion, 0.1)
        errors.append(abs(target[0] - motion.pose()[0]))
    assert errors[1] < 0.5 * errors[0]


def test_speed_ramps_then_holds_and_time_limit_stops():
    motion = TcpMotion(START)
    motion.speed(np.array([0.0, 0.0, 0.1, 0.0, 0.0, 0.0]), accel_m_s2=0.5)
    run(motion, 1.0)
    # 0.2 s ramp covers 0.01 m, then 0.8 s at 0.1 m/s
    assert motion.pose()[2] - START[2] == pytest.approx(0.09, abs=2e-3)
    np.testing.assert_allclose(motion.twist(), [0, 0, 0.1, 0, 0, 0], atol=1e-12)
    motion.speed(np.array([0.1, 0.0, 0.0, 0.0, 0.0, 0.0]), accel_m_s2=1.0, time_s=0.2)
    run(motion, 0.6)
    assert motion.mode == MotionMode.HOLD
    np.testing.assert_array_equal(motion.twist(), np.zeros(6))


def test_linear_move_ends_exactly_on_target_in_the_expected_time():
    motion = TcpMotion(START)
    target = START.copy()
    target[:3] += [0.12, 0.0, -0.05]
    motion.move(target, speed_m_s=0.25, accel_m_s2=1.2)
    steps = 0
    while motion.busy:
        motion.step(DT_S)
        steps += 1
        assert steps < 5000
    np.testing.assert_array_equal(motion.pose(), target)
    length = 0.13
    expected_s = length / 0.25 + 0.25 / 1.2  # trapezoid: cruise time plus one ramp
    assert steps * DT_S == pytest.approx(expected_s, rel=0.05)


def test_stop_decelerates_at_the_given_rate():
    motion = TcpMotion(START)
    motion.speed(np.array([0.2, 0.0, 0.0, 0.0, 0.0, 0.0]), accel_m_s2=10.0)
    run(motion, 0.1)
    x0 = motion.pose()[0]
    motion.stop(decel_m_s2=2.0)
    steps = 0
    while motion.busy:
        motion.step(DT_S)
        steps += 1
    assert steps * DT_S == pytest.approx(0.1, abs=2 * DT_S)  # 0.2 m/s at 2 m/s^2
    assert motion.pose()[0] - x0 == pytest.approx(0.01, rel=0.05)  # v^2 / 2a
    assert motion.mode == MotionMode.HOLD
    motion.stop(decel_m_s2=2.0)
    assert not motion.busy  # stopping at rest is a no-op


def test_imposed_pose_keeps_the_command():
    motion = TcpMotion(START)
    target = START.copy()
    target[0] += 0.05
    motion.servo(target, lookahead_s=0.05, gain=300.0)
    pushed = START.copy()
    pushed[1] += 0.01
    motion.impose_pose(pushed)
    assert motion.pose()[1] == pytest.approx(pushed[1])
    run(motion, 1.0)
    assert motion.mode == MotionMode.SERVO
    np.testing.assert_allclose(motion.pose()[:3], target[:3], atol=1e-4)


def test_limits_are_checked():
    with pytest.raises(ValueError, match="max_speed_m_s must be positive"):
        MotionLimits(max_speed_m_s=0.0)
    with pytest.raises(ValueError, match="max_accel_m_s2"):
        MotionLimits(max_accel_m_s2=math.inf)
