"""Names for the UR controller's status words: ``safety_status_bits``, ``robot_mode`` and ``runtime_state`` (RTDE).

Pure functions, no I/O. ``controller_stop`` turns the three words into one named cause ("" while the controller
runs a program in normal operation), so that the stack can say why the arm stopped. The bit and mode numbers are
those of UR's RTDE guide for e-Series controllers (CB3 controllers report the same words).
"""

from __future__ import annotations

import functools
from enum import IntEnum

#: ``safety_status_bits``: bit number -> name (UR RTDE guide). Bit 0 (normal mode) and bit 1 (reduced mode) are
#: not stops; every other set bit is.
SAFETY_STATUS_BITS = {
    0: "normal mode",
    1: "reduced mode",
    2: "protective stop",
    3: "recovery mode",
    4: "safeguard stop",
    5: "system emergency stop",
    6: "robot emergency stop",
    7: "emergency stop",
    8: "safety violation",
    9: "safety fault",
    10: "stopped due to safety",
}
#: The bits that are not stops.
NOT_A_STOP = frozenset({0, 1})
#: Status words whose names ``safety_flags`` and ``controller_stop`` keep: the controller reports the same few words
#: at every servo tick, so each is named once; any other word is named as before, only not kept.
NAMED_WORDS_KEPT = 256
#: The order in which a stop cause is named when several bits are set: the most severe first.
SEVERITY = (5, 6, 7, 9, 8, 4, 2, 3, 10)


class RobotMode(IntEnum):
    """RTDE ``robot_mode``: the arm's power and brake state. Only RUNNING (powered, brakes released) can move."""

    NO_CONTROLLER = -1
    DISCONNECTED = 0
    CONFIRM_SAFETY = 1
    BOOTING = 2
    POWER_OFF = 3
    POWER_ON = 4
    IDLE = 5
    BACKDRIVE = 6
    RUNNING = 7
    UPDATING_FIRMWARE = 8


class RuntimeState(IntEnum):
    """RTDE ``runtime_state``: the state of the controller's program."""

    STOPPING = 0
    STOPPED = 1
    PLAYING = 2
    PAUSING = 3
    PAUSED = 4
    RESUMING = 5


@functools.lru_cache(maxsize=NAMED_WORDS_KEPT)
def safety_flags(bits: int) -> tuple[str, ...]:
    """The names of the stop bits set in ``safety_status_bits`` (most severe first; normal/reduced mode left out).
    An unknown bit is named ``"safety bit N"``."""
    known = [SAFETY_STATUS_BITS[bit] for bit in SEVERITY if bits >> bit & 1]
    unknown = [f"safety bit {bit}" for bit in range(max(bits.bit_length(), 1))
               if bits >> bit & 1 and bit not in SAFETY_STATUS_BITS]
    return tuple(known + unknown)


def robot_mode_name(mode: int) -> str:
    """``robot_mode`` as its RTDE name (``"POWER_OFF"``), or ``"robot mode N"`` for an unknown value."""
    try:
        return RobotMode(mode).name
    except ValueError:
        return f"robot mode {mode}"


@functools.lru_cache(maxsize=NAMED_WORDS_KEPT)
def controller_stop(safety_bits: int, robot_mode: int, runtime_state: int) -> str:
    """The controller's reason for not running the stack's program, or "" when it runs it in normal operation.

    In order: the most severe safety stop bit (``safety_flags``), a robot mode other than RUNNING (``"robot mode
    POWER_OFF"``), a program paused or pausing (``"program paused"``), stopped or stopping (``"program
    stopped"``), resuming (``"program resuming"``: not ours to resume), an unknown runtime state.
    """
    flags = safety_flags(safety_bits)
    if flags:
        return flags[0]
    if robot_mode != RobotMode.RUNNING:
        return f"robot mode {robot_mode_name(robot_mode)}"
    if runtime_state in (RuntimeState.PAUSED, RuntimeState.PAUSING):
        return "program paused"
    if runtime_state in (RuntimeState.STOPPED, RuntimeState.STOPPING):
        return "program stopped"
    if runtime_state == RuntimeState.RESUMING:
        return "program resuming"
    if runtime_state != RuntimeState.PLAYING:
        return f"runtime state {runtime_state}"
    return ""
