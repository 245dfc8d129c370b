"""The arm commander's safety rules, without sockets: every limit fires, and only past its bound."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hydrosoft.services.config import LimitsConfig
from hydrosoft.services.safety import (NO_TARGET, check_target, interpolate, is_moving, outside_workspace,
                                      rotation_angle_rad, watchdog)

LIMITS = LimitsConfig(workspace_min=(-0.1, -0.1, 0.0), workspace_max=(0.1, 0.1, 0.2), max_speed_m_s=0.1,
                      max_angular_speed_rad_s=1.0, max_force_n=20.0, heartbeat_timeout_s=0.5, state_timeout_s=0.2)
HOME = np.array([0.0, 0.0, 0.1, 1.0, 0.0, 0.0, 0.0])
S = 1_000_000_000


def about_z(angle_rad: float, position=(0.0, 0.0, 0.1)) -> np.ndarray:
    return np.array([*position, math.cos(angle_rad / 2), 0.0, 0.0, math.sin(angle_rad / 2)])


@pytest.mark.parametrize("axis", range(3))
def test_targets_outside_the_box_on_any_side_are_refused(axis):
    inside_edge = HOME.copy()
    inside_edge[axis] = LIMITS.workspace_max[axis]
    assert check_target(inside_edge, LIMITS) is None
    assert outside_workspace(inside_edge[:3], LIMITS) is None  # the planner's check of where a goal takes the arm
    for bound, sign in ((LIMITS.workspace_max, 1), (LIMITS.workspace_min, -1)):
        outside = HOME.copy()
        outside[axis] = bound[axis] + sign * 1e-6
        assert "outside the workspace" in check_target(outside, LIMITS)
        assert outside_workspace(outside[:3], LIMITS) == check_target(outside, LIMITS)


def test_malformed_targets_are_refused():
    assert check_target(HOME, LIMITS) is None
    assert "non-finite" in check_target([np.nan, 0, 0.1, 1, 0, 0, 0], LIMITS)
    assert "non-finite" in check_target([0, 0, 0.1, np.inf, 0, 0, 0], LIMITS)
    assert "norm" in check_target([0, 0, 0.1, 1.001, 0, 0, 0], LIMITS)
    assert "norm" in check_target([0, 0, 0.1, 0, 0, 0, 0], LIMITS)
    assert "shape" in check_target(np.zeros(6), LIMITS)


def test_interpolation_moves_at_most_max_speed_along_the_straight_line_and_arrives():
    target = HOME + [0.05, 0.03, 0.0, 0, 0, 0, 0]
    dt_s = 0.008
    pose, steps = HOME, 0
    while not np.array_equal(pose, target):
        nxt = interpolate(pose, target, dt_s, LIMITS)
        assert np.linalg.norm(nxt[:3] - pose[:3]) <= LIMITS.max_speed_m_s * dt_s + 1e-15
        assert np.linalg.norm(np.cross(nxt[:3] - HOME[:3], target[:3] - HOME[:3])) < 1e-15  # on the line
        pose, steps = nxt, steps + 1
        assert steps < 1000
    assert steps == math.ceil(np.linalg.norm(target[:3] - HOME[:3]) / (LIMITS.max_speed_m_s * dt_s))


def test_interpolation_turns_at_most_max_angular_speed_the_short_way():
    step = interpolate(HOME, about_z(1.0), 0.01, LIMITS)
    assert math.isclose(rotation_angle_rad(HOME[3:], step[3:]), 0.01, rel_tol=1e-9)
    assert step[6] > 0  # towards +z
    flipped = -about_z(1.0)[3:]  # the same orientation with the other sign: still the short way, +0.01 rad
    step = interpolate(HOME, np.concatenate([HOME[:3], flipped]), 0.01, LIMITS)
    assert math.isclose(rotation_angle_rad(HOME[3:], step[3:]), 0.01, rel_tol=1e-9) and step[6] * step[3] > 0


def test_the_binding_limit_sets_one_fraction_for_position_and_orientation():
    target = about_z(0.5, position=(0.01, 0.0, 0.1))  # 10 mm (0.1 s at max speed) and 0.5 rad (0.5 s)
    step = interpolate(HOME, target, 0.01, LIMITS)
    assert math.isclose(rotation_angle_rad(HOME[3:], step[3:]), 0.01, rel_tol=1e-9)
    assert math.isclose(step[0], 0.01 * 0.01 / 0.5, rel_tol=1e-9)  # the same fraction (2 %) of the way


def test_the_watchdog_passes_a_healthy_arm_and_fires_on_each_rule():
    now = 10 * S
    ok = dict(target_deadline_ns=now + S // 10, heartbeat_stamp_ns=now - S // 10, state_stamp_ns=now - S // 100,
              force_n=5.0)

    def why(**changes):
        return watchdog(now, **{**ok, **changes}, limits=LIMITS)

    assert why() is None
    assert why(target_deadline_ns=None) == NO_TARGET
    assert why(target_deadline_ns=now) is None and "deadline passed" in why(target_deadline_ns=now - 1)
    assert "no planner heartbeat" in why(heartbeat_stamp_ns=None)
    assert why(heartbeat_stamp_ns=now - S // 2) is None
    assert "heartbeat 0.501 s old" in why(heartbeat_stamp_ns=now - S // 2 - S // 1000)
    assert "no arm state" in why(state_stamp_ns=None)
    assert why(state_stamp_ns=now - S // 5) is None
    assert "not advancing" in why(state_stamp_ns=now - S // 5 - 1)
    assert why(force_n=20.0) is None and "above the limit" in why(force_n=20.01)
    assert "above the limit" in why(force_n=float("nan"))
    assert why(force_n=None) == "no fresh F/T reading"


def test_moving_is_judged_on_linear_and_angular_speed():
    assert not is_moving(np.zeros(6))
    assert not is_moving([0.001, 0, 0, 0, 0, 0.005])
    assert is_moving([0, 0.003, 0, 0, 0, 0])
    assert is_moving([0, 0, 0, 0.02, 0, 0])
