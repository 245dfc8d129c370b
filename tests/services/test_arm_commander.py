"""The arm commander: its decisions without sockets, then the real service process driving a simulated UR controller.

The process tests run ``python -m hydrosoft.services.arm_commander CONFIG`` against a simulated controller
subprocess (``python -m hydrosoft.drivers.ur.simulator``) on a 127.0.0.N of their own, with a config written to
tmp. The test plays the planner (targets, heartbeats) and the F/T reader (wrenches) on their endpoints and reads
the TCP through the simulator's inspection port. Every wait has a timeout; every process is stopped by its pid.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import selectors
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import msgspec
import numpy as np
import pytest

from hydrosoft.drivers.base import ArmState
from hydrosoft.drivers.ur.config import DASHBOARD_PORT, SIM_CONTROL_PORT, URArmConfig
from hydrosoft.services.commands import arm as arm_enable
from hydrosoft.services.bus import messages as msg
from hydrosoft.services.arm_commander import (EXIT_STOP_UNCONFIRMED, FT_LOST, HOLD, MAX_STEP_PERIODS, NO_TARGET,
                                             PLANNER_LOST, UNTARED_FT, ServoLogic, driver_config)
from hydrosoft.services.bus.sockets import Bus, LatestSubscriber, Publisher, Stale
from hydrosoft.services.bus.config import LimitsConfig, load_config
from loopback import free_ur_host

# --- the decisions, without sockets --------------------------------------------------------------------------------

LIMITS = LimitsConfig(workspace_min=(0.1, -0.4, 0.1), workspace_max=(0.5, 0.0, 0.5), max_speed_m_s=0.1,
                      max_angular_speed_rad_s=1.0, max_force_n=40.0, servo_rate_hz=125.0, heartbeat_timeout_s=0.3,
                      planner_lost_s=0.6, state_timeout_s=0.2, max_target_lead_s=0.5, max_plan_age_s=0.6)
HOME = np.array([0.3, -0.2, 0.4, 0.0, 0.0, 1.0, 0.0])  # the simulator's default TCP: 0.4 m up, tool down
S = 1_000_000_000
PERIOD_NS = S // 125
T0 = 100 * S


GOAL_NS = T0 - S  # the played goal's start: after the commander's (0)


def target(pose, stamp_ns: int, lead_s: float = 1.0, arm: str = "bubble", goal_ns: int = GOAL_NS,
           plan_done_ns: int | None = None) -> msg.ArmTarget:
    return msg.ArmTarget(arm=arm, tcp_pose=np.asarray(pose, dtype=np.float64), deadline_ns=stamp_ns + int(lead_s * S),
                         plan_seq=1, seq=1, stamp_ns=stamp_ns, source="planner", goal_started_ns=goal_ns,
                         plan_done_ns=stamp_ns if plan_done_ns is None else plan_done_ns)


def state(now_ns: int, pose=HOME, speed=np.zeros(6), controller_stop: str = "", safety_flags=(),
          link_since_ns: int = 0) -> ArmState:
    return ArmState(tcp_pose=np.asarray(pose, dtype=np.float64), tcp_speed=np.asarray(speed, dtype=np.float64),
                    running=not controller_stop, protective_stop="protective stop" in safety_flags,
                    emergency_stop=False, stamp_ns=now_ns, hw_stamp_ns=now_ns, controller_stop=controller_stop,
                    safety_flags=tuple(safety_flags), link_since_ns=link_since_ns)


def step(logic: ServoLogic, now_ns: int, pose=HOME, speed=np.zeros(6), heartbeat_ns=None, force=(0.0, 0.0, 0.0),
         reading: ArmState | None = None, **kwargs):
    reading = state(now_ns, pose, speed) if reading is None else reading
    logic.observe(reading)
    return logic.decide(now_ns, reading, None, now_ns if heartbeat_ns is None else heartbeat_ns,
                        None if force is None else np.asarray(force, dtype=np.float64), **kwargs)


def new_logic(limits: LimitsConfig = LIMITS) -> ServoLogic:
    return ServoLogic(limits, "bubble", HOME[3:], started_ns=0)


def servoing_logic(limits: LimitsConfig = LIMITS) -> ServoLogic:
    logic = new_logic(limits)
    assert logic.offer(target(HOME + [0.1, 0, 0, 0, 0, 0, 0], T0), T0) is None
    assert step(logic, T0).command is not None
    return logic


def test_servo_commands_step_from_the_measured_pose_then_from_the_last_command():
    logic = new_logic(msgspec.structs.replace(LIMITS, max_target_lead_s=1.0))  # the late tick lies 0.5 s on
    first = step(logic, T0)
    assert first.command is None and first.reason == NO_TARGET and not first.stop
    logic.offer(target(HOME + [0.1, 0, 0, 0, 0, 0, 0], T0), T0)
    a = step(logic, T0, pose=HOME + [0.001, 0, 0, 0, 0, 0, 0])
    b = step(logic, T0 + PERIOD_NS, pose=HOME)  # the arm lags: the next step still starts at the last command
    assert a.reason == "" and logic.servoing
    assert np.isclose(a.command[0] - HOME[0], 0.001 + 0.1 / 125) and np.isclose(b.command[0] - a.command[0], 0.1 / 125)
    burst = step(logic, T0 + PERIOD_NS + S // 1000)  # a tick right after the last: a step for 1 ms only
    assert np.isclose(burst.command[0] - b.command[0], 0.1 * 0.001)
    late = step(logic, T0 + PERIOD_NS + S // 2)  # a tick 0.5 s late moves no further than two periods allow
    assert np.isclose(late.command[0] - burst.command[0], 2 * 0.1 / 125)


def test_a_refused_target_stops_the_arm_and_drops_the_valid_one():
    logic = servoing_logic()
    kind, reason = logic.offer(target(HOME + [0.5, 0, 0, 0, 0, 0, 0], T0 + 1), T0 + 1)
    assert kind == "target_refused" and "outside the workspace" in reason
    decision = step(logic, T0 + PERIOD_NS)
    assert decision.command is None and decision.stop and decision.reason.startswith("target refused")
    assert logic.target is None
    assert "not 'bubble'" in logic.offer(target(HOME, T0 + 2, arm="other"), T0 + 2)[1]


def test_a_stop_spends_the_target_and_only_a_fresh_target_with_fresh_inputs_resumes():
    logic = servoing_logic()
    decision = step(logic, T0 + PERIOD_NS, force=None)
    assert decision.stop and decision.reason == "no fresh F/T reading"
    assert logic.offer(target(HOME + [0.1, 0, 0, 0, 0, 0, 0], T0), T0) is None  # the same target again: ignored
    assert step(logic, T0 + 2 * PERIOD_NS).command is None  # a fresh F/T reading, no fresh target: hold
    assert logic.reason == "no fresh F/T reading" and logic.owner == "stack"
    logic.offer(target(HOME + [0.1, 0, 0, 0, 0, 0, 0], T0 + 3 * PERIOD_NS), T0 + 3 * PERIOD_NS)  # fresh target,
    assert step(logic, T0 + 3 * PERIOD_NS, force=None).command is None  # the F/T silent again: spent
    assert step(logic, T0 + 4 * PERIOD_NS).command is None
    logic.offer(target(HOME + [0.1, 0, 0, 0, 0, 0, 0], T0 + 5 * PERIOD_NS), T0 + 5 * PERIOD_NS)
    assert step(logic, T0 + 5 * PERIOD_NS).command is not None


def test_the_stop_is_sent_once_and_again_only_when_the_arm_moves():
    logic = servoing_logic()
    late_ns = T0 + int(1.1 * S)  # past the 1 s deadline
    moving = np.array([0.05, 0, 0, 0, 0, 0])
    assert step(logic, late_ns, speed=moving).stop
    assert not step(logic, late_ns + PERIOD_NS, speed=moving, stopping=True).stop  # its stop is still in flight
    assert not step(logic, late_ns + 2 * PERIOD_NS).stop  # at rest
    assert step(logic, late_ns + 3 * PERIOD_NS, speed=moving).stop  # pushed or drifting: stop again
    assert "deadline passed" in logic.reason


def test_only_a_held_arm_at_rest_with_no_target_and_no_stop_in_flight_counts_as_idle():
    logic = new_logic()
    moving = np.array([0.05, 0, 0, 0, 0, 0])
    assert logic.holding_at_rest(state(T0), stopping=False)
    assert not logic.holding_at_rest(state(T0, speed=moving), stopping=False)  # drifting: watch it at full rate
    assert not logic.holding_at_rest(state(T0), stopping=True)
    assert not logic.holding_at_rest(None, stopping=False)  # the driver failed: keep trying at full rate
    logic = servoing_logic()
    assert not logic.holding_at_rest(state(T0), stopping=False)
    logic.halt("deadline passed")  # the stop spends the target
    assert logic.holding_at_rest(state(T0), stopping=False)


def test_driver_errors_a_frozen_state_and_the_force_rules_stop_the_arm():
    logic = servoing_logic()
    decision = logic.decide(T0 + PERIOD_NS, None, "arm driver: stale", T0, 0.0)
    assert decision.stop and decision.reason == "arm driver: stale"

    logic = servoing_logic()
    frozen = state(T0)  # the controller's stamp does not advance
    for k in range(1, 30):
        logic.observe(frozen)
        decision = logic.decide(T0 + k * PERIOD_NS, frozen, None, T0 + k * PERIOD_NS, 0.0)
        if decision.command is None:
            break
    assert "not advancing" in decision.reason and 0.2 * S < k * PERIOD_NS <= 0.2 * S + PERIOD_NS

    logic = servoing_logic()
    assert "over the limit" in step(logic, T0 + PERIOD_NS, force=[0, 0, 40.5]).reason
    logic = servoing_logic()
    assert step(logic, T0 + PERIOD_NS, force=None).reason == "no fresh F/T reading"
    logic = servoing_logic()
    assert step(logic, T0 + PERIOD_NS, force=[0, 0, np.nan]).reason == "no fresh F/T reading"


def test_an_untared_ft_reading_holds_the_arm_whatever_force_it_reads():
    """A wrench the F/T reader could not tare (no stored bias) is off by the sensor's offset: the arm stops with a
    cause that says so, even when the force it reads is small; a fresh target servoes again on tared readings."""
    logic = servoing_logic()
    decision = step(logic, T0 + PERIOD_NS, force=[0.0, 0.0, 0.1], untared=True)
    assert decision.command is None and decision.stop and decision.reason == UNTARED_FT
    assert logic.offer(target(HOME + [0.1, 0, 0, 0, 0, 0, 0], T0 + 2 * PERIOD_NS), T0 + 2 * PERIOD_NS) is None
    assert step(logic, T0 + 2 * PERIOD_NS, force=[0.0, 0.0, 0.1], untared=True).reason == UNTARED_FT
    assert logic.offer(target(HOME + [0.1, 0, 0, 0, 0, 0, 0], T0 + 3 * PERIOD_NS), T0 + 3 * PERIOD_NS) is None
    assert step(logic, T0 + 3 * PERIOD_NS, force=[0.0, 0.0, 0.1]).command is not None


def test_a_fresh_target_during_a_stop_waits_for_its_end():
    logic = servoing_logic()
    late_ns = T0 + int(1.1 * S)
    step(logic, late_ns)
    logic.offer(target(HOME, late_ns), late_ns)
    decision = step(logic, late_ns + PERIOD_NS, stopping=True)
    assert decision.command is None and "deadline passed" in decision.reason
    assert step(logic, late_ns + 2 * PERIOD_NS).command is not None


def test_an_external_stop_latches_until_a_person_enables_and_only_a_new_goal_moves_the_arm():
    logic = servoing_logic()
    paused = state(T0 + PERIOD_NS, controller_stop="program paused")
    decision = step(logic, T0 + PERIOD_NS, reading=paused)
    assert decision.command is None and decision.stop and logic.owner == "external"
    assert "external stop: program paused" in decision.reason and logic.external == "program paused"
    for k in range(2, 10):  # the controller plays again (someone pressed play), targets keep coming: held
        now = T0 + k * PERIOD_NS
        logic.offer(target(HOME + [0.1, 0, 0, 0, 0, 0, 0], now), now)
        assert step(logic, now).command is None and logic.owner == "external"
    protective = state(T0, controller_stop="protective stop", safety_flags=("protective stop",))
    assert "protective stop" in ServoLogic.enable_refusal(protective)
    assert ServoLogic.enable_refusal(state(T0, controller_stop="robot mode POWER_OFF")).startswith("the controller")
    assert ServoLogic.enable_refusal(None) is not None and ServoLogic.enable_refusal(state(T0)) is None
    enabled_ns = T0 + 10 * PERIOD_NS
    assert logic.enable(enabled_ns) == "program paused" and logic.external is None
    now = enabled_ns + PERIOD_NS
    kind, text = logic.offer(target(HOME + [0.1, 0, 0, 0, 0, 0, 0], now), now)  # the goal from before: not acted on
    assert kind == "old_goal" and "arm enable" in text and step(logic, now).command is None
    now += PERIOD_NS
    assert logic.offer(target(HOME + [0.1, 0, 0, 0, 0, 0, 0], now, goal_ns=enabled_ns + 1), now) is None
    assert step(logic, now).command is not None and logic.owner == ""


@pytest.mark.parametrize("cause", ["program stopped", "safeguard stop", "emergency stop", "safety fault",
                                   "robot mode POWER_OFF"])
def test_every_controller_stop_latches_as_external(cause):
    logic = servoing_logic()
    step(logic, T0 + PERIOD_NS, reading=state(T0 + PERIOD_NS, controller_stop=cause))
    assert logic.owner == "external" and cause in logic.reason and "arm enable bubble" in logic.reason


def test_goals_started_before_the_commander_or_its_last_reconnect_do_not_move_the_arm():
    logic = ServoLogic(LIMITS, "bubble", HOME[3:], started_ns=T0)  # a commander (re)started at T0
    kind, text = logic.offer(target(HOME + [0.1, 0, 0, 0, 0, 0, 0], T0 + 1, goal_ns=T0 - S), T0 + 1)
    assert kind == "old_goal" and "the commander's start" in text
    assert step(logic, T0 + PERIOD_NS).command is None
    assert logic.offer(target(HOME + [0.1, 0, 0, 0, 0, 0, 0], T0 + 2, goal_ns=T0 + 1), T0 + 2) is None
    assert step(logic, T0 + 2 * PERIOD_NS).command is not None
    reconnected = state(T0 + 3 * PERIOD_NS, link_since_ns=T0 + 3 * PERIOD_NS - 1)
    assert step(logic, T0 + 3 * PERIOD_NS, reading=reconnected).command is None  # the target is void
    kind, text = logic.offer(target(HOME + [0.1, 0, 0, 0, 0, 0, 0], T0 + 4 * PERIOD_NS, goal_ns=T0 + 1),
                             T0 + 4 * PERIOD_NS)
    assert kind == "old_goal" and "reconnect" in text


def test_a_refused_target_holds_the_arm_for_the_rest_of_its_goal():
    logic = servoing_logic()
    now = T0 + PERIOD_NS
    assert logic.offer(target(HOME + [0.5, 0, 0, 0, 0, 0, 0], now), now)[0] == "target_refused"
    step(logic, now)
    now += PERIOD_NS
    assert logic.offer(target(HOME + [0.05, 0, 0, 0, 0, 0, 0], now), now)[0] == "old_goal"  # same goal: held
    assert step(logic, now).command is None
    now += PERIOD_NS
    assert logic.offer(target(HOME + [0.05, 0, 0, 0, 0, 0, 0], now, goal_ns=GOAL_NS + 1), now) is None
    assert step(logic, now).command is not None


def test_a_lost_planner_heartbeat_ends_the_goal_and_only_a_new_goal_moves_the_arm():
    logic = servoing_logic()
    now = T0 + PERIOD_NS
    decision = step(logic, now, heartbeat_ns=T0 - int(0.61 * S))  # fresh at T0, past planner_lost_s now: lost
    assert decision.stop and decision.command is None
    assert "planner lost" in decision.reason and "heartbeat" in decision.planner_lost
    assert logic.goal_floor_ns == now and logic.goal_floor_cause == PLANNER_LOST
    for k in (2, 3):  # the planner runs on: fresh heartbeats and its goal's next targets
        now = T0 + k * PERIOD_NS
        kind, text = logic.offer(target(HOME + [0.1, 0, 0, 0, 0, 0, 0], now), now)
        assert kind == "old_goal" and PLANNER_LOST in text
        held = step(logic, now)
        assert held.command is None and not held.planner_lost and PLANNER_LOST in held.reason
    now += PERIOD_NS
    assert logic.offer(target(HOME + [0.1, 0, 0, 0, 0, 0, 0], now, goal_ns=now - 1), now) is None  # a new goal
    assert step(logic, now).command is not None


def test_a_planner_frozen_past_its_targets_deadline_still_ends_its_goal():
    """A frozen planner's last target expires first (its lead under the heartbeat timeout): the stop for the
    deadline drops the target, and the heartbeat going stale afterwards still ends the goal."""
    logic = new_logic()
    assert logic.offer(target(HOME + [0.1, 0, 0, 0, 0, 0, 0], T0, lead_s=0.2), T0) is None
    assert step(logic, T0, heartbeat_ns=T0).command is not None
    expired = step(logic, T0 + int(0.25 * S), heartbeat_ns=T0)
    assert expired.stop and "deadline passed" in expired.reason and not expired.planner_lost
    stale = step(logic, T0 + int(0.35 * S), heartbeat_ns=T0)  # stale, not yet lost: the goal still stands
    assert not stale.planner_lost and logic.goal_floor_cause != PLANNER_LOST
    lost = step(logic, T0 + int(0.65 * S), heartbeat_ns=T0)  # no target, and the heartbeat past planner_lost_s
    assert lost.planner_lost and "planner lost" in lost.reason and logic.owner == "stack"
    thawed = T0 + int(0.8 * S)
    assert logic.offer(target(HOME + [0.1, 0, 0, 0, 0, 0, 0], thawed), thawed)[0] == "old_goal"
    assert step(logic, thawed).command is None


def test_a_heartbeat_gap_shorter_than_planner_lost_s_stops_the_arm_and_the_goals_next_target_resumes_it():
    """A planner starved for a moment (its heartbeat stale past ``heartbeat_timeout_s``, back before
    ``limits.planner_lost_s``) stops the arm as the watchdog says, but its goal stands."""
    logic = servoing_logic()
    now = T0 + int(0.4 * S)
    gap = step(logic, now, heartbeat_ns=T0)
    assert gap.stop and gap.command is None and "heartbeat" in gap.reason and not gap.planner_lost
    now += PERIOD_NS
    assert logic.offer(target(HOME + [0.1, 0, 0, 0, 0, 0, 0], now), now) is None  # the same goal's next target
    assert step(logic, now, heartbeat_ns=now).command is not None and logic.goal_floor_cause != PLANNER_LOST


def test_f_t_readings_lost_past_sensor_lost_s_end_the_goal_and_a_reader_back_does_not_resume_it():
    """F/T readings missing for a moment stop the arm until the goal's next target; missing for longer than
    ``limits.sensor_lost_s`` (a dead reader, an unplugged sensor) they end every goal started before, so the reader
    coming back moves nothing; a new goal moves the arm."""
    logic = servoing_logic(msgspec.structs.replace(LIMITS, sensor_lost_s=0.5))
    now = T0 + int(0.3 * S)
    gap = step(logic, now, force=None)  # a short gap: the watchdog's stop, the goal stands
    assert gap.stop and "F/T" in gap.reason and not gap.ft_lost and logic.goal_floor_cause != FT_LOST
    now += PERIOD_NS
    assert logic.offer(target(HOME + [0.1, 0, 0, 0, 0, 0, 0], now), now) is None
    assert step(logic, now).command is not None  # readings back: the same goal's next target servoes
    quiet = step(logic, now + int(0.49 * S), force=None)  # none since now, not yet for sensor_lost_s
    assert quiet.stop and not quiet.ft_lost and logic.goal_floor_cause != FT_LOST
    lost_at = now + int(0.51 * S)
    lost = step(logic, lost_at, force=None)
    assert lost.stop is False and lost.command is None  # stopped already at the first missing reading
    assert "F/T readings lost" in lost.ft_lost and "F/T readings lost" in lost.reason
    assert logic.goal_floor_ns == lost_at and logic.goal_floor_cause == FT_LOST
    assert not step(logic, lost_at + PERIOD_NS, force=None).ft_lost  # counted once
    back = lost_at + 2 * PERIOD_NS  # the reader is back, the planner sends the old goal's next target
    kind, text = logic.offer(target(HOME + [0.1, 0, 0, 0, 0, 0, 0], back), back)
    assert kind == "old_goal" and FT_LOST in text
    assert step(logic, back).command is None
    back += PERIOD_NS
    assert logic.offer(target(HOME + [0.1, 0, 0, 0, 0, 0, 0], back, goal_ns=back - 1), back) is None  # a new goal
    assert step(logic, back).command is not None


def test_a_restarted_f_t_reader_ends_the_goal_at_its_first_reading():
    """A reader back within ``limits.sensor_lost_s`` (a fast restart) is still a restart: its wrenches are numbered
    from 1 again, and the goal started before it ends at its first reading."""
    logic = servoing_logic()
    now = T0 + PERIOD_NS
    assert step(logic, now, ft_seq=500).command is not None
    assert step(logic, now + PERIOD_NS, ft_seq=501).command is not None  # numbered on: the same reader
    now += 2 * PERIOD_NS
    restarted = step(logic, now, ft_seq=1)
    assert restarted.stop and restarted.command is None and "reader restarted" in restarted.ft_lost
    assert logic.goal_floor_ns == now and logic.goal_floor_cause == FT_LOST
    now += PERIOD_NS
    assert logic.offer(target(HOME + [0.1, 0, 0, 0, 0, 0, 0], now), now)[0] == "old_goal"
    assert step(logic, now, ft_seq=2).command is None and not step(logic, now + 1, ft_seq=3).ft_lost


def test_f_t_readings_never_seen_since_the_start_end_no_goal():
    """A commander whose F/T reader has not published yet (it starts later) holds the arm, but lost nothing."""
    logic = new_logic(msgspec.structs.replace(LIMITS, sensor_lost_s=0.5))
    assert logic.offer(target(HOME + [0.1, 0, 0, 0, 0, 0, 0], T0), T0) is None
    for k in range(3):
        decision = step(logic, T0 + k * S, force=None)
        assert decision.command is None and not decision.ft_lost
    assert logic.goal_floor_cause != FT_LOST


def test_a_heartbeat_not_seen_yet_holds_the_arm_without_ending_the_goal():
    """A subscriber that has not heard the planner yet (it joined late) lost nothing: its goal moves once the
    heartbeat arrives with a fresh target."""
    logic = new_logic()
    assert logic.offer(target(HOME + [0.1, 0, 0, 0, 0, 0, 0], T0), T0) is None
    logic.observe(state(T0))
    held = logic.decide(T0, state(T0), None, None, np.zeros(3))
    assert held.command is None and held.reason == "no planner heartbeat" and not held.planner_lost
    now = T0 + PERIOD_NS
    assert logic.offer(target(HOME + [0.1, 0, 0, 0, 0, 0, 0], now), now) is None
    assert step(logic, now).command is not None


def test_a_flipped_tool_target_is_refused_and_a_move_from_outside_the_box_is_not_started():
    logic = servoing_logic()
    flipped = np.array([0.3, -0.2, 0.1, 1.0, 0.0, 0.0, 0.0])  # tool z up, at the lowest height of the box
    kind, reason = logic.offer(target(flipped, T0 + 1), T0 + 1)
    assert kind == "target_refused" and "tilted 180.0 deg" in reason
    assert step(logic, T0 + PERIOD_NS).command is None
    logic = new_logic()
    below = HOME - [0, 0, 0.35, 0, 0, 0, 0]  # z = 0.05 m, under the box's 0.1 m
    logic.offer(target(HOME, T0), T0)
    decision = step(logic, T0, pose=below)
    assert decision.command is None and "path starts outside" in decision.refusal


def test_over_the_force_limit_a_retreat_moves_a_push_is_refused_and_release_needs_the_lower_level():
    logic = servoing_logic()  # moving along +x; tool down: the TCP's -z is base +z
    up_n = np.array([0.0, 0.0, -41.0])  # the table pushes the bubble up, over the 40 N limit
    now = T0 + PERIOD_NS
    decision = step(logic, now, force=up_n)
    assert decision.command is None and "over the limit" in decision.reason and "off the direction" in decision.reason
    now += PERIOD_NS
    logic.offer(target(HOME + [0, 0, 0.02, 0, 0, 0, 0], now), now)  # up, away from the table: a retreat
    assert step(logic, now, force=up_n).command is not None
    now += PERIOD_NS
    logic.offer(target(HOME - [0, 0, 0.02, 0, 0, 0, 0], now), now)  # down, into the table: refused
    assert step(logic, now, force=up_n * 35.0 / 41.0).command is None  # 35 N: below the limit, above the release
    now += PERIOD_NS
    logic.offer(target(HOME + [0.05, 0, 0, 0, 0, 0, 0], now), now)
    assert step(logic, now, force=[0.0, 0.0, -31.0]).command is None  # still above the 30 N release level
    now += PERIOD_NS
    logic.offer(target(HOME + [0.05, 0, 0, 0, 0, 0, 0], now), now)
    assert step(logic, now, force=[0.0, 0.0, -29.0]).command is not None  # released: normal servoing


def test_a_target_lead_of_1e12_ns_holds_only_for_max_target_lead_s():
    logic = new_logic()
    logic.offer(target(HOME + [0.1, 0, 0, 0, 0, 0, 0], T0, lead_s=1e3), T0)  # a deadline 1e12 ns ahead
    last_servo_ns = T0
    for k in range(0, int(3 * S / PERIOD_NS)):
        now = T0 + k * PERIOD_NS
        if step(logic, now, reading=state(now)).command is not None:
            last_servo_ns = now
    assert last_servo_ns <= T0 + int(LIMITS.max_target_lead_s * S) and "deadline passed" in logic.reason


def test_a_passed_deadline_while_servoing_is_a_hold_counted_once_and_a_fresh_target_resumes():
    logic = servoing_logic()
    late_ns = T0 + int(0.55 * S)  # past the 0.5 s clamped deadline, the plan 0.55 s old (limit 0.6 s)
    decision = step(logic, late_ns)
    assert decision.stop and decision.command is None and decision.hold_started
    assert decision.reason.startswith(HOLD) and logic.holding and logic.owner == "stack"
    later = [step(logic, late_ns + k * PERIOD_NS) for k in range(1, 5)]  # held: no second count, the cause stays
    assert not any(d.hold_started or d.stop for d in later) and logic.holding and logic.reason == decision.reason
    fresh_ns = late_ns + 5 * PERIOD_NS
    logic.offer(target(HOME + [0.1, 0, 0, 0, 0, 0, 0], fresh_ns), fresh_ns)  # the same goal's next target
    resumed = step(logic, fresh_ns)
    assert resumed.command is not None and resumed.reason == "" and not logic.holding


def test_a_passed_deadline_is_a_stop_not_a_hold_when_another_rule_fires_or_nothing_was_servoed():
    for name, kwargs in [("heartbeat", {"heartbeat_ns": T0 - S}), ("F/T", {"force": None}),
                         ("force", {"force": [0.0, 0.0, -45.0]})]:
        logic = servoing_logic()
        decision = step(logic, T0 + int(0.55 * S), **kwargs)
        assert decision.stop and not decision.hold_started and not logic.holding, name
        assert not decision.reason.startswith(HOLD), name
    logic = servoing_logic()  # the plan's age too
    decision = step(logic, T0 + int(0.61 * S))
    assert decision.stop and not logic.holding and "deadline passed" in decision.reason
    idle = new_logic()  # a target that arrives with its deadline passed was never servoed on
    idle.offer(target(HOME + [0.1, 0, 0, 0, 0, 0, 0], T0 - S, lead_s=0.2), T0)
    decision = step(idle, T0)
    assert decision.command is None and not idle.holding and not decision.hold_started


def test_a_hold_turns_into_the_cause_of_a_later_stop_and_an_external_stop_ends_it():
    logic = servoing_logic()
    step(logic, T0 + int(0.55 * S))
    assert logic.holding
    step(logic, T0 + int(0.56 * S), reading=state(T0 + int(0.56 * S), controller_stop="program paused"))
    assert not logic.holding and logic.owner == "external" and logic.external == "program paused"


def test_a_goal_end_stops_the_arm_naming_the_outcome_until_a_fresh_target():
    logic = servoing_logic()
    now = T0 + PERIOD_NS
    halt = msgspec.structs.replace(target(HOME, now), deadline_ns=now, goal_end="reached")
    assert logic.offer(halt, now) is None
    decision = step(logic, now)
    assert decision.command is None and decision.stop and decision.reason == "goal reached"
    for k in range(1, 40):  # heartbeats stop, the deadline is long gone: the cause stays the goal's end
        step(logic, now + k * PERIOD_NS, heartbeat_ns=T0 - S)
    assert logic.reason == "goal reached" and logic.owner == "stack" and not logic.servoing and not logic.holding
    fresh_ns = now + 40 * PERIOD_NS
    logic.offer(target(HOME + [0.1, 0, 0, 0, 0, 0, 0], fresh_ns, goal_ns=fresh_ns - 1), fresh_ns)
    assert step(logic, fresh_ns).command is not None and logic.reason == ""


def test_a_hung_solve_stops_the_arm_within_max_plan_age_s_while_heartbeats_and_targets_go_on():
    logic = new_logic()
    plan_done_ns = T0
    last_servo_ns = T0
    for k in range(0, int(4 * S / PERIOD_NS)):
        now = T0 + k * PERIOD_NS
        if k % 12 == 0:  # re-sent targets of the last plan, fresh heartbeats (step's default)
            logic.offer(target(HOME + [0.1, 0, 0, 0, 0, 0, 0], now, plan_done_ns=plan_done_ns), now)
        if step(logic, now).command is not None:
            last_servo_ns = now
    assert (last_servo_ns - T0) <= LIMITS.max_plan_age_s * S < (last_servo_ns - T0) + 2 * 12 * PERIOD_NS
    assert "no plan completed" in logic.reason


def test_the_driver_takes_its_speed_rates_and_state_age_from_the_limits():
    config = load_config(Path(__file__).parents[2] / "deploy" / "lab.toml")
    driver = driver_config(config, "bubble")
    assert driver.max_tcp_speed_m_s == config.limits.max_speed_m_s
    assert driver.servo_rate_hz == driver.state_rate_hz == config.limits.servo_rate_hz
    assert driver.max_age_s == config.limits.state_timeout_s and driver.host == config.arms[0].ur_host


# --- the service process against a simulated controller -----------------------------------------------------------

ARM = "bubble"
NAME = f"arm_commander-{ARM}"
SIM_READY_TIMEOUT_S = 10.0
COMMANDER_READY_TIMEOUT_S = 40.0  # imports and connect on two busy cores
PROCESS_STOP_TIMEOUT_S = 5.0
SCENARIO_TIMEOUT_S = 30.0
SOCKET_TIMEOUT_S = 2.0
HEARTBEAT_PERIOD_S = 0.05
WRENCH_PERIOD_S = 0.01
REPLAN_PERIOD_S = 0.1  # the played planner re-sends its target this often
TARGET_LEAD_S = 1.0
IMPOSE_SETTLE_S = 0.05  # after putting the TCP at HOME, how long it must stay there
PROBE_LEAD_S = 0.1  # the target at HOME that shows the commander hears the played planner
ARM_STATE_MAX_AGE_S = 0.1  # the commander publishes every 8 ms, every 40 ms while it holds the arm at rest
IDLE_SETTLE_S = 0.3  # after a stop, until the commander idles
STATUS_MAX_AGE_S = 2.0  # the runtime publishes the status every 1 s
POLL_PERIOD_S = 0.005  # how often the test reads the simulated TCP
AT_REST_M_S = 1e-4
#: Scheduling allowance of the timing bounds on two shared cores (the loop, the bus, the test's own polling), s.
SCHEDULING_SLACK_S = 0.15
#: How long the arm takes to stop from max speed at the driver's stop deceleration, s.
STOP_TIME_S = LIMITS.max_speed_m_s / URArmConfig(host="x").stop_decel_m_s2
SERVO_PERIOD_S = 1.0 / LIMITS.servo_rate_hz
#: Speeds are the simulator's own TCP twist (the test's read stamps would jitter with its scheduling). The simulated
#: servoL tracks each command with a first-order lag (tau = 0.1 s at the driver's lookahead and gain): right after a
#: command that moves the path on by T seconds at its speed, the speed peaks at (T / tau) / (1 - exp(-T / tau)) times
#: the path's speed: 1.04 for one servo period, 1.08 for a late tick's step of MAX_STEP_PERIODS (2) periods, the
#: longest the commander takes; allow that ripple and a little delivery jitter.
SERVO_LAG_S = 0.1
_LONGEST_STEP_S = MAX_STEP_PERIODS * SERVO_PERIOD_S
SERVO_RIPPLE = (_LONGEST_STEP_S / SERVO_LAG_S) / (1 - np.exp(-_LONGEST_STEP_S / SERVO_LAG_S)) - 1 + 0.01


def free_loopback_host() -> str:
    """A free 127.0.0.N for this module's simulated UR controllers (``loopback.free_ur_host``)."""
    return free_ur_host(130, 120)


