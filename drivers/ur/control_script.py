"""Emulation of the control script that ``ur_rtde`` 1.6.5 uploads (``rtde_control.script``), over RTDE registers.

The real script is a URScript loop on the controller; this is the same protocol without a URScript interpreter
(devices.md sections 3.3-3.7). Each controller cycle the script reads the command id from
``input_int_register_<offset>`` and:

- ``0`` (the client's "clear", also what ``kickWatchdog`` writes): signal ready, ``output_int_register_<offset> = 1``;
- a real-time command (servoL, speedL, ...): act on its arguments once per package the client writes and stay
  ready, no "done" handshake;
- any other command: run it once (``executing``), write ``2`` (done) when it has finished, then wait for the
  client to write ``0`` back;
- ``255`` (stopScript): end the program.

Arguments travel in ``input_double_register_<offset + k>`` (and ``input_int_register_<offset + 1>`` for the
asynchronous flag) in the recipe layouts of devices.md section 3.3. ``output_int_register_<offset + 2>`` is the
async-progress word: bit 15 set while an asynchronous move runs.

Watchdog: ``setWatchdog(f)`` arms ``rtde_set_watchdog("input_int_register_<offset>", f, "stop")``. When that register
has not been written by any RTDE client for longer than ``1 / f`` seconds, the program stops and the TCP
decelerates to rest, as the controller does with the "stop" action.
"""

from __future__ import annotations

import math
import re
from collections import Counter

import numpy as np

from hydrosoft.drivers.ur.motion import MotionMode, TcpMotion
from hydrosoft.drivers.ur.pose import ur_to_pose
from hydrosoft.drivers.ur.rtde_protocol import REGISTER_COUNT
from hydrosoft.drivers.ur.safety_status import RuntimeState

# Command ids written into input_int_register_<offset> by the client (devices.md section 3.3).
CMD_CLEAR = 0
CMD_MOVEL = 3
CMD_SPEEDL = 10
CMD_SPEED_STOP = 15
CMD_SERVO_STOP = 16
CMD_SERVOL = 24
CMD_PROTECTIVE_STOP = 31
CMD_STOPL = 33
CMD_STOPJ = 34
CMD_SET_WATCHDOG = 35
CMD_STOP_SCRIPT = 255
# Answered with "ready" again, no "done" handshake (the uploaded 1.6.5 script's real-time set).
REALTIME_COMMANDS = frozenset({6, 9, 10, 11, 24, 25, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71})

SIGNAL_READY = 1
SIGNAL_DONE = 2
ASYNC_RUNNING_BIT = 1 << 15

UPPER_RANGE_OFFSET = 24
PROGRAM_HEADER = "def rtde_control():"
_OFFSET_MARKER = re.compile(r"# int register offset\n\s*(\d+)")


def is_control_program(text: str) -> bool:
    """True when ``text`` is ur_rtde's control program (it starts with ``def rtde_control():``)."""
    return text.lstrip().startswith(PROGRAM_HEADER)


def register_offset(program: str) -> int:
    """Register offset (0, or 24 with ``FLAG_UPPER_RANGE_REGISTERS``) that the client injected into ``program``.

    The client writes the number right after the line ``# int register offset``. Raises ``ValueError`` when the
    marker is missing or the number is neither 0 nor 24.
    """
    match = _OFFSET_MARKER.search(program)
    if match is None:
        raise ValueError("control program has no '# int register offset' marker")
    offset = int(match.group(1))
    if offset not in (0, UPPER_RANGE_OFFSET):
        raise ValueError(f"control program register offset is {offset}, expected 0 or {UPPER_RANGE_OFFSET}")
    return offset


def split_scripts(buffer: str) -> tuple[list[str], str]:
    """Split text received on the script port into complete scripts and the incomplete rest.

    A script is either a program (``def``/``sec`` up to its top-level ``end`` line, as ur_rtde sends its control
    script in one piece) or, otherwise, one line. Returns ``(scripts, rest)``; feed ``rest`` + new bytes next time.
    """
    scripts: list[str] = []
    while buffer:
        if buffer.lstrip().startswith(("def ", "sec ")):
            lines = buffer.splitlines(keepends=True)
            end = next((i for i, line in enumerate(lines) if line.rstrip("\r\n") == "end" and line.endswith("\n")),
                       None)
            if end is None:
                break
            scripts.append("".join(lines[: end + 1]))
            buffer = "".join(lines[end + 1 :])
        else:
            line, newline, rest = buffer.partition("\n")
            if not newline:
                break
            if line.strip():
                scripts.append(line)
            buffer = rest
    return scripts, buffer


