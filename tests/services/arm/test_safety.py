"""The arm commander's safety rules, without sockets: every limit fires, and only past its bound."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hydrosoft.services.bus.config import LIMIT_BOUNDS, ConfigError, LimitsConfig
from hydrosoft.services.arm.safety import (NO_TARGET, check_path, check_target, clamped_deadline_ns, interpolate,
                                      is_moving, outside_workspace, retreat_refusal, rotation_angle_rad,
                                      tilt_and_yaw_deg, watchdog)

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
    assert why(force_n=None) == "no fresh F/T reading"
    assert why(plan_done_ns=now - 2 * S) is None  # the default max_plan_age_s
    assert "no plan completed for 2.001 s" in why(plan_done_ns=now - 2 * S - S // 1000)


TOOL_DOWN = np.array([0.0, 0.0, 1.0, 0.0])  # a half turn about y: the tool z axis points down
ORIENTED = LimitsConfig(max_tilt_deg=20.0, yaw_range_deg=(-90.0, 45.0))


def quat(axis, angle_deg: float) -> np.ndarray:
    half = math.radians(angle_deg) / 2
    return np.array([math.cos(half), *(math.sin(half) * np.asarray(axis, dtype=np.float64))])


def turned(q_first: np.ndarray, q_then: np.ndarray) -> np.ndarray:
    """``q_first`` then ``q_then`` about the tool's own axes."""
    w0, x0, y0, z0 = q_first
    w1, x1, y1, z1 = q_then
    return np.array([w0 * w1 - x0 * x1 - y0 * y1 - z0 * z1, w0 * x1 + x0 * w1 + y0 * z1 - z0 * y1,
                     w0 * y1 - x0 * z1 + y0 * w1 + z0 * x1, w0 * z1 + x0 * y1 - y0 * x1 + z0 * w1])


def test_tilt_and_yaw_are_measured_from_the_nominal_tool_orientation():
    assert tilt_and_yaw_deg(TOOL_DOWN, TOOL_DOWN) == pytest.approx((0.0, 0.0))
    assert tilt_and_yaw_deg(turned(TOOL_DOWN, quat([1, 0, 0], 25.0)), TOOL_DOWN)[0] == pytest.approx(25.0)
    assert tilt_and_yaw_deg(turned(TOOL_DOWN, quat([0, 0, 1], -60.0)), TOOL_DOWN) == pytest.approx((0.0, -60.0))
    assert tilt_and_yaw_deg([1.0, 0.0, 0.0, 0.0], TOOL_DOWN)[0] == pytest.approx(180.0)  # flipped: tool z up


def test_a_flipped_or_tilted_tool_and_a_yaw_outside_the_range_are_refused_at_any_height():
    position = [0.0, 0.0, 0.0]  # the lowest height of the box
    ok = np.concatenate([position, turned(TOOL_DOWN, quat([0, 1, 0], 19.9))])
    assert check_target(ok, ORIENTED, TOOL_DOWN) is None
    flipped = np.concatenate([position, [1.0, 0.0, 0.0, 0.0]])
    assert "tilted 180.0 deg" in check_target(flipped, ORIENTED, TOOL_DOWN)
    assert "tilted 20.1 deg" in check_target(np.concatenate([position, turned(TOOL_DOWN, quat([1, 1, 0] / np.sqrt(2),
                                                                                              20.1))]),
                                             ORIENTED, TOOL_DOWN)
    for yaw, allowed in ((-90.0, True), (-90.5, False), (45.0, True), (45.5, False)):
        pose = np.concatenate([position, turned(TOOL_DOWN, quat([0, 0, 1], yaw))])
        assert (check_target(pose, ORIENTED, TOOL_DOWN) is None) == allowed, yaw


def test_a_straight_move_is_refused_when_it_starts_outside_the_box_or_the_orientation_limits():
    target = np.concatenate([[0.0, 0.0, 0.1], TOOL_DOWN])
    assert check_path(target, target, ORIENTED, TOOL_DOWN) is None
    below = np.concatenate([[0.0, 0.0, -0.01], TOOL_DOWN])  # the arm below the box: its move up would cross it
    assert "path starts outside" in check_path(below, target, ORIENTED, TOOL_DOWN)
    tilted = np.concatenate([[0.0, 0.0, 0.1], turned(TOOL_DOWN, quat([1, 0, 0], 40.0))])
    assert "tilted 40.0 deg" in check_path(tilted, target, ORIENTED, TOOL_DOWN)


