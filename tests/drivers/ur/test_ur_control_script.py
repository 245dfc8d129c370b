"""The emulated ur_rtde control script: register handshake, real-time commands, watchdog, stopScript."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest

from hydrosoft.drivers.ur import control_script as cs
from hydrosoft.drivers.ur.motion import MotionMode, TcpMotion

START = np.array([0.3, -0.2, 0.4, 0.0, 0.0, 1.0, 0.0])
TOOL_DOWN = [0.0, 3.141592653589793, 0.0]
TICK_NS = 2_000_000


class Rig:
    """A script, its registers and TCP, ticked at 500 Hz; ``write`` plays a client's input package."""

    def __init__(self, offset: int = 0) -> None:
        self.regs = cs.Registers()
        self.motion = TcpMotion(START)
        self.counters: Counter = Counter()
        self.script = cs.ControlScript(self.regs, self.motion, self.counters, stop_decel_m_s2=10.0)
        self.now_ns = 1_000_000_000
        self.script.start(offset)

    def write(self, command: int, doubles=(), async_flag: int | None = None) -> None:
        base = self.script.offset
        self.regs.int_in[base] = command
        self.regs.int_in_written_ns[base] = self.now_ns
        self.regs.double_in[base : base + len(doubles)] = doubles
        if async_flag is not None:
            self.regs.int_in[base + 1] = async_flag

    def tick(self, count: int = 1) -> None:
        for _ in range(count):
            self.now_ns += TICK_NS
            self.script.cycle(self.now_ns)
            self.motion.step(TICK_NS / 1e9)

    @property
    def handshake(self) -> int:
        return int(self.regs.int_out[self.script.offset])


def test_register_offset_is_read_from_the_injected_text():
    header = "def rtde_control():\n    global reg_offset_float = # float register offset\n{0}    global " \
             "reg_offset_int = # int register offset\n{0}    global x = 2\nend\n"
    assert cs.register_offset(header.format(0)) == 0
    assert cs.register_offset(header.format(24)) == 24
    assert cs.is_control_program(header.format(0))
    assert not cs.is_control_program("textmsg(\"hi\")\n")
    with pytest.raises(ValueError, match="expected 0 or 24"):
        cs.register_offset(header.format(7))
    with pytest.raises(ValueError, match="no '# int register offset' marker"):
        cs.register_offset("def rtde_control():\nend\n")


def test_movel_runs_the_ready_done_clear_handshake():
    rig = Rig()
    assert rig.handshake == cs.SIGNAL_READY
    rig.write(cs.CMD_MOVEL, [0.35, -0.2, 0.4, *TOOL_DOWN, 0.25, 1.2], async_flag=0)
    rig.tick()
    assert rig.motion.mode == MotionMode.MOVE
    assert rig.handshake == cs.SIGNAL_READY  # still executing
    rig.tick(300)  # 0.05 m at 0.25 m/s with 1.2 m/s^2 ramps: 0.41 s
    assert rig.handshake == cs.SIGNAL_DONE
    np.testing.assert_allclose(rig.motion.pose()[:3], [0.35, -0.2, 0.4])
    rig.tick(5)
    assert rig.handshake == cs.SIGNAL_DONE  # waits for the client's clear, does not run the move again
    assert rig.counters[f"commands[{cs.CMD_MOVEL}]"] == 1
    rig.write(cs.CMD_CLEAR)
    rig.tick()
    assert rig.handshake == cs.SIGNAL_READY


def test_async_movel_is_done_at_once_and_reports_progress_until_stopl():
    rig = Rig()
    rig.write(cs.CMD_MOVEL, [0.5, -0.2, 0.4, *TOOL_DOWN, 0.1, 1.2], async_flag=1)
    rig.tick()
    assert rig.handshake == cs.SIGNAL_DONE
    assert rig.regs.int_out[2] & cs.ASYNC_RUNNING_BIT
    rig.write(cs.CMD_CLEAR)
    rig.tick(20)
    rig.write(cs.CMD_STOPL, [5.0], async_flag=0)
    rig.tick(60)
    assert rig.handshake == cs.SIGNAL_DONE
    assert rig.regs.int_out[2] == 0
    assert rig.motion.mode == MotionMode.HOLD
    assert rig.motion.pose()[0] < 0.5


