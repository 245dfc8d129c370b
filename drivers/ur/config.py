"""Settings of the UR driver (``URArmConfig``) and of the simulated controller (``URSimulatorConfig``).

Host facts (the lab arm's IP) belong in ``deploy/lab.toml``; the defaults here are device behaviour. Both configs are
frozen and checked on creation: a bad value raises ``ValueError`` naming the field and the value, and the checks
include how fields relate (see ``URArmConfig.__post_init__``).
"""

from __future__ import annotations

import ipaddress
import math
from dataclasses import dataclass, field

import numpy as np

from hydrosoft.drivers.ur.motion import MotionLimits

# TCP ports of a UR controller that ur_rtde 1.6.5 uses (devices.md section 3.1); the client hard-codes them.
RTDE_PORT = 30004
DASHBOARD_PORT = 29999
SCRIPT_PORT = 30003
# The simulator's own fault/inspection port (not a UR port; JSON lines, see simulator.py).
SIM_CONTROL_PORT = 30100

MAX_STATE_RATE_HZ = 500.0  # an e-Series controller's fastest RTDE output (a CB3's is 125 Hz)

# ur_rtde's servoL argument ranges (rtde_control_interface docs).
SERVO_LOOKAHEAD_RANGE_S = (0.03, 0.2)
SERVO_GAIN_RANGE = (100.0, 2000.0)


def _require_positive(owner: str, **values: float) -> None:
    for name, value in values.items():
        if not (math.isfinite(value) and value > 0.0):
            raise ValueError(f"{owner}.{name} must be positive and finite, got {value}")


@dataclass(frozen=True)
class URArmConfig:
    """How ``URArm`` drives a UR e-Series arm through ur_rtde.

    host: controller address (the lab arm's IP, or 127.0.0.N for the simulator).
    servo_rate_hz: rate at which ``servo_to`` is called; each servoL is given ``1 / servo_rate_hz`` s.
    state_rate_hz: rate the controller streams the state ``read_state`` returns (the receive interface's RTDE
        output frequency, at most ``MAX_STATE_RATE_HZ``). The stack reads it once per servo period, so a faster
        stream only costs CPU: at 500 Hz instead of 125, ur_rtde's receive client took about twice the CPU and the
        simulated controller about 1.5 times as much (one-off measurement against the simulated controller).
    control_rate_hz: rate the controller streams to the control interface (at most ``MAX_STATE_RATE_HZ``), from
        which ur_rtde reads the script's handshake and whether the program runs. At 125 Hz instead of an
        e-Series' 500 a command with a handshake (a stop) waits up to 8 ms longer, and the client process idled at
        9.9 % of a core instead of 16 % (one-off measurement against the simulated controller).
    servo_lookahead_s: servoL lookahead time (s, UR range 0.03-0.2): longer smooths more and lags more.
    servo_gain: servoL proportional gain (UR range 100-2000): higher tracks tighter.
    servo_speed_m_s, servo_accel_m_s2: passed to servoL (the controller does not use them today).
    stop_decel_m_s2: deceleration of ``stop()`` (servoStop/speedStop), m/s^2.
    max_tcp_speed_m_s: the fastest the stack ever moves the TCP (m/s); bounds how long a stop takes.
    watchdog_min_hz: the controller stops the program when no command reaches it for ``1 / watchdog_min_hz`` s
        (ur_rtde ``setWatchdog``). ``stop()`` sends no command while it decelerates, so the watchdog period must be
        at least twice the longest stop, ``max_tcp_speed_m_s / stop_decel_m_s2``.
    max_age_s: ``read_state`` raises ``Stale`` when the newest controller state is older than this (s).
    connect_timeout_s: limit of each TCP probe of the controller's ports before the ur_rtde constructors run.
    reconnect_initial_s, reconnect_max_s: reconnect back-off after the controller is gone: first wait, doubling up
        to the maximum.
    upper_range_registers: use RTDE registers 24-47 (leave 0-23 to a fieldbus or another program).
    """

    host: str
    servo_rate_hz: float = 125.0
    state_rate_hz: float = 125.0
    control_rate_hz: float = 125.0
    servo_lookahead_s: float = 0.1
    servo_gain: float = 300.0
    servo_speed_m_s: float = 0.25
    servo_accel_m_s2: float = 1.2
    stop_decel_m_s2: float = 2.0
    max_tcp_speed_m_s: float = 0.25
    watchdog_min_hz: float = 4.0
    max_age_s: float = 0.1
    connect_timeout_s: float = 1.0
    reconnect_initial_s: float = 0.2
    reconnect_max_s: float = 5.0
    upper_range_registers: bool = False

    def __post_init__(self) -> None:
        if not self.host:
            raise ValueError("URArmConfig.host is empty")
        _require_positive(
            "URArmConfig",
            servo_rate_hz=self.servo_rate_hz,
            state_rate_hz=self.state_rate_hz,
            control_rate_hz=self.control_rate_hz,
            servo_speed_m_s=self.servo_speed_m_s,
            servo_accel_m_s2=self.servo_accel_m_s2,
            stop_decel_m_s2=self.stop_decel_m_s2,
            max_tcp_speed_m_s=self.max_tcp_speed_m_s,
            watchdog_min_hz=self.watchdog_min_hz,
            max_age_s=self.max_age_s,
            connect_timeout_s=self.connect_timeout_s,
            reconnect_initial_s=self.reconnect_initial_s,
            reconnect_max_s=self.reconnect_max_s,
        )
        for name in ("state_rate_hz", "control_rate_hz"):
            if getattr(self, name) > MAX_STATE_RATE_HZ:
                raise ValueError(f"URArmConfig.{name} must be at most {MAX_STATE_RATE_HZ} Hz (an e-Series "
                                 f"controller's RTDE limit), got {getattr(self, name)}")
        low, high = SERVO_LOOKAHEAD_RANGE_S
        if not low <= self.servo_lookahead_s <= high:
            raise ValueError(
                f"URArmConfig.servo_lookahead_s must be in [{low}, {high}] s, got {self.servo_lookahead_s}"
            )
        low, high = SERVO_GAIN_RANGE
        if not low <= self.servo_gain <= high:
            raise ValueError(f"URArmConfig.servo_gain must be in [{low}, {high}], got {self.servo_gain}")
        if self.watchdog_period_s < 2.0 * self.max_stop_duration_s:
            raise ValueError(
                f"URArmConfig: watchdog period 1/watchdog_min_hz = {self.watchdog_period_s:.3f} s must be at least "
                f"twice the longest stop max_tcp_speed_m_s/stop_decel_m_s2 = {self.max_stop_duration_s:.3f} s"
            )
        if self.watchdog_period_s < 3.0 * self.servo_period_s:
            raise ValueError(
                f"URArmConfig: watchdog period {self.watchdog_period_s:.3f} s must be at least three servo periods "
                f"({3.0 * self.servo_period_s:.3f} s)"
            )
        if self.reconnect_max_s < self.reconnect_initial_s:
            raise ValueError(
                f"URArmConfig.reconnect_max_s ({self.reconnect_max_s}) is below reconnect_initial_s "
                f"({self.reconnect_initial_s})"
            )

    @property
    def servo_period_s(self) -> float:
        return 1.0 / self.servo_rate_hz

    @property
    def watchdog_period_s(self) -> float:
        return 1.0 / self.watchdog_min_hz

    @property
    def max_stop_duration_s(self) -> float:
        return self.max_tcp_speed_m_s / self.stop_decel_m_s2


