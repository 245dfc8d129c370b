"""The UR status words decoded into named stop causes (``drivers/ur/safety_status.py``), without sockets."""

from __future__ import annotations

import pytest

from hydrosoft.drivers.ur.safety_status import (SAFETY_STATUS_BITS, RobotMode, RuntimeState, controller_stop,
                                                robot_mode_name, safety_flags)

NORMAL = 1 << 0
RUNNING, PLAYING = RobotMode.RUNNING, RuntimeState.PLAYING


@pytest.mark.parametrize("bit", sorted(set(SAFETY_STATUS_BITS) - {0, 1}))
def test_every_safety_stop_bit_is_named_and_stops(bit):
    name = SAFETY_STATUS_BITS[bit]
    assert safety_flags(1 << bit) == (name,)
    assert controller_stop(1 << bit, RUNNING, PLAYING) == name


def test_normal_and_reduced_mode_are_not_stops_and_unknown_bits_are_named():
    assert safety_flags(NORMAL) == () and safety_flags(1 << 1) == ()
    assert controller_stop(NORMAL, RUNNING, PLAYING) == "" and controller_stop(1 << 1, RUNNING, PLAYING) == ""
    assert safety_flags(1 << 13) == ("safety bit 13",)


def test_the_most_severe_stop_is_named_first():
    bits = (1 << 2) | (1 << 4) | (1 << 7) | (1 << 10)
    assert safety_flags(bits) == ("emergency stop", "safeguard stop", "protective stop", "stopped due to safety")
    assert controller_stop(bits, RobotMode.POWER_OFF, RuntimeState.STOPPED) == "emergency stop"


@pytest.mark.parametrize("mode", [m for m in RobotMode if m != RobotMode.RUNNING])
def test_a_robot_mode_other_than_running_is_a_stop(mode):
    assert controller_stop(NORMAL, mode, PLAYING) == f"robot mode {mode.name}"


@pytest.mark.parametrize(("state", "cause"), [(RuntimeState.PAUSED, "program paused"),
                                              (RuntimeState.PAUSING, "program paused"),
                                              (RuntimeState.STOPPED, "program stopped"),
                                              (RuntimeState.STOPPING, "program stopped"),
                                              (RuntimeState.RESUMING, "program resuming"), (9, "runtime state 9")])
def test_a_program_that_does_not_play_is_a_stop(state, cause):
    assert controller_stop(NORMAL, RUNNING, state) == cause


def test_unknown_robot_modes_are_named_by_number():
    assert robot_mode_name(42) == "robot mode 42" and robot_mode_name(3) == "POWER_OFF"
