"""The simulated UR controller's state, without sockets: robot and safety status, registers, program, TCP motion.

``URControllerModel`` is what the socket layer (``simulator.py``) and the dashboard (``dashboard.py``) act on:
``tick(now_ns)`` advances the emulated control script and the TCP, ``output_values()`` gives every RTDE output
variable for a data package, ``write_inputs`` applies a client's input data package, ``load_program`` takes what
arrived on the script port. Everything runs on one thread (the simulator's event loop); nothing here blocks.

Status words follow the RTDE guide (names in ``safety_status.py``): ``robot_status_bits`` bit 0 power on, bit 1
program running; ``safety_status_bits`` bit 0 normal, bit 2 protective stop, bit 4 safeguard stop, bit 7 emergency
stop; ``robot_mode`` 7 = RUNNING (3 = POWER_OFF after an emergency stop); ``safety_mode`` 1 = NORMAL, 3 =
PROTECTIVE_STOP, 5 = SAFEGUARD_STOP, 7 = ROBOT_EMERGENCY_STOP. The stops a person causes (safeguard and emergency
stop, a paused program) are injected through the simulator's control endpoint and the dashboard.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from typing import Callable

import numpy as np

from hydrosoft.drivers.ur.control_script import (
    ControlScript,
    Registers,
    RuntimeState,
    is_control_program,
    register_offset,
)
from hydrosoft.drivers.ur.motion import MotionLimits, TcpMotion
from hydrosoft.drivers.ur.pose import rotvec_from_quat
from hydrosoft.drivers.ur.rtde_protocol import OUTPUT_TYPES, REGISTER_COUNT, VECTOR_LENGTHS

ROBOT_MODE_RUNNING = 7
ROBOT_MODE_POWER_OFF = 3
SAFETY_MODE_NORMAL = 1
SAFETY_MODE_PROTECTIVE_STOP = 3
SAFETY_MODE_SAFEGUARD_STOP = 5
SAFETY_MODE_ROBOT_EMERGENCY_STOP = 7
ROBOT_STATUS_POWER_ON = 1 << 0
ROBOT_STATUS_PROGRAM_RUNNING = 1 << 1
SAFETY_STATUS_NORMAL = 1 << 0
SAFETY_STATUS_PROTECTIVE_STOP = 1 << 2
SAFETY_STATUS_SAFEGUARD_STOP = 1 << 4
SAFETY_STATUS_EMERGENCY_STOP = 1 << 7
#: servoL's command id (``control_script.CMD_SERVOL``) as a client writes it into the command register.
SERVOL_COMMAND = 24
JOINT_MODE_RUNNING = 253
# A plausible UR5e joint configuration (rad) reported as actual_q; the simulator has no kinematics.
HOME_JOINTS_RAD = (0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0)

# Tick listener: called after every tick with (now_ns, TCP pose (7,) [m, wxyz], TCP twist (6,) [m/s, rad/s]).
TickListener = Callable[[int, np.ndarray, np.ndarray], None]


@dataclass(frozen=True)
class ControllerIdentity:
    """What the controller reports about itself: RTDE version (major, minor, bugfix, build), serial, model."""

    version: tuple[int, int, int, int] = (5, 15, 0, 0)
    serial_number: str = "20235500001"
    robot_model: str = "UR5"


class URControllerModel:
    """State of one simulated e-Series controller.

    Args:
        tcp_pose: initial TCP pose ``(7,)`` [m, wxyz] in the base frame.
        limits: TCP speed/acceleration limits.
        identity: version, serial and model reported on RTDE and the dashboard.
        remote_control: the dashboard's answer to ``is in remote control``.
        stop_decel_m_s2: deceleration used when a stop command carries none (m/s^2).
        unlock_delay_s: how long after a protective stop the dashboard refuses ``unlock protective stop`` (the
            real controller: 5 s).
        now_ns: ``time.monotonic_ns`` at boot; ``timestamp`` counts seconds from here.

    ``counters`` (a ``collections.Counter``) counts events by name: program uploads, faults, refused inputs,
    commands (see ``ControlScript``).
    """

    def __init__(
        self,
        tcp_pose: np.ndarray,
        limits: MotionLimits | None = None,
        identity: ControllerIdentity | None = None,
        remote_control: bool = True,
        stop_decel_m_s2: float = 10.0,
        unlock_delay_s: float = 5.0,
        now_ns: int = 0,
    ) -> None:
        self.identity = identity or ControllerIdentity()
        self.remote_control = remote_control
        self.unlock_delay_s = unlock_delay_s
        self.counters: Counter = Counter()
        self.motion = TcpMotion(tcp_pose, limits)
        self.registers = Registers()
        self.script = ControlScript(self.registers, self.motion, self.counters, stop_decel_m_s2)
        self.script.motion_allowed = self.motion_allowed
        self.script.on_protective_stop_request = self.trigger_protective_stop
        self.protective_stop = False
        self.safeguard_stop = False
        self.emergency_stop = False
        self.program: str | None = None
        self.digital_output_bits = 0
        self.speed_slider_fraction = 1.0
        self._boot_ns = now_ns
        self._last_tick_ns = now_ns
        self._protective_stop_ns = 0
        self._listeners: list[TickListener] = []

    # -- time ------------------------------------------------------------------------------------------------

    def tick(self, now_ns: int) -> None:
        """Advance to ``now_ns``: one pass of the control script, then the TCP motion, then the listeners."""
        dt_s = (now_ns - self._last_tick_ns) / 1e9
        self._last_tick_ns = now_ns
        self.script.cycle(now_ns)
        self.motion.step(dt_s)
        if self._listeners:
            pose, twist = self.motion.pose(), self.motion.twist()
            for listener in self._listeners:
                listener(now_ns, pose, twist)

    def add_tick_listener(self, listener: TickListener) -> None:
        """Call ``listener(now_ns, pose (7,), twist (6,))`` after every tick (e.g. sim_world's physics)."""
        self._listeners.append(listener)

    def timestamp_s(self) -> float:
        """Controller time (s since boot) at the last tick: the RTDE ``timestamp``."""
        return (self._last_tick_ns - self._boot_ns) / 1e9

    # -- safety and program ----------------------------------------------------------------------------------

    def motion_allowed(self) -> bool:
        return not (self.protective_stop or self.safeguard_stop or self.emergency_stop)

    def trigger_safeguard_stop(self) -> None:
        """Safeguard stop (a light curtain or door opened): the TCP stops; motion is refused until released."""
        self.counters["safeguard_stop"] += 1
        self.safeguard_stop = True
        self.motion.stop(self.motion.limits.protective_stop_decel_m_s2)

    def trigger_emergency_stop(self) -> None:
        """Emergency stop: the program ends, the TCP stops and the arm powers off (robot mode POWER_OFF) until
        released."""
        self.counters["emergency_stop"] += 1
        self.emergency_stop = True
        self.script.stop()
        self.motion.stop(self.motion.limits.protective_stop_decel_m_s2)

    def release_safety_stop(self) -> None:
        """A person resets a safeguard or emergency stop (sim only: a real controller needs its inputs reset and,
        after an emergency stop, the arm powered on again). The program stays as it is."""
        self.safeguard_stop = self.emergency_stop = False
        self.counters["safety_stop_released"] += 1

    def pause_program(self) -> None:
        """Dashboard ``pause`` (or the pendant's pause): the program pauses and the TCP decelerates to rest."""
        self.counters["pause"] += 1
        self.script.pause()

    def trigger_protective_stop(self) -> None:
        """Protective stop: the TCP stops at the protective deceleration; motion commands are refused until unlock."""
        self.counters["protective_stop"] += 1
        self.protective_stop = True
        self._protective_stop_ns = self._last_tick_ns
        self.motion.stop(self.motion.limits.protective_stop_decel_m_s2)

    def unlock_protective_stop(self) -> bool:
        """Clear the protective stop if ``unlock_delay_s`` has passed since it happened; True when cleared."""
        if not self.protective_stop:
            return True
        if (self._last_tick_ns - self._protective_stop_ns) / 1e9 < self.unlock_delay_s:
            return False
        self.protective_stop = False
        self.counters["protective_stop_unlocked"] += 1
        return True

    def load_program(self, text: str) -> None:
        """A program arrived on the script port: ur_rtde's control program (re)starts; anything else is counted."""
        if not is_control_program(text):
            self.counters["foreign_script"] += 1
            return
        try:
            offset = register_offset(text)
        except ValueError:
            self.counters["bad_program"] += 1
            return
        if self.emergency_stop:  # the arm is powered off: nothing runs until a person resets it
            self.counters["program_refused"] += 1
            return
        self.program = text
        self.counters["program_loaded"] += 1
        self.script.stop()
        self.script.start(offset)

    def play(self) -> bool:
        """Dashboard ``play``: restart the loaded program; False when none is loaded."""
        if self.program is None or self.emergency_stop:
            return False
        self.script.stop()
        self.script.start(register_offset(self.program))
        return True

    def stop_program(self) -> None:
        """Dashboard ``stop`` or the stop-script fault: the program ends and the TCP decelerates to rest."""
        self.script.stop()

    @property
    def runtime_state(self) -> RuntimeState:
        return self.script.runtime_state

    # -- RTDE ------------------------------------------------------------------------------------------------

    def write_inputs(self, values: dict[str, object], now_ns: int) -> None:
        """Apply one client input package (``name -> value``, names already checked against ``INPUT_TYPES``)."""
        regs = self.registers
        for name, value in values.items():
            if name.startswith("input_int_register_"):
                index = int(name.rsplit("_", 1)[1])
                if index in (0, 24) and int(value) == SERVOL_COMMAND:  # type: ignore[call-overload]
                    self.counters["servol_received"] += 1  # reached the controller, acted on or not
                regs.int_in[index] = int(value)  # type: ignore[call-overload]
                regs.int_in_written_ns[index] = now_ns
            elif name.startswith("input_double_register_"):
                regs.double_in[int(name.rsplit("_", 1)[1])] = float(value)  # type: ignore[arg-type]
        if "standard_digital_output_mask" in values:
            mask = int(values["standard_digital_output_mask"])  # type: ignore[call-overload]
            bits = int(values.get("standard_digital_output", 0))  # type: ignore[call-overload]
            self.digital_output_bits = (self.digital_output_bits & ~mask) | (bits & mask)
        if values.get("speed_slider_mask"):
            self.speed_slider_fraction = float(values["speed_slider_fraction"])  # type: ignore[arg-type]

    def robot_status_bits(self) -> int:
        bits = ROBOT_STATUS_POWER_ON
        if self.script.running:
            bits |= ROBOT_STATUS_PROGRAM_RUNNING
        return bits

    def safety_status_bits(self) -> int:
        bits = 0
        if self.emergency_stop:
            bits |= SAFETY_STATUS_EMERGENCY_STOP
        if self.safeguard_stop:
            bits |= SAFETY_STATUS_SAFEGUARD_STOP
        if self.protective_stop:
            bits |= SAFETY_STATUS_PROTECTIVE_STOP
        return bits or SAFETY_STATUS_NORMAL

    def safety_mode(self) -> int:
        if self.emergency_stop:
            return SAFETY_MODE_ROBOT_EMERGENCY_STOP
        if self.safeguard_stop:
            return SAFETY_MODE_SAFEGUARD_STOP
        if self.protective_stop:
            return SAFETY_MODE_PROTECTIVE_STOP
        return SAFETY_MODE_NORMAL

    def robot_mode(self) -> int:
        return ROBOT_MODE_POWER_OFF if self.emergency_stop else ROBOT_MODE_RUNNING

    def output_values(self) -> dict[str, object]:
        """Every name of ``OUTPUT_TYPES`` with its current value (vectors as lists), for data packages."""
        pose, twist = self.motion.pose(), self.motion.twist()
        ur_pose = [*pose[:3].tolist(), *rotvec_from_quat(pose[3:]).tolist()]
        values = dict(_CONSTANT_OUTPUTS)
        values.update(
            timestamp=self.timestamp_s(),
            actual_TCP_pose=ur_pose,
            target_TCP_pose=ur_pose,
            actual_TCP_speed=twist.tolist(),
            target_TCP_speed=twist.tolist(),
            safety_mode=self.safety_mode(),
            safety_status=self.safety_mode(),
            speed_scaling=self.speed_slider_fraction,
            target_speed_fraction=self.speed_slider_fraction,
            actual_digital_output_bits=self.digital_output_bits,
            runtime_state=int(self.runtime_state),
            robot_status_bits=self.robot_status_bits(),
            safety_status_bits=self.safety_status_bits(),
            robot_mode=self.robot_mode(),
        )
        values.update(zip(_INT_OUTPUT_REGISTERS, self.registers.int_out.tolist()))
        values.update(zip(_DOUBLE_OUTPUT_REGISTERS, self.registers.double_out.tolist()))
        return values


def _zero(rtde_type: str) -> object:
    length = VECTOR_LENGTHS.get(rtde_type)
    if length is None:
        return 0.0 if rtde_type == "DOUBLE" else 0
    return [0.0 if rtde_type.endswith("D") else 0] * length


_INT_OUTPUT_REGISTERS = [f"output_int_register_{i}" for i in range(REGISTER_COUNT)]
_DOUBLE_OUTPUT_REGISTERS = [f"output_double_register_{i}" for i in range(REGISTER_COUNT)]
#: The outputs that never change in this model (the rest of ``output_values`` is filled in per call).
_CONSTANT_OUTPUTS: dict[str, object] = {
    **{name: _zero(rtde_type) for name, rtde_type in OUTPUT_TYPES.items()},
    "target_q": list(HOME_JOINTS_RAD),
    "actual_q": list(HOME_JOINTS_RAD),
    "joint_temperatures": [30.0] * 6,
    "joint_mode": [JOINT_MODE_RUNNING] * 6,
    "actual_tool_accelerometer": [0.0, 0.0, -9.81],
    "actual_main_voltage": 48.0,
    "actual_robot_voltage": 48.0,
}