def wait_for_line(proc: subprocess.Popen, prefix: str, timeout_s: float) -> str:
    """The first stdout line of ``proc`` starting with ``prefix``; TimeoutError after ``timeout_s``."""
    deadline_s = time.monotonic() + timeout_s
    with selectors.DefaultSelector() as selector:
        selector.register(proc.stdout, selectors.EVENT_READ)
        while (left_s := deadline_s - time.monotonic()) > 0:
            if selector.select(left_s):
                line = proc.stdout.readline()
                if line.startswith(prefix):
                    return line
                if not line:
                    raise RuntimeError(f"{proc.args} exited ({proc.wait(PROCESS_STOP_TIMEOUT_S)}) before {prefix!r}")
    raise TimeoutError(f"{proc.args} printed no {prefix!r} within {timeout_s} s")


def stop_process(proc: subprocess.Popen, sig: int = signal.SIGTERM) -> int:
    """Signal ``proc`` by pid, SIGKILL it after ``PROCESS_STOP_TIMEOUT_S``; its exit code."""
    if proc.poll() is None:
        os.kill(proc.pid, sig)
        try:
            proc.wait(PROCESS_STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(PROCESS_STOP_TIMEOUT_S)
    return proc.returncode


class Rig:
    """A simulated controller and the commander process on its own 127.0.0.N, with the config in ``tmp``."""

    def __init__(self, tmp: Path) -> None:
        self.host = free_loopback_host()
        self.wrenches_sent = 0  # the played F/T reader's wrenches so far, over every scenario (``PlayedPlanner``)
        run_dir = tmp / "run"
        run_dir.mkdir()
        self.config_path = tmp / "stack.toml"
        self.config_path.write_text(f"""
run_dir = "{run_dir}"
mode = "sim"
[[arms]]
name = "{ARM}"
ur_host = "{self.host}"
nominal_tcp = {HOME[3:].tolist()}
[limits]
workspace_min = {list(LIMITS.workspace_min)}
workspace_max = {list(LIMITS.workspace_max)}
max_speed_m_s = {LIMITS.max_speed_m_s}
max_force_n = {LIMITS.max_force_n}
servo_rate_hz = {LIMITS.servo_rate_hz}
heartbeat_timeout_s = {LIMITS.heartbeat_timeout_s}
planner_lost_s = {LIMITS.planner_lost_s}
state_timeout_s = {LIMITS.state_timeout_s}
max_target_lead_s = {LIMITS.max_target_lead_s}
max_plan_age_s = {LIMITS.max_plan_age_s}
[planner]
heartbeat_period_s = {HEARTBEAT_PERIOD_S}
""")
        self.config = load_config(self.config_path)
        self.log_path = tmp / "commander.log"
        self.simulator = subprocess.Popen(
            [sys.executable, "-m", "hydrosoft.drivers.ur.simulator", "--host", self.host, "--unlock-delay-s", "0"],
            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        self.commander: subprocess.Popen | None = None
        wait_for_line(self.simulator, "UR simulator ready", SIM_READY_TIMEOUT_S)

    def start_commander(self) -> subprocess.Popen:
        """The commander process, started (and READY) unless it runs already."""
        if self.commander is None or self.commander.poll() is not None:
            with self.log_path.open("a") as log:
                self.commander = subprocess.Popen(
                    [sys.executable, "-m", "hydrosoft.services.arm_commander", str(self.config_path)],
                    stdout=subprocess.PIPE, stderr=log, text=True)
            line = wait_for_line(self.commander, "READY", COMMANDER_READY_TIMEOUT_S)
            assert line.split() == ["READY", NAME, str(self.commander.pid)]
        return self.commander

    def sim_state(self) -> dict:
        """The simulator's inspection snapshot (pose, twist, counters, ...)."""
        with socket.create_connection((self.host, SIM_CONTROL_PORT), timeout=SOCKET_TIMEOUT_S) as conn:
            conn.sendall(b'{"op": "state"}\n')
            return json.loads(conn.makefile().readline())

    def stop(self) -> None:
        for proc in (self.commander, self.simulator):
            if proc is not None:
                stop_process(proc)
                proc.stdout.close()


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    rig = Rig(tmp_path_factory.mktemp("arm_commander"))
    try:
        yield rig
    finally:
        rig.stop()


class SimTcp:
    """The simulated TCP read through the inspection port from asyncio, one persistent connection."""

    def __init__(self, host: str) -> None:
        self.host = host

    async def __aenter__(self) -> SimTcp:
        self._reader, self._writer = await asyncio.wait_for(
            asyncio.open_connection(self.host, SIM_CONTROL_PORT), SOCKET_TIMEOUT_S)
        return self

    async def __aexit__(self, *exc_info) -> None:
        self._writer.close()

    async def request(self, op: str, **fields) -> dict:
        self._writer.write((json.dumps({"op": op, **fields}) + "\n").encode())
        reply = json.loads(await asyncio.wait_for(self._reader.readline(), SOCKET_TIMEOUT_S))
        assert reply["ok"], reply
        return reply

    async def read(self) -> tuple[int, np.ndarray, np.ndarray]:
        """``(now_ns, pose (7,), twist (6,))`` of the simulated TCP."""
        reply = await self.request("state")
        return time.monotonic_ns(), np.array(reply["pose"]), np.array(reply["twist"])


class PlayedPlanner:
    """Plays the planner (targets re-sent every ``REPLAN_PERIOD_S`` towards ``goal``, heartbeats while
    ``heartbeats``) and the F/T reader (a wrench of ``force_n`` along z, none while it is None), and listens to the
    commander's ArmState and status. The F/T reader is one reader over the rig's scenarios: its wrenches are numbered
    on from the last scenario's, as a reader that runs on numbers them (one numbered from 1 again is a restarted
    reader, which ends the commander's goals)."""

    def __init__(self, rig: Rig) -> None:
        config = rig.config
        self.rig = rig
        self.bus = Bus()
        self.targets = Publisher(self.bus, config.endpoint("planner"), source="planner")
        self.health = Publisher(self.bus, config.endpoint("planner", "status"), source="planner")
        self.wrenches = Publisher(self.bus, config.endpoint(f"ft_reader-{ARM}"), source=f"ft_reader-{ARM}")
        self.wrenches.sent[f"wrench/{ARM}"] = rig.wrenches_sent
        self.listener = LatestSubscriber(self.bus, [config.endpoint(NAME), config.endpoint(NAME, "status")],
                                         topics=[f"arm_state/{ARM}", f"status/{NAME}"])
        self.goal: np.ndarray | None = None
        self.goal_started_ns = 0  # the played goal's start: set when the scenario begins, after the commander's
        self.plan_done_ns: int | None = None  # None: each target's plan completed as it is sent
        self.heartbeats = True
        self.force_n: float | None = 0.0
        self.last_heartbeat_ns = 0
        self._tasks: list[asyncio.Task] = []

    async def __aenter__(self) -> PlayedPlanner:
        self.new_goal()
        self._tasks = [asyncio.create_task(coro) for coro in
                       (self.listener.run(), self._heartbeat(), self._wrench(), self._replan())]
        return self

    async def __aexit__(self, *exc_info) -> None:
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        self.rig.wrenches_sent = self.wrenches.sent[f"wrench/{ARM}"]
        self.bus.close()

    async def _heartbeat(self) -> None:
        while True:
            if self.heartbeats:
                sent = await self.health.send(msg.Heartbeat(period_s=HEARTBEAT_PERIOD_S), "heartbeat/planner")
                self.last_heartbeat_ns = sent.stamp_ns
            await asyncio.sleep(HEARTBEAT_PERIOD_S)

    async def _wrench(self) -> None:
        while True:
            if self.force_n is not None:
                await self.wrenches.send(msg.Wrench(sensor=ARM, wrench=np.array([0, 0, self.force_n, 0, 0, 0.0]),
                                                    tared=True), f"wrench/{ARM}")
            await asyncio.sleep(WRENCH_PERIOD_S)

    async def _replan(self) -> None:
        while True:
            if self.goal is not None:
                await self.send_target(self.goal, TARGET_LEAD_S)
            await asyncio.sleep(REPLAN_PERIOD_S)

    def new_goal(self) -> None:
        """A person starts a new goal now: the targets from here on belong to it."""
        self.goal_started_ns = time.monotonic_ns()

    async def send_target(self, pose, lead_s: float) -> msg.ArmTarget:
        now_ns = time.monotonic_ns()
        return await self.targets.send(msg.ArmTarget(
            arm=ARM, tcp_pose=np.asarray(pose, dtype=np.float64), deadline_ns=now_ns + int(lead_s * S),
            plan_seq=1, goal_started_ns=self.goal_started_ns,
            plan_done_ns=now_ns if self.plan_done_ns is None else self.plan_done_ns), f"arm_target/{ARM}")

    def arm_state(self) -> msg.ArmState | None:
        try:
            return self.listener.latest(f"arm_state/{ARM}", ARM_STATE_MAX_AGE_S, msg.ArmState).value
        except Stale:
            return None

    def status(self) -> msg.ServiceStatus | None:
        try:
            return self.listener.latest(f"status/{NAME}", STATUS_MAX_AGE_S, msg.ServiceStatus).value
        except Stale:
            return None


async def until(condition, timeout_s: float, what: str):
    """Poll ``condition()`` every ``POLL_PERIOD_S`` until it returns something truthy; fail after ``timeout_s``."""
    deadline_s = time.monotonic() + timeout_s
    while not (result := condition()):
        assert time.monotonic() < deadline_s, f"{what} did not happen within {timeout_s} s"
        await asyncio.sleep(POLL_PERIOD_S)
    return result


async def start_at_home(planner: PlayedPlanner, tcp: SimTcp) -> None:
    """Wait until the commander holds the arm, put the TCP at HOME, and make sure the commander hears the played
    planner: a short target at HOME (no motion) must make it servo, then stop again at its deadline."""
    await until(lambda: (s := planner.arm_state()) is not None and not s.servo_active, 5.0, "the commander holding")
    deadline_s = time.monotonic() + 2.0
    while True:  # until it stays there: a servo command still under way would pull it back towards its target
        await tcp.request("impose_pose", pose=HOME.tolist())
        await asyncio.sleep(IMPOSE_SETTLE_S)
        _, pose, twist = await tcp.read()
        if np.array_equal(pose, HOME) and not twist.any():
            break
        assert time.monotonic() < deadline_s, "the TCP did not stay at HOME within 2 s"
    await until(lambda: np.allclose(planner.arm_state().tcp_pose, HOME, atol=1e-6), 2.0, "the ArmState at HOME")
    deadline_s = time.monotonic() + 5.0
    while not (arm_state := planner.arm_state()).servo_active:
        assert time.monotonic() < deadline_s, "the commander did not take a target within 5 s"
        if arm_state.goal_floor_ns >= planner.goal_started_ns:  # it lost the last scenario's planner after this
            planner.new_goal()  # goal began: start another, as a person would
        await planner.send_target(HOME, PROBE_LEAD_S)
        await asyncio.sleep(PROBE_LEAD_S / 2)
    await until(lambda: not planner.arm_state().servo_active, 2.0, "the commander holding after the probe")


async def moving_at_speed(tcp: SimTcp, timeout_s: float = 3.0) -> None:
    deadline_s = time.monotonic() + timeout_s
    while np.linalg.norm((await tcp.read())[2][:3]) < 0.8 * LIMITS.max_speed_m_s:
        assert time.monotonic() < deadline_s, f"the TCP did not reach 80 % of max speed within {timeout_s} s"
        await asyncio.sleep(POLL_PERIOD_S)


async def at_rest(tcp: SimTcp, timeout_s: float) -> tuple[int, np.ndarray]:
    """Poll until the TCP is at rest; its ``(now_ns, pose)`` then."""
    deadline_s = time.monotonic() + timeout_s
    while True:
        now_ns, pose, twist = await tcp.read()
        if np.linalg.norm(twist) < AT_REST_M_S:
            return now_ns, pose
        assert time.monotonic() < deadline_s, f"the TCP was not at rest within {timeout_s} s"
        await asyncio.sleep(POLL_PERIOD_S)


def scenario(coro_fn, rig: Rig):
    """Run ``coro_fn(planner, tcp)`` against the running commander, within ``SCENARIO_TIMEOUT_S``."""
    rig.start_commander()

    async def main():
        async with PlayedPlanner(rig) as planner, SimTcp(rig.host) as tcp:
            await start_at_home(planner, tcp)
            return await coro_fn(planner, tcp)

    return asyncio.run(asyncio.wait_for(main(), SCENARIO_TIMEOUT_S))


def test_the_tcp_moves_to_a_valid_target_no_faster_than_max_speed(rig):
    distance_m = 0.1
    goal = HOME + [distance_m, 0, 0, 0, 0, 0, 0]

    async def run(planner: PlayedPlanner, tcp: SimTcp):
        planner.goal = goal
        samples = [await tcp.read()]
        while np.linalg.norm(samples[-1][1][:3] - goal[:3]) > 1e-4:
            assert time.monotonic_ns() - samples[0][0] < 10 * S, "the TCP did not reach the target within 10 s"
            await asyncio.sleep(POLL_PERIOD_S)
            samples.append(await tcp.read())
        return samples, planner.arm_state()

    samples, arm_state = scenario(run, rig)
    poses = np.array([s[1] for s in samples])
    speeds = np.array([np.linalg.norm(s[2][:3]) for s in samples])  # the simulator's own TCP twist
    cruising = speeds[np.abs(poses[:, 0] - HOME[0] - distance_m / 2) < distance_m / 4]  # the middle half of the way
    assert speeds.max() <= LIMITS.max_speed_m_s * (1 + SERVO_RIPPLE), speeds.max()
    # and it uses the speed it may (less while other processes take the loop's CPU: late ticks make short steps)
    assert cruising.mean() > 0.5 * LIMITS.max_speed_m_s, cruising.mean()
    assert np.abs(poses[:, 1:3] - HOME[1:3]).max() < 1e-6  # a straight line along x
    assert arm_state.servo_active and np.allclose(arm_state.tcp_pose[:3], goal[:3], atol=1e-3)


def test_a_target_outside_the_workspace_is_refused_and_never_moved_towards(rig):
    async def run(planner: PlayedPlanner, tcp: SimTcp):
        planner.goal = HOME + [0, -0.1, 0, 0, 0, 0, 0]
        await moving_at_speed(tcp)
        errors_before = (await until(planner.status, 3.0, "a status")).errors.get("target_refused", 0)
        planner.goal = None
        await planner.send_target(HOME + [0.3, 0, 0, 0, 0, 0, 0], TARGET_LEAD_S)  # x = 0.6 m > 0.5 m
        poses = []
        deadline_ns = time.monotonic_ns() + S
        while time.monotonic_ns() < deadline_ns:
            poses.append((await tcp.read())[1])
            await asyncio.sleep(POLL_PERIOD_S)
        _, rest = await at_rest(tcp, 1.0)
        status = await until(lambda: (s := planner.status()) and s.errors.get("target_refused", 0) > errors_before
                             and s, 3.0, "the refusal counted in the status")
        return np.array(poses), rest, planner.arm_state(), status

    poses, rest, arm_state, status = scenario(run, rig)
    assert poses[:, 0].max() <= HOME[0] + 1e-6  # never towards +x
    assert rest[1] > HOME[1] - 0.1 + 0.01  # stopped well short of the valid target it was moving to
    assert not arm_state.servo_active and arm_state.stop_reason.startswith("target refused")
    assert "outside the workspace" in status.last_error


def test_the_arm_stops_when_the_target_deadline_passes(rig):
    """... as a hold: named and counted once as such (``deadline_hold``), not as a fault."""
    lead_s = 0.4

    def status_after(stamp_ns: int):
        return lambda: (s := planner_status()) and s.stamp_ns > stamp_ns and s

    async def run(planner: PlayedPlanner, tcp: SimTcp):
        nonlocal planner_status
        planner_status = planner.status
        before = await until(status_after(time.monotonic_ns()), 3.0, "a status after the probe's hold")
        sent = await planner.send_target(HOME + [0.15, 0, 0, 0, 0, 0, 0], lead_s)
        await moving_at_speed(tcp)
        rest_ns, rest = await at_rest(tcp, 2.0)
        after = await until(status_after(rest_ns), 3.0, "a status after the rest")
        holds = after.errors.get("deadline_hold", 0) - before.errors.get("deadline_hold", 0)
        return sent, rest_ns, rest, planner.arm_state(), holds

    planner_status = None
    sent, rest_ns, rest, arm_state, holds = scenario(run, rig)
    late_s = (rest_ns - sent.deadline_ns) * 1e-9
    assert late_s < SERVO_PERIOD_S + STOP_TIME_S + SCHEDULING_SLACK_S, late_s
    assert rest[0] - HOME[0] < LIMITS.max_speed_m_s * (lead_s + SCHEDULING_SLACK_S)
    assert not arm_state.servo_active and "deadline passed" in arm_state.stop_reason
    assert arm_state.holding and arm_state.stop_reason.startswith(HOLD) and holds == 1


def test_the_arm_stops_in_bounded_time_when_heartbeats_stop_and_only_a_new_goal_moves_it_again(rig):
    bound_s = LIMITS.heartbeat_timeout_s + SERVO_PERIOD_S + STOP_TIME_S + SCHEDULING_SLACK_S

    async def run(planner: PlayedPlanner, tcp: SimTcp):
        planner.goal = HOME + [0.15, 0, 0, 0, 0, 0, 0]
        await moving_at_speed(tcp)
        planner.heartbeats = False
        last_heartbeat_ns = planner.last_heartbeat_ns
        rest_ns, rest = await at_rest(tcp, 2.0)
        planner.goal = None
        reason = planner.arm_state().stop_reason
        # a target re-sent just before the goal was dropped may still be on its way: it must reach the commander
        # (and be spent by the stop) before heartbeats resume, or it is a fresh target that rightly resumes
        await asyncio.sleep(4 * REPLAN_PERIOD_S + 0.2)
        planner.heartbeats = True
        await asyncio.sleep(0.5)
        for _ in range(3):  # the planner runs on: its goal's fresh targets, with fresh heartbeats
            await planner.send_target(HOME, TARGET_LEAD_S)
            await asyncio.sleep(REPLAN_PERIOD_S)
        _, still, twist = await tcp.read()
        held = planner.arm_state()
        status = await until(lambda: (s := planner.status()) and s.errors.get("old_goal", 0) and s, 3.0,
                             "old_goal counted")
        planner.new_goal()
        await planner.send_target(HOME, TARGET_LEAD_S)
        resumed = await until(lambda: (s := planner.arm_state()) and s.servo_active and s, 1.0, "servoing again")
        return (rest_ns - last_heartbeat_ns) * 1e-9, reason, np.linalg.norm(still - rest), held, status, resumed

    latency_s, reason, drift_m, held, status, resumed = scenario(run, rig)
    print(f"last heartbeat to the arm at rest: {latency_s:.3f} s (bound {bound_s:.3f} s)")
    assert LIMITS.heartbeat_timeout_s < latency_s < bound_s, latency_s
    assert "heartbeat" in reason
    assert drift_m < 1e-6 and not held.servo_active  # neither a fresh heartbeat nor its goal's targets resume
    assert held.goal_floor_cause == PLANNER_LOST and PLANNER_LOST in held.stop_reason, held
    assert status.errors.get("planner_lost", 0) >= 1 and status.errors.get("old_goal", 0) >= 1, status.errors
    assert resumed.stop_reason == ""  # a new goal moves the arm


def test_the_arm_stops_when_the_force_exceeds_the_limit_or_the_ft_goes_silent(rig):
    async def run(planner: PlayedPlanner, tcp: SimTcp):
        planner.goal = HOME + [0.15, 0, 0, 0, 0, 0, 0]
        await moving_at_speed(tcp)
        planner.force_n = LIMITS.max_force_n + 1.0
        tic_ns = time.monotonic_ns()
        rest_ns, _ = await at_rest(tcp, 1.0)
        over_limit = planner.arm_state().stop_reason, (rest_ns - tic_ns) * 1e-9
        planner.force_n = 0.0
        await until(lambda: (s := planner.arm_state()) and s.servo_active, 1.0, "servoing again")
        planner.goal = HOME + [0, 0, -0.15, 0, 0, 0, 0]
        await moving_at_speed(tcp)
        planner.force_n = None
        await at_rest(tcp, 1.0)
        return over_limit, planner.arm_state().stop_reason

    (reason, stop_s), silent_reason = scenario(run, rig)
    assert "over the limit" in reason
    assert stop_s < WRENCH_PERIOD_S + SERVO_PERIOD_S + STOP_TIME_S + SCHEDULING_SLACK_S, stop_s
    assert silent_reason == "no fresh F/T reading"


def test_a_held_arm_reads_the_newest_of_all_the_wrenches_that_came_since_its_last_tick(rig):
    burst = 300  # wrenches sent within one idle period, far more than a default subscriber queue holds

    async def run(planner: PlayedPlanner, tcp: SimTcp):
        planner.force_n = None  # the test sends the wrenches itself
        await asyncio.sleep(IDLE_SETTLE_S)
        for _ in range(burst):
            await planner.wrenches.send(msg.Wrench(sensor=ARM, wrench=np.zeros(6), tared=True), f"wrench/{ARM}")
        await asyncio.sleep(0.005)  # the publisher's own queue empties: the last wrench is not dropped there
        over = np.array([0, 0, LIMITS.max_force_n + 1.0, 0, 0, 0.0])
        await planner.wrenches.send(msg.Wrench(sensor=ARM, wrench=over, tared=True), f"wrench/{ARM}")
        sent = await planner.send_target(HOME + [0.01, 0, 0, 0, 0, 0, 0], TARGET_LEAD_S)
        state = await until(lambda: (s := planner.arm_state()) and s.stamp_ns > sent.stamp_ns and (
            s.servo_active or "over the limit" in s.stop_reason) and s, 1.0, "servoing or a stop for the force")
        return state.servo_active, state.stop_reason

    servo_active, reason = scenario(run, rig)
    assert not servo_active and "over the limit" in reason, reason


def test_a_held_arm_is_checked_at_the_idle_rate_and_a_target_wakes_the_commander_at_once(rig):
    trials = 8
    idle_period_s = 1.0 / LIMITS.idle_rate_hz

    async def arm_states(watcher: LatestSubscriber, seen: list[msg.ArmState]) -> None:
        while True:
            await watcher.wait()
            seen.append(watcher.latest(f"arm_state/{ARM}", ARM_STATE_MAX_AGE_S, msg.ArmState).value)

    async def run(planner: PlayedPlanner, tcp: SimTcp):
        seen: list[msg.ArmState] = []
        watcher = LatestSubscriber(planner.bus, rig.config.endpoint(NAME), topics=[f"arm_state/{ARM}"])
        watching = asyncio.create_task(arm_states(watcher, seen))
        try:
            await asyncio.sleep(IDLE_SETTLE_S)
            held = len(seen)
            await asyncio.sleep(1.0)
            held_hz = len(seen) - held
            wakes_ms = []
            for _ in range(trials):
                sent = await planner.send_target(HOME, PROBE_LEAD_S)
                first = await until(lambda: next((s for s in seen if s.servo_active and s.stamp_ns > sent.stamp_ns),
                                                 None), 1.0, "servoing on the target")
                wakes_ms.append((first.stamp_ns - sent.stamp_ns) * 1e-6)
                await until(lambda: not seen[-1].servo_active, 2.0, "holding after the target's deadline")
                await asyncio.sleep(IDLE_SETTLE_S + idle_period_s * np.random.default_rng(len(wakes_ms)).random())
            return held_hz, wakes_ms
        finally:
            watching.cancel()

    held_hz, wakes_ms = scenario(run, rig)
    print(f"held: {held_hz} ArmState/s; target to first servo state: {sorted(np.round(wakes_ms, 1))} ms")
    assert LIMITS.idle_rate_hz / 2 <= held_hz <= 2 * LIMITS.idle_rate_hz < LIMITS.servo_rate_hz, held_hz
    # without the wake a target would wait for the rest of an idle period: uniform over 0-40 ms
    assert np.median(wakes_ms) < idle_period_s * 1e3 / 4, wakes_ms


def test_a_target_lead_of_1e12_ns_stops_the_arm_within_max_target_lead_s(rig):
    async def run(planner: PlayedPlanner, tcp: SimTcp):
        sent = await planner.targets.send(msg.ArmTarget(
            arm=ARM, tcp_pose=HOME + [0.15, 0, 0, 0, 0, 0, 0], deadline_ns=time.monotonic_ns() + 10**12, plan_seq=1,
            goal_started_ns=planner.goal_started_ns, plan_done_ns=time.monotonic_ns()), f"arm_target/{ARM}")
        await moving_at_speed(tcp)
        rest_ns, _ = await at_rest(tcp, 3.0)
        return (rest_ns - sent.stamp_ns) * 1e-9, planner.arm_state()

    rest_s, arm_state = scenario(run, rig)
    assert rest_s < LIMITS.max_target_lead_s + STOP_TIME_S + SCHEDULING_SLACK_S, rest_s
    assert "deadline passed" in arm_state.stop_reason and arm_state.stop_owner == "stack"


def test_a_hung_solve_stops_the_arm_process_within_max_plan_age_s(rig):
    async def run(planner: PlayedPlanner, tcp: SimTcp):
        planner.plan_done_ns = time.monotonic_ns()  # the last solve ended now; targets of it keep coming
        planner.goal = HOME + [0.15, 0, 0, 0, 0, 0, 0]
        await moving_at_speed(tcp)
        rest_ns, _ = await at_rest(tcp, 3.0)
        reason = planner.arm_state().stop_reason
        return (rest_ns - planner.plan_done_ns) * 1e-9, reason, planner.last_heartbeat_ns

    rest_s, reason, last_heartbeat_ns = scenario(run, rig)
    assert rest_s < LIMITS.max_plan_age_s + SERVO_PERIOD_S + STOP_TIME_S + SCHEDULING_SLACK_S, rest_s
    assert "no plan completed" in reason
    assert (time.monotonic_ns() - last_heartbeat_ns) * 1e-9 < 5.0  # the heartbeats went on throughout


def test_a_flipped_tool_target_is_refused_and_never_approached(rig):
    flipped = np.array([HOME[0], HOME[1], LIMITS.workspace_min[2], 1.0, 0.0, 0.0, 0.0])  # tool up, lowest height

    async def run(planner: PlayedPlanner, tcp: SimTcp):
        await planner.send_target(flipped, TARGET_LEAD_S)
        poses = []
        deadline_ns = time.monotonic_ns() + S
        while time.monotonic_ns() < deadline_ns:
            poses.append((await tcp.read())[1])
            await asyncio.sleep(POLL_PERIOD_S)
        assert np.abs(np.array(poses) - HOME).max() < 1e-6  # neither turned nor lowered
        status = await until(lambda: (s := planner.status()) and "tilted" in s.last_error and s, 3.0,
                             "the refusal counted")
        return planner.arm_state(), status

    arm_state, status = scenario(run, rig)
    assert not arm_state.servo_active and "tilted 180.0 deg" in arm_state.stop_reason
    assert status.errors.get("target_refused", 0) >= 1


def test_over_the_force_limit_a_retreat_moves_the_arm_and_a_push_is_refused(rig):
    async def run(planner: PlayedPlanner, tcp: SimTcp):
        planner.force_n = -(LIMITS.max_force_n + 1.0)  # the tool's -z is base +z: the bubble is pushed up
        await asyncio.sleep(0.1)
        planner.goal = HOME + [0, 0, 0.05, 0, 0, 0, 0]  # up, along the force: a retreat
        await moving_at_speed(tcp)
        retreating = planner.arm_state()
        planner.new_goal()  # a new goal (its first target's refusal must not hold the next one)
        planner.goal = HOME - [0, 0, 0.05, 0, 0, 0, 0]  # down, into the contact
        _, rest = await at_rest(tcp, 2.0)
        await asyncio.sleep(3 * REPLAN_PERIOD_S)
        _, still, _ = await tcp.read()
        return retreating, np.linalg.norm(still - rest), planner.arm_state()

    retreating, drift_m, pushing = scenario(run, rig)
    assert retreating.servo_active and retreating.tcp_pose[2] > HOME[2]
    assert drift_m < 1e-6 and not pushing.servo_active and "over the limit" in pushing.stop_reason


async def dashboard(host: str, line: str) -> str:
    """One request to the simulated controller's dashboard (29999), as a person at the pendant would; its reply."""
    reader, writer = await asyncio.wait_for(asyncio.open_connection(host, DASHBOARD_PORT), SOCKET_TIMEOUT_S)
    try:
        await asyncio.wait_for(reader.readline(), SOCKET_TIMEOUT_S)  # the banner
        writer.write(f"{line}\n".encode())
        return (await asyncio.wait_for(reader.readline(), SOCKET_TIMEOUT_S)).decode().strip()
    finally:
        writer.close()


#: Each external stop: how a person or the controller causes it, the cause the commander names, and how a person
#: clears it on the controller's side (None: nothing to clear; ``arm enable`` restarts the program).
EXTERNAL_STOPS = {
    "dashboard stop": (("dashboard", "stop"), "program stopped", None),
    "dashboard pause": (("dashboard", "pause"), "program paused", None),
    "protective stop": (("sim", "protective_stop"), "protective stop", ("dashboard", "unlock protective stop")),
    "safeguard stop": (("sim", "safeguard_stop"), "safeguard stop", ("sim", "release_safety_stop")),
    "emergency stop": (("sim", "emergency_stop"), "emergency stop", ("sim", "release_safety_stop")),
}
HELD_CHECK_S = 0.6  # how long fresh targets keep coming while the test checks that nothing reaches the controller
STOP_SEEN_S = 0.1  # after the TCP came to rest: the commander has read the controller's stop (every 8 ms) by then


@pytest.mark.parametrize("kind", list(EXTERNAL_STOPS))
def test_an_external_stop_latches_until_arm_enable_and_a_new_goal(rig, kind):
    (inject_via, inject), cause, clear = EXTERNAL_STOPS[kind]

    async def act(tcp: SimTcp, via: str, what: str) -> None:
        if via == "dashboard":
            await dashboard(rig.host, what)
        else:
            await tcp.request(what)

    async def run(planner: PlayedPlanner, tcp: SimTcp):
        planner.goal = HOME + [0.15, 0, 0, 0, 0, 0, 0]
        await moving_at_speed(tcp)
        await act(tcp, inject_via, inject)
        await at_rest(tcp, 2.0)
        await asyncio.sleep(STOP_SEEN_S)
        before = (await tcp.request("state"))["counters"]

        async def assert_held(when: str) -> None:
            await asyncio.sleep(HELD_CHECK_S)  # the goal's targets keep coming meanwhile
            counters = (await tcp.request("state"))["counters"]
            for counter in ("servol_received", "program_loaded"):  # no servo command reached it, no program restart
                assert counters.get(counter, 0) == before.get(counter, 0), (counter, when)

        await assert_held("while the controller reports the stop")
        latched, refused = planner.arm_state(), None
        degraded = await until(lambda: (s := planner.status()) and s.state == "degraded" and s, 2.0, "degraded")
        if clear is not None:  # a person clears the controller's own stop: the arm stays held
            await act(tcp, *clear)
            await assert_held("after the controller's stop was cleared")
            await act(tcp, inject_via, inject)  # again: arm enable is refused while the controller reports it
            await until(lambda: planner.arm_state().controller_stop == cause, 2.0, "the stop reported again")
            refused = await arm_enable.enable(str(rig.config_path), ARM, "test")
            await act(tcp, *clear)
            await until(lambda: planner.arm_state().controller_stop != cause, 2.0, "the stop cleared again")
        held_counters, held = (await tcp.request("state"))["counters"], planner.arm_state()
        enable_code = await asyncio.to_thread(arm_enable.run, argparse.Namespace(
            arm=ARM, config=str(rig.config_path), by="lab safety officer"))
        await asyncio.sleep(HELD_CHECK_S)  # the old goal's targets keep coming
        old_goal_counters, old_goal = (await tcp.request("state"))["counters"], planner.arm_state()
        ready = await until(lambda: (s := planner.status()) and s.state == "ready" and s, 2.0, "ready again")
        planner.new_goal()
        await moving_at_speed(tcp)
        return latched, before, refused, held_counters, held, enable_code, old_goal_counters, old_goal, degraded, ready

    (latched, before, refused, held_counters, held, enable_code, old_goal_counters, old_goal, degraded,
     ready) = scenario(run, rig)
    assert latched.stop_owner == "external" and cause in latched.stop_reason, latched
    assert degraded.errors.get("external_stop", 0) > 0 and cause in degraded.last_error, degraded  # for `status`
    assert ready.state == "ready"
    assert latched.controller_stop == cause and not latched.servo_active
    assert held_counters.get("program_loaded", 0) == before.get("program_loaded", 0)
    assert held.latched and held.stop_owner == "external" and cause in held.stop_reason, held
    if refused is not None:
        assert not refused.ok and cause in refused.error, refused
    assert enable_code == 0
    assert old_goal_counters.get("servol_received", 0) == before.get("servol_received", 0)  # the old goal: held
    assert not old_goal.latched and not old_goal.servo_active and "arm enable" in old_goal.stop_reason, old_goal
    log = rig.log_path.read_text()
    assert "arm enabled by 'lab safety officer'" in log


def test_a_commander_restarted_mid_goal_does_not_move_the_arm_until_a_new_goal(rig):
    async def run(planner: PlayedPlanner, tcp: SimTcp):
        planner.goal = HOME + [0.15, 0, 0, 0, 0, 0, 0]
        await moving_at_speed(tcp)
        await asyncio.to_thread(stop_process, rig.commander, signal.SIGKILL)
        await asyncio.to_thread(rig.start_commander)
        ready_ns = time.monotonic_ns()
        await until(lambda: (s := planner.arm_state()) and s.stamp_ns > ready_ns, 5.0, "the new commander's state")
        await at_rest(tcp, 2.0)
        before = (await tcp.request("state"))["counters"]
        await asyncio.sleep(2 * HELD_CHECK_S)  # the goal from before the restart keeps sending targets
        after, held = (await tcp.request("state"))["counters"], planner.arm_state()
        planner.new_goal()
        await moving_at_speed(tcp)
        return before, after, held, planner.status()

    before, after, held, status = scenario(run, rig)
    assert after.get("servol_received", 0) == before.get("servol_received", 0)
    assert not held.servo_active and "before the commander's start" in held.stop_reason, held
    assert status.errors.get("old_goal", 0) > 0


def test_sigint_stops_the_arm_then_exits_0_and_stops_the_script(rig):
    async def run(planner: PlayedPlanner, tcp: SimTcp):
        planner.goal = HOME + [0.15, 0, 0, 0, 0, 0, 0]
        await moving_at_speed(tcp)
        counters = (await tcp.request("state"))["counters"]
        exit_code = await asyncio.to_thread(stop_process, rig.commander, signal.SIGINT)
        after = await tcp.request("state")
        return counters, exit_code, after

    before, exit_code, after = scenario(run, rig)
    log = rig.log_path.read_text()
    assert exit_code == 0, log[-2000:]
    assert np.linalg.norm(after["twist"]) < AT_REST_M_S
    assert after["counters"].get("commands[16]", 0) > before.get("commands[16]", 0)  # servoStop
    assert after["counters"].get("stop_script", 0) == before.get("stop_script", 0) + 1
    assert after["runtime_state"] != 2  # the program no longer plays
    assert log.rindex("arm stopped and at rest") < log.rindex("stopped (exit 0)")


def test_a_stop_never_confirmed_at_rest_exits_3(rig):
    """The controller gone at shutdown: the commander cannot see the arm at rest and says so by its exit code (the
    controller's own watchdog is then what stops the arm)."""
    commander = rig.start_commander()
    with socket.create_connection((rig.host, SIM_CONTROL_PORT), timeout=SOCKET_TIMEOUT_S) as conn:
        conn.sendall(b'{"op": "drop", "duration_s": 3.0}\n')
        assert json.loads(conn.makefile().readline())["ok"]
    time.sleep(0.3)  # the commander's driver has lost the link
    exit_code = stop_process(commander, signal.SIGINT)
    log = rig.log_path.read_text()
    assert exit_code == EXIT_STOP_UNCONFIRMED, log[-2000:]
    assert "not seen at rest" in log[log.rindex("SIGINT received"):]