def _default_tcp_pose() -> np.ndarray:
    # 0.3 m in front, 0.4 m up, tool pointing down (a half turn about y): UR rotvec (0, pi, 0)
    return np.array([0.3, -0.2, 0.4, 0.0, 0.0, 1.0, 0.0])


@dataclass(frozen=True)
class URSimulatorConfig:
    """The simulated controller.

    host: loopback address it serves on (127.0.0.0/8 only; tests use a distinct 127.0.0.N each).
    tcp_pose: initial TCP pose ``(7,)`` [m, wxyz] in the base frame.
    tick_hz: controller cycle rate (the e-Series runs 500 Hz); every tick advances the script and the TCP.
    max_output_hz: cap on the RTDE output rate a client may ask for.
    limits: TCP speed and acceleration limits.
    stop_decel_m_s2: deceleration of a stop command that carries none (m/s^2).
    unlock_delay_s: protective stops cannot be unlocked on the dashboard before this (real controller: 5 s).
    remote_control: the dashboard's answer to ``is in remote control``.
    sim_control_port: port of the simulator's JSON-lines fault and inspection endpoint.
    """

    host: str = "127.0.0.1"
    tcp_pose: np.ndarray = field(default_factory=_default_tcp_pose)
    tick_hz: float = 500.0
    max_output_hz: float = 500.0
    limits: MotionLimits = field(default_factory=MotionLimits)
    stop_decel_m_s2: float = 10.0
    unlock_delay_s: float = 5.0
    remote_control: bool = True
    sim_control_port: int = SIM_CONTROL_PORT

    def __post_init__(self) -> None:
        try:
            address = ipaddress.ip_address(self.host)
        except ValueError as exc:
            raise ValueError(f"URSimulatorConfig.host must be an IPv4 loopback address, got {self.host!r}") from exc
        if not address.is_loopback:
            raise ValueError(f"URSimulatorConfig.host must be in 127.0.0.0/8, got {self.host}")
        _require_positive(
            "URSimulatorConfig",
            tick_hz=self.tick_hz,
            max_output_hz=self.max_output_hz,
            stop_decel_m_s2=self.stop_decel_m_s2,
        )
        if not (math.isfinite(self.unlock_delay_s) and self.unlock_delay_s >= 0.0):
            raise ValueError(f"URSimulatorConfig.unlock_delay_s must be >= 0, got {self.unlock_delay_s}")
        if np.asarray(self.tcp_pose).shape != (7,):
            raise ValueError(f"URSimulatorConfig.tcp_pose must have shape (7,), got {np.asarray(self.tcp_pose).shape}")
