"""The simulated controller's state and its dashboard replies, without sockets."""

from __future__ import annotations

import re

import numpy as np

from hydrosoft.drivers.ur import rtde_protocol as rtde
from hydrosoft.drivers.ur.safety_status import RuntimeState
from hydrosoft.drivers.ur.controller import (SAFETY_STATUS_NORMAL, SAFETY_STATUS_PROTECTIVE_STOP, URControllerModel)
from hydrosoft.drivers.ur.safety_status import controller_stop
from hydrosoft.drivers.ur.dashboard import UNLOCK_TOO_EARLY, dashboard_reply

START = np.array([0.3, -0.2, 0.4, 0.0, 0.0, 1.0, 0.0])
PROGRAM = "def rtde_control():\n  x = # int register offset\n{}  y = 1\nend\n"


def model(**kwargs) -> URControllerModel:
    return URControllerModel(START, now_ns=0, **kwargs)


def test_every_output_variable_encodes_with_its_rtde_type():
    m = model()
    m.tick(2_000_000)
    recipe = rtde.Recipe.build(1, list(rtde.OUTPUT_TYPES), rtde.OUTPUT_TYPES)
    payload = rtde.encode_data_package(recipe, m.output_values())[rtde.HEADER_SIZE:]
    values = rtde.decode_data_package(recipe, payload)
    assert values["timestamp"] == 0.002
    np.testing.assert_allclose(values["actual_TCP_pose"], [0.3, -0.2, 0.4, 0.0, np.pi, 0.0])
    assert values["runtime_state"] == RuntimeState.STOPPED
    assert values["safety_status_bits"] == SAFETY_STATUS_NORMAL


def test_program_upload_starts_the_script_with_its_offset():
    m = model()
    m.load_program("textmsg(\"hello\")")
    assert m.counters["foreign_script"] == 1
    assert m.runtime_state == RuntimeState.STOPPED
    m.load_program(PROGRAM.format(24))
    assert m.runtime_state == RuntimeState.PLAYING
    assert m.script.offset == 24
    assert m.output_values()["output_int_register_24"] == 1  # ready
    assert m.output_values()["robot_status_bits"] & 0b10
    m.load_program(PROGRAM.format(5))
    assert m.counters["bad_program"] == 1


def test_inputs_write_registers_and_stamp_the_int_ones():
    m = model()
    m.write_inputs({"input_int_register_0": 24, "input_double_register_3": 1.5, "speed_slider_mask": 1,
                    "speed_slider_fraction": 0.4}, now_ns=123)
    assert m.registers.int_in[0] == 24
    assert m.registers.int_in_written_ns[0] == 123
    assert m.registers.double_in[3] == 1.5
    assert m.output_values()["speed_scaling"] == 0.4


def test_dashboard_answers_what_the_client_checks():
    m = model(remote_control=False)
    assert re.search(r"\d+\.\d+\.\d+\.\d+", dashboard_reply(m, "PolyscopeVersion\n"))
    assert dashboard_reply(m, "get serial number").isdigit()
    assert dashboard_reply(m, "is in remote control") == "false"
    assert dashboard_reply(m, "play") == "Failed to execute: play"
    m.load_program(PROGRAM.format(0))
    assert "true" in dashboard_reply(m, "running")
    assert dashboard_reply(m, "stop") == "Stopped"
    assert m.runtime_state == RuntimeState.STOPPED
    assert dashboard_reply(m, "play") == "Starting program"
    assert m.runtime_state == RuntimeState.PLAYING
    assert dashboard_reply(m, "make coffee") == "could not understand: 'make coffee'"
    assert m.counters["dashboard_unknown"] == 1


def test_protective_stop_sets_the_bits_and_unlocks_only_after_the_delay():
    m = model(unlock_delay_s=5.0)
    m.tick(1_000_000_000)
    m.trigger_protective_stop()
    values = m.output_values()
    assert values["safety_status_bits"] == SAFETY_STATUS_PROTECTIVE_STOP
    assert values["safety_mode"] == 3
    assert dashboard_reply(m, "safetystatus") == "Safetystatus: PROTECTIVE_STOP"
    m.tick(3_000_000_000)
    assert dashboard_reply(m, "unlock protective stop") == UNLOCK_TOO_EARLY
    m.tick(6_500_000_000)
    assert dashboard_reply(m, "unlock protective stop") == "Protective stop releasing"
    assert not m.protective_stop
    assert m.counters["protective_stop_unlocked"] == 1


def test_tick_listeners_see_the_pose_and_twist():
    m = model()
    seen = []
    m.add_tick_listener(lambda now_ns, pose, twist: seen.append((now_ns, pose, twist)))
    m.motion.speed(np.array([0.1, 0, 0, 0, 0, 0]), accel_m_s2=100.0)
    m.tick(2_000_000)
    m.tick(4_000_000)
    assert [s[0] for s in seen] == [2_000_000, 4_000_000]
    assert seen[-1][2][0] == 0.1
    assert seen[-1][1][0] > 0.3


def test_safeguard_emergency_stop_and_pause_are_injected_with_their_status_words():
    m = model()
    m.load_program(PROGRAM.format(0))

    def cause() -> str:
        values = m.output_values()
        return controller_stop(values["safety_status_bits"], values["robot_mode"], values["runtime_state"])

    assert cause() == ""
    m.trigger_safeguard_stop()
    assert cause() == "safeguard stop" and not m.motion_allowed()
    assert dashboard_reply(m, "safetystatus") == "Safetystatus: SAFEGUARD_STOP"
    m.release_safety_stop()
    assert cause() == "" and m.motion_allowed()
    assert dashboard_reply(m, "pause") == "Pausing program"
    assert cause() == "program paused" and dashboard_reply(m, "programState") == "PAUSED rtde_control"
    assert dashboard_reply(m, "play") == "Starting program" and cause() == ""
    m.trigger_emergency_stop()
    assert cause() == "emergency stop" and m.output_values()["robot_mode"] == 3  # POWER_OFF
    m.load_program(PROGRAM.format(0))  # a program cannot start while the arm is powered off
    assert m.counters["program_refused"] == 1 and m.runtime_state == RuntimeState.STOPPED
    m.release_safety_stop()
    assert cause() == "program stopped"


def test_servol_packages_are_counted_as_they_reach_the_controller_whether_or_not_it_acts():
    m = model()
    m.write_inputs({"input_int_register_0": 24}, now_ns=1)  # no program runs: not acted on, still counted
    m.write_inputs({"input_int_register_24": 24}, now_ns=2)
    m.write_inputs({"input_int_register_0": 16}, now_ns=3)
    assert m.counters["servol_received"] == 2