def test_servol_is_real_time_and_acts_once_per_package():
    rig = Rig(offset=cs.UPPER_RANGE_OFFSET)
    target = [0.31, -0.2, 0.4, *TOOL_DOWN]
    rig.write(cs.CMD_SERVOL, [*target, 0.25, 1.2, 0.008, 0.1, 300.0])
    rig.tick(3)
    assert rig.handshake == cs.SIGNAL_READY
    assert rig.motion.mode == MotionMode.SERVO
    assert rig.counters[f"commands[{cs.CMD_SERVOL}]"] == 1
    rig.write(cs.CMD_SERVOL, [*target, 0.25, 1.2, 0.008, 0.1, 300.0])
    rig.tick(300)
    assert rig.counters[f"commands[{cs.CMD_SERVOL}]"] == 2
    assert rig.motion.pose()[0] == pytest.approx(0.31, abs=1e-4)
    rig.write(cs.CMD_SERVO_STOP, [2.0])
    rig.tick(2)
    assert rig.handshake == cs.SIGNAL_DONE  # already at rest: done at once


def test_motion_is_refused_when_not_allowed_and_bad_arguments_are_counted():
    rig = Rig()
    rig.script.motion_allowed = lambda: False
    rig.write(cs.CMD_SERVOL, [0.4, -0.2, 0.4, *TOOL_DOWN, 0.25, 1.2, 0.008, 0.1, 300.0])
    rig.tick(10)
    assert rig.motion.mode == MotionMode.HOLD
    assert rig.counters["motion_refused"] == 1
    rig.script.motion_allowed = lambda: True
    rig.write(cs.CMD_SPEEDL, [0.0, 0.0, float("nan"), 0.0, 0.0, 0.0, 0.5, 0.0])
    rig.tick()
    assert rig.motion.mode == MotionMode.HOLD
    assert rig.counters["bad_arguments"] == 1


def test_watchdog_stops_the_program_when_the_command_register_goes_quiet():
    rig = Rig()
    rig.write(cs.CMD_SET_WATCHDOG, [10.0])
    rig.tick()
    assert rig.script.watchdog_period_s == pytest.approx(0.1)
    rig.write(cs.CMD_CLEAR)
    rig.write(cs.CMD_SPEEDL, [0.1, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0])
    for _ in range(10):  # a package every 60 ms keeps it alive
        rig.tick(30)
        rig.write(cs.CMD_SPEEDL, [0.1, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0])
    assert rig.script.running
    assert rig.counters["watchdog_expired"] == 0
    rig.tick(60)  # 120 ms of silence
    assert not rig.script.running
    assert rig.script.runtime_state == cs.RuntimeState.STOPPED
    assert rig.counters["watchdog_expired"] == 1
    rig.tick(100)
    np.testing.assert_array_equal(rig.motion.twist(), np.zeros(6))


def test_stop_script_ends_the_program_and_unknown_commands_complete():
    rig = Rig()
    rig.write(77)
    rig.tick()
    assert rig.handshake == cs.SIGNAL_DONE
    assert rig.counters["unsupported_command"] == 1
    rig.write(cs.CMD_CLEAR)
    rig.tick()
    rig.write(cs.CMD_STOP_SCRIPT)
    rig.tick()
    assert rig.script.runtime_state == cs.RuntimeState.STOPPED
    assert rig.counters["stop_script"] == 1


def test_script_port_text_splits_into_programs_and_lines():
    program = "def rtde_control():\n  textmsg(\"x\")\n  end_here = 1\nend\n"
    scripts, rest = cs.split_scripts(program[:20])
    assert scripts == [] and rest == program[:20]
    scripts, rest = cs.split_scripts(rest + program[20:] + "stopl(1.0)\npopup(")
    assert scripts == [program, "stopl(1.0)"]
    assert rest == "popup("