class Registers:
    """The controller's general-purpose RTDE registers, 0..47 of each kind, plus when each int input was written.

    ``int_in``/``double_in`` are written by clients; ``int_out``/``double_out`` by the (emulated) script.
    ``int_in_written_ns[i]`` is the ``time.monotonic_ns`` stamp of the last client write of ``input_int_register_i``
    (0 = never), which the watchdog reads.
    """

    def __init__(self) -> None:
        self.int_in = np.zeros(REGISTER_COUNT, dtype=np.int64)
        self.double_in = np.zeros(REGISTER_COUNT, dtype=np.float64)
        self.int_out = np.zeros(REGISTER_COUNT, dtype=np.int64)
        self.double_out = np.zeros(REGISTER_COUNT, dtype=np.float64)
        self.int_in_written_ns = np.zeros(REGISTER_COUNT, dtype=np.int64)


class ControlScript:
    """The emulated control program. ``cycle(now_ns)`` is one pass of its main loop (call it every controller tick).

    ``motion_allowed()`` is asked before any motion command: the controller answers False while protectively or
    emergency stopped, and the command is dropped (counted ``motion_refused``). Counters (``counters``):
    ``commands[<id>]`` per command id executed, ``stop_script`` (255 seen), ``watchdog_expired``,
    ``unsupported_command``, ``bad_arguments``, ``motion_refused``.
    """

    def __init__(self, registers: Registers, motion: TcpMotion, counters: Counter, stop_decel_m_s2: float) -> None:
        self.registers = registers
        self.motion = motion
        self.counters = counters
        self.stop_decel_m_s2 = stop_decel_m_s2
        self.runtime_state = RuntimeState.STOPPED
        self.offset = 0
        self.motion_allowed = lambda: True
        self.on_protective_stop_request = lambda: None
        self._executing: int | None = None
        self._async_move = False
        self._watchdog_period_ns: int | None = None
        self._realtime_written_ns = 0

    @property
    def running(self) -> bool:
        return self.runtime_state == RuntimeState.PLAYING

    @property
    def watchdog_period_s(self) -> float | None:
        """Armed watchdog period (s), or None when no watchdog is set."""
        return None if self._watchdog_period_ns is None else self._watchdog_period_ns / 1e9

    def start(self, offset: int) -> None:
        """Start the program with the given register offset: clear the handshake and signal ready."""
        self.offset = offset
        self.runtime_state = RuntimeState.PLAYING
        self._executing = None
        self._async_move = False
        self._watchdog_period_ns = None
        self.registers.int_out[offset + 2] = 0
        self.registers.int_out[offset] = SIGNAL_READY

    def pause(self) -> None:
        """Pause the program (dashboard or pendant ``pause``): it no longer reads commands and the TCP decelerates
        to rest; ``start`` (dashboard ``play`` restarts the program) ends the pause."""
        if not self.running:
            return
        self.stop()
        self.runtime_state = RuntimeState.PAUSED

    def stop(self) -> None:
        """End the program (stopScript, dashboard ``stop``, watchdog, fault): the TCP decelerates to rest."""
        if not self.running:
            return
        self.runtime_state = RuntimeState.STOPPED
        self._executing = None
        self._async_move = False
        self._watchdog_period_ns = None
        self.registers.int_out[self.offset + 2] = 0
        self.motion.stop(self.motion.limits.protective_stop_decel_m_s2)

    # -- the main loop ---------------------------------------------------------------------------------------

    def cycle(self, now_ns: int) -> None:
        """One pass of the script's loop at ``now_ns`` (``time.monotonic_ns``)."""
        if not self.running:
            return
        if self._watchdog_expired(now_ns):
            self.counters["watchdog_expired"] += 1
            self.stop()
            return
        regs, base = self.registers, self.offset
        if self._async_move and not self.motion.busy:
            self._async_move = False
            regs.int_out[base + 2] = 0
        command = int(regs.int_in[base])
        if command == CMD_CLEAR:
            self._executing = None
            regs.int_out[base] = SIGNAL_READY
            return
        if command == CMD_STOP_SCRIPT:
            self.counters["stop_script"] += 1
            self.stop()
            return
        if command in REALTIME_COMMANDS:
            written_ns = int(regs.int_in_written_ns[base])
            if written_ns != self._realtime_written_ns:  # act once per package; re-reading it changes nothing
                self._realtime_written_ns = written_ns
                self._realtime(command)
            regs.int_out[base] = SIGNAL_READY
            return
        if self._executing is None:
            if regs.int_out[base] != SIGNAL_READY:
                return  # done with the previous command; waiting for the client's clear
            self._executing = command
            self._begin(command)
        if self._executing is not None and self._finished(self._executing):
            regs.int_out[base] = SIGNAL_DONE
            self._executing = None

    def _watchdog_expired(self, now_ns: int) -> bool:
        if self._watchdog_period_ns is None:
            return False
        return now_ns - int(self.registers.int_in_written_ns[self.offset]) > self._watchdog_period_ns

    def _doubles(self, count: int) -> np.ndarray:
        return self.registers.double_in[self.offset : self.offset + count].copy()

    def _async_flag(self) -> bool:
        return bool(self.registers.int_in[self.offset + 1])

    def _motion_ok(self, args: np.ndarray) -> bool:
        if not np.all(np.isfinite(args)):
            self.counters["bad_arguments"] += 1
            return False
        if not self.motion_allowed():
            self.counters["motion_refused"] += 1
            return False
        return True

    def _realtime(self, command: int) -> None:
        if command == CMD_SERVOL:
            args = self._doubles(11)  # pose 0-5, speed 6, accel 7, time 8, lookahead 9, gain 10
            if self._motion_ok(args):
                self.motion.servo(ur_to_pose(args[:6]), lookahead_s=float(args[9]), gain=float(args[10]))
                self.counters[f"commands[{command}]"] += 1
        elif command == CMD_SPEEDL:
            args = self._doubles(8)  # twist 0-5, accel 6, time 7
            if self._motion_ok(args):
                self.motion.speed(args[:6], accel_m_s2=float(args[6]), time_s=float(args[7]))
                self.counters[f"commands[{command}]"] += 1
        else:
            self.counters["unsupported_command"] += 1

    def _begin(self, command: int) -> None:
        """Start non-real-time ``command``; ``_finished`` says when it is done."""
        self.counters[f"commands[{command}]"] += 1
        if command == CMD_MOVEL:
            args = self._doubles(8)  # pose 0-5, speed 6, accel 7
            if self._motion_ok(args):
                self.motion.move(ur_to_pose(args[:6]), speed_m_s=float(args[6]), accel_m_s2=float(args[7]))
                if self._async_flag():
                    self._async_move = True
                    self.registers.int_out[self.offset + 2] = ASYNC_RUNNING_BIT
        elif command in (CMD_SERVO_STOP, CMD_SPEED_STOP, CMD_STOPL, CMD_STOPJ):
            decel = float(self._doubles(1)[0])
            self.motion.stop(decel if math.isfinite(decel) and decel > 0.0 else self.stop_decel_m_s2)
            self._async_move = False
            self.registers.int_out[self.offset + 2] = 0
        elif command == CMD_SET_WATCHDOG:
            min_hz = float(self._doubles(1)[0])
            if math.isfinite(min_hz) and min_hz > 0.0:
                self._watchdog_period_ns = int(1e9 / min_hz)
            else:
                self.counters["bad_arguments"] += 1
        elif command == CMD_PROTECTIVE_STOP:
            self.on_protective_stop_request()
        else:
            self.counters["unsupported_command"] += 1

    def _finished(self, command: int) -> bool:
        if command == CMD_MOVEL and not self._async_flag():
            return not self.motion.busy
        synchronous_stop = command in (CMD_STOPL, CMD_STOPJ) and not self._async_flag()
        if command in (CMD_SERVO_STOP, CMD_SPEED_STOP) or synchronous_stop:
            return self.motion.mode == MotionMode.HOLD
        return True
