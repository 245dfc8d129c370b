"""Settings of the FT 300 driver: the serial line, the stream's start/stop timing and the link-health limits.

Device facts (baud rate, Modbus address) default to the sensor's factory values (Robotiq FT 300 manual; the facts
and their sources are in ``protocol.py``). Host facts, such as the port path, belong in ``deploy/lab.toml``.
The stop/start timings follow the ROS driver (``rq_sensor_com.cpp``): the stream counts as stopped after 80 ms
without a byte, and the sensor gets 100 ms to switch back to Modbus before the start request.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

from hydrosoft.drivers.robotiq_ft300.protocol import BAUD_RATE, FRAME_PERIOD_S, SLAVE_ADDRESS

MODBUS_MAX_SLAVE_ADDRESS = 247


@dataclass(frozen=True)
class FT300Config:
    """How to reach one FT 300 and when to give up on it. Durations in seconds.

    port: serial device path, best a stable ``/dev/serial/by-id/...`` link (or a simulator's pty link).
    slave_address: the sensor's Modbus RTU address (factory 9).
    baud_rate: line speed, 8N1 (factory 19200).
    max_age_s: ``read()`` raises ``Stale`` when the newest frame is older than this (5 frame periods at 100 Hz).
    read_timeout_s: longest blocking serial read in the reader thread; bounds how late a stall is noticed.
    write_timeout_s: longest blocking serial write (a 50-byte stop burst takes 26 ms at 19200 baud).
    stop_silence_s: the line counts as silent (stream stopped) after this long without a byte (ROS: 80 ms).
    stop_attempt_s: how long to listen for silence after one stop burst before sending another.
    stop_attempts: stop bursts sent before giving up on a line that keeps talking.
    modbus_switch_delay_s: pause after the stream stopped before sending a Modbus request (ROS: 100 ms).
    reply_timeout_s: wait for the sensor's reply to the start-stream request.
    first_frame_timeout_s: wait for the first valid frame after the reply before the connection fails.
    restart_after_s: with no valid frame for this long the link is dropped and opened again (stop, start).
    backoff_initial_s, backoff_max_s: wait between reconnect attempts; doubles after each failure up to the max.
    rate_window_s: window of the measured frame rate in the health report.
    """

    port: str
    slave_address: int = SLAVE_ADDRESS
    baud_rate: int = BAUD_RATE
    max_age_s: float = 0.05
    read_timeout_s: float = 0.02
    write_timeout_s: float = 0.5
    stop_silence_s: float = 0.08
    stop_attempt_s: float = 0.5
    stop_attempts: int = 5
    modbus_switch_delay_s: float = 0.1
    reply_timeout_s: float = 0.2
    first_frame_timeout_s: float = 0.5
    restart_after_s: float = 0.5
    backoff_initial_s: float = 0.1
    backoff_max_s: float = 2.0
    rate_window_s: float = 1.0

    def __post_init__(self) -> None:
        if not self.port:
            raise ValueError("FT300Config.port is empty: give the serial device path")
        if not 1 <= self.slave_address <= MODBUS_MAX_SLAVE_ADDRESS:
            raise ValueError(f"FT300Config.slave_address={self.slave_address} is outside Modbus' 1..247")
        if self.baud_rate <= 0:
            raise ValueError(f"FT300Config.baud_rate={self.baud_rate} must be positive")
        if self.stop_attempts < 1:
            raise ValueError(f"FT300Config.stop_attempts={self.stop_attempts} must be at least 1")
        for field in fields(self):
            value = getattr(self, field.name)
            if field.name.endswith("_s") and not (math.isfinite(value) and value > 0):
                raise ValueError(f"FT300Config.{field.name}={value} must be a positive number of seconds")
        if self.max_age_s <= FRAME_PERIOD_S:
            raise ValueError(
                f"FT300Config.max_age_s={self.max_age_s} must exceed one frame period ({FRAME_PERIOD_S} s), "
                "or every read between two frames is stale"
            )
        if self.stop_silence_s <= 2 * FRAME_PERIOD_S:
            raise ValueError(
                f"FT300Config.stop_silence_s={self.stop_silence_s} must exceed two frame periods "
                f"({2 * FRAME_PERIOD_S} s), or the gap between two frames passes for a stopped stream"
            )
        if self.stop_attempt_s <= self.stop_silence_s:
            raise ValueError(
                f"FT300Config.stop_attempt_s={self.stop_attempt_s} must exceed stop_silence_s={self.stop_silence_s}"
            )
        if self.restart_after_s <= self.max_age_s:
            raise ValueError(
                f"FT300Config.restart_after_s={self.restart_after_s} must exceed max_age_s={self.max_age_s}: "
                "reads go stale before the link is restarted"
            )
        if self.backoff_max_s < self.backoff_initial_s:
            raise ValueError(
                f"FT300Config.backoff_max_s={self.backoff_max_s} is below backoff_initial_s={self.backoff_initial_s}"
            )