def test_over_the_force_limit_only_a_move_along_the_contact_force_is_a_retreat():
    current = np.concatenate([[0.0, 0.0, 0.1], TOOL_DOWN])
    up_in_tcp = [0.0, 0.0, -30.0]  # the table pushes the bubble up: base +z is the tool's -z
    up = current + [0, 0, 0.005, 0, 0, 0, 0]
    assert retreat_refusal(current, up, up_in_tcp) is None
    assert "off the direction" in retreat_refusal(current, current - [0, 0, 0.005, 0, 0, 0, 0], up_in_tcp)  # pushes
    assert "off the direction" in retreat_refusal(current, current + [0.005, 0, 0, 0, 0, 0, 0], up_in_tcp)  # slides
    assert retreat_refusal(current, current + [0.005, 0, 0.006, 0, 0, 0, 0], up_in_tcp) is None  # 40 deg off: away
    assert "does not move" in retreat_refusal(current, current, up_in_tcp)
    turning = np.concatenate([up[:3], turned(TOOL_DOWN, quat([1, 0, 0], 5.0))])
    assert "turns the tool" in retreat_refusal(current, turning, up_in_tcp)


def test_a_deadline_is_clamped_to_the_longest_lead_after_arrival():
    limits = LimitsConfig(max_target_lead_s=0.5)
    arrived = 100 * S
    assert clamped_deadline_ns(arrived + S // 4, arrived, limits) == arrived + S // 4
    assert clamped_deadline_ns(arrived + 10**12, arrived, limits) == arrived + S // 2


def test_moving_is_judged_on_linear_and_angular_speed():
    assert not is_moving(np.zeros(6))
    assert not is_moving([0.001, 0, 0, 0, 0, 0.005])
    assert is_moving([0, 0.003, 0, 0, 0, 0])
    assert is_moving([0, 0, 0, 0.02, 0, 0])


@pytest.mark.parametrize("name", [name for name in LIMIT_BOUNDS if name != "max_yaw_deg"])
def test_every_limit_has_an_upper_bound(name):
    bound = LIMIT_BOUNDS[name]
    others = {"idle_rate_hz": 1.0} if name == "servo_rate_hz" else {}
    if name == "heartbeat_timeout_s":  # planner_lost_s may not lie below it
        others = {"planner_lost_s": LIMIT_BOUNDS["planner_lost_s"]}
    LimitsConfig(**{name: bound, **others, **({"servo_rate_hz": bound} if name == "idle_rate_hz" else {})})
    with pytest.raises(ConfigError, match=f"limits.{name}: must be at most {bound}"):
        LimitsConfig(**{name: bound * 1.01, **others})


def test_the_release_level_lies_below_the_force_limit_and_the_yaw_range_is_ordered():
    assert LimitsConfig(max_force_n=40.0).release_level_n == 30.0
    assert LimitsConfig(max_force_n=40.0, release_force_n=10.0).release_level_n == 10.0
    with pytest.raises(ConfigError, match="release_force_n"):
        LimitsConfig(max_force_n=40.0, release_force_n=40.0)
    with pytest.raises(ConfigError, match="yaw_range_deg"):
        LimitsConfig(yaw_range_deg=(10.0, -10.0))
    with pytest.raises(ConfigError, match="workspace_max"):
        LimitsConfig(workspace_min=(-1.0, 0.0, 0.0), workspace_max=(1.0, 0.1, 0.1))


def test_planner_lost_s_lies_at_or_above_the_heartbeat_timeout():
    assert LimitsConfig(heartbeat_timeout_s=0.5, planner_lost_s=0.5).planner_lost_s == 0.5
    with pytest.raises(ConfigError, match="limits.planner_lost_s: must be at least heartbeat_timeout_s"):
        LimitsConfig(heartbeat_timeout_s=0.5, planner_lost_s=0.4)
