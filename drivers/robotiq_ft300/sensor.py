"""``FT300Sensor``: the Robotiq FT 300 over pyserial, as a ``drivers.base.ForceTorqueSensor``.

Connecting stops any stream the sensor is already sending (0xFF bursts until the line is silent, as the ROS
driver does), starts the stream with the Modbus request, checks the reply and waits for a first valid frame. A
reader thread (pyserial blocks) then feeds a ``FrameScanner`` and keeps the newest wrench with the monotonic time it
arrived; ``read()`` hands it out, or raises ``Stale`` when it is older than ``max_age_s`` and ``NotConnected``
while the link is down, and ``wait_newer`` wakes an event loop as a new one arrives (no polling). The thread asks the
port for the bytes that can complete the next frame (``FrameScanner.bytes_wanted``), so a frame takes one read. It
drops the link on a serial error or when no valid frame came for ``restart_after_s``, and opens it again with
doubling backoff. ``close()`` stops the stream and closes the port.

Check a sensor by hand: ``python -m hydrosoft.drivers.robotiq_ft300.sensor --port /dev/serial/by-id/...``.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass

import numpy as np
import serial

from hydrosoft.drivers.base import WrenchSample
from hydrosoft.drivers.errors import DriverError, NotConnected, ProtocolError, Stale
from hydrosoft.drivers.robotiq_ft300.config import FT300Config
from hydrosoft.drivers.robotiq_ft300.protocol import (
    STOP_BURST,
    STREAM_REGISTER,
    WRITE_REPLY_SIZE,
    FrameScanner,
    check_write_registers_reply,
    start_stream_request,
)

log = logging.getLogger(__name__)

READ_CHUNK = 4096  # largest read while draining the line
JOIN_TIMEOUT_S = 3.0  # wait for the reader thread on close; above the longest connect step it may be in


@dataclass(frozen=True)
class FT300Health:
    """Link health of one sensor; counters run from the first connect.

    connected: the port is open and the stream was confirmed (False while reconnecting or closed).
    rate_hz: valid frames per second over the last ``rate_window_s`` (about 100 when healthy).
    frames: valid frames received.
    crc_errors: frame candidates rejected for their CRC (line noise, or lost alignment).
    bytes_skipped: bytes thrown away while looking for a frame.
    resyncs: times frame alignment was found again after losing it.
    last_frame_age_s: seconds since the newest valid frame arrived (``None`` before the first).
    reconnects: times the link was opened again after it dropped.
    last_error: why the link last dropped or a reconnect attempt failed (``None`` if it never did).
    """

    connected: bool
    rate_hz: float
    frames: int
    crc_errors: int
    bytes_skipped: int
    resyncs: int
    last_frame_age_s: float | None
    reconnects: int
    last_error: str | None


class _Closing(DriverError):
    """``close()`` was called while the link was being opened."""


class FT300Sensor:
    """One Robotiq FT 300 streaming over a serial port. Wrenches are ``(6,)`` N and N m in the sensor frame.

    ``await connect()`` before ``read()``; ``await close()`` at the end (or ``async with FT300Sensor(cfg)``).
    ``read()`` never waits for the line: it returns the newest sample (stamped with ``time.monotonic_ns()`` at
    receipt; the FT 300 has no clock of its own, so ``hw_stamp_ns`` is ``None``) or raises.
    """

    def __init__(self, config: FT300Config) -> None:
        self.config = config
        self._lock = threading.Lock()
        self._scanner = FrameScanner()
        self._latest: WrenchSample | None = None
        self._frame_stamps_ns: deque[int] = deque()
        self._link_up_ns = 0
        self._port: serial.Serial | None = None
        self._reconnects = 0
        self._last_error: str | None = None
        self._closing = threading.Event()
        self._thread: threading.Thread | None = None
        self._waiters: list[tuple[asyncio.AbstractEventLoop, asyncio.Future[None]]] = []  # ``wait_newer``'s

    def __str__(self) -> str:
        return f"FT300Sensor({self.config.port})"

    async def __aenter__(self) -> FT300Sensor:
        await self.connect()
        return self

    async def __aexit__(self, *exc_info: object) -> None:
        await self.close()

    # -- public API ---------------------------------------------------------------------------------------------

    async def connect(self) -> None:
        """Open the port, stop any running stream, start it and wait for a first valid frame; then start the reader.

        Raises ``NotConnected`` (port missing, no reply, no frames) or ``ProtocolError`` (unexpected reply, a line
        that keeps talking after the stop bursts), naming the port. Does nothing when already connected.
        """
        if self._thread is not None:
            return
        self._closing.clear()
        port = await asyncio.to_thread(self._open_link)
        self._thread = threading.Thread(target=self._reader_main, args=(port,), name=f"{self}-reader", daemon=True)
        self._thread.start()

    async def read(self) -> WrenchSample:
        """The newest sample. Raises ``NotConnected`` before ``connect``, after ``close`` and while the link is
        down; ``Stale`` when the newest frame is older than ``max_age_s``."""
        return self.latest()

    async def wait_newer(self, after_ns: int, timeout_s: float) -> None:
        """Return as soon as a sample stamped after ``after_ns`` (``time.monotonic_ns``) has arrived, at once when
        one already has, or after ``timeout_s`` (s) without one; raises nothing (``read`` says what there is)."""
        loop = asyncio.get_running_loop()
        woken: asyncio.Future[None] = loop.create_future()
        waiter = (loop, woken)
        with self._lock:
            if self._latest is not None and self._latest.stamp_ns > after_ns:
                return
            self._waiters.append(waiter)
        timer = loop.call_later(max(timeout_s, 0.0), _wake, woken)
        try:
            await woken
        finally:
            timer.cancel()
            with self._lock:
                if waiter in self._waiters:
                    self._waiters.remove(waiter)

    def latest(self) -> WrenchSample:
        """``read()`` for callers outside asyncio (same result, same errors)."""
        with self._lock:
            port, sample, error = self._port, self._latest, self._last_error
        if self._thread is None:
            raise NotConnected(f"{self}: not connected (connect() not called, or closed)")
        if port is None:
            raise NotConnected(error)
        age_s = (time.monotonic_ns() - sample.stamp_ns) / 1e9
        if age_s > self.config.max_age_s:
            raise Stale(f"{self}: newest frame is {age_s:.3f} s old (limit {self.config.max_age_s} s)")
        return sample

    def health(self) -> FT300Health:
        """A snapshot of the link's health (see ``FT300Health``)."""
        now_ns = time.monotonic_ns()
        with self._lock:
            self._forget_old_stamps(now_ns)
            window_s = min(self.config.rate_window_s, (now_ns - self._link_up_ns) / 1e9)
            connected = self._port is not None
            rate_hz = len(self._frame_stamps_ns) / window_s if connected and window_s > 0 else 0.0
            latest = self._latest
            reconnects, last_error = self._reconnects, self._last_error
        scanner = self._scanner
        return FT300Health(
            connected=connected,
            rate_hz=rate_hz,
            frames=scanner.frames,
            crc_errors=scanner.crc_errors,
            bytes_skipped=scanner.bytes_skipped,
            resyncs=scanner.resyncs,
            last_frame_age_s=None if latest is None else (now_ns - latest.stamp_ns) / 1e9,
            reconnects=reconnects,
            last_error=last_error,
        )

    async def close(self) -> None:
        """Stop the reader, stop the stream (0xFF bursts until silent) and close the port. Safe to call twice.

        A failure to stop the stream is logged, not raised: the port is closed either way.
        """
        await asyncio.to_thread(self._shut_down)

    # -- opening the link ---------------------------------------------------------------------------------------

    def _open_link(self) -> serial.Serial:
        """Open the port and start the stream (blocking). Returns the open port with the link marked up."""
        cfg = self.config
        try:
            port = serial.Serial(
                port=cfg.port,
                baudrate=cfg.baud_rate,
                bytesize=serial.EIGHTBITS,
                parity=serial.PARITY_NONE,
                stopbits=serial.STOPBITS_ONE,
                timeout=cfg.read_timeout_s,
                write_timeout=cfg.write_timeout_s,
                exclusive=True,
            )
        except (serial.SerialException, OSError, ValueError) as exc:
            raise NotConnected(
                f"{self}: cannot open {cfg.port}: {exc} (adapter plugged in? user in the dialout group?)"
            ) from exc
        try:
            self._stop_stream(port)
            self._pause(cfg.modbus_switch_delay_s)
            port.reset_input_buffer()
            self._start_stream(port)
            self._await_first_frame(port)
        except (serial.SerialException, OSError) as exc:
            port.close()
            raise NotConnected(f"{self}: lost {cfg.port} while starting the stream: {exc}") from exc
        except DriverError:
            port.close()
            raise
        return port

    def _pause(self, duration_s: float) -> None:
        if self._closing.wait(duration_s):
            raise _Closing(f"{self}: closing")

    def _wait_for_silence(self, port: serial.Serial, interruptible: bool) -> bool:
        """Drain the line until no byte came for ``stop_silence_s``; False if it kept talking for ``stop_attempt_s``.
        With ``interruptible``, ``close()`` ends the wait (raises ``_Closing``)."""
        cfg = self.config
        deadline_ns = time.monotonic_ns() + round(cfg.stop_attempt_s * 1e9)
        port.timeout = cfg.stop_silence_s
        try:
            while time.monotonic_ns() < deadline_ns:
                if interruptible and self._closing.is_set():
                    raise _Closing(f"{self}: closing")
                if not port.read(READ_CHUNK):
                    return True
            return False
        finally:
            port.timeout = cfg.read_timeout_s

    def _stop_stream(self, port: serial.Serial, interruptible: bool = True) -> None:
        """Send 0xFF bursts until the line goes silent (ROS driver: repeat until 80 ms without a byte)."""
        for _ in range(self.config.stop_attempts):
            port.write(STOP_BURST)
            port.flush()
            if self._wait_for_silence(port, interruptible):
                return
        raise ProtocolError(
            f"{self}: {self.config.port} kept sending after {self.config.stop_attempts} stop bursts of 0xFF; "
            "is this an FT 300?"
        )

    def _start_stream(self, port: serial.Serial) -> None:
        """Send the start-stream request (0x0200 to register 410) and check the sensor's echo."""
        cfg = self.config
        port.write(start_stream_request(cfg.slave_address))
        port.timeout = cfg.reply_timeout_s
        try:
            reply = port.read(WRITE_REPLY_SIZE)
        finally:
            port.timeout = cfg.read_timeout_s
        if not reply:
            raise NotConnected(
                f"{self}: no reply on {cfg.port} within {cfg.reply_timeout_s} s to the start-stream request "
                f"(Modbus slave {cfg.slave_address}, {cfg.baud_rate} baud); is the sensor powered and wired?"
            )
        try:
            check_write_registers_reply(reply, cfg.slave_address, STREAM_REGISTER, 1)
        except ProtocolError as exc:
            raise ProtocolError(f"{self}: start-stream request on {cfg.port}: {exc}") from exc

    def _await_first_frame(self, port: serial.Serial) -> None:
        """Read until a first valid frame arrives (it is published) or ``first_frame_timeout_s`` passes."""
        cfg = self.config
        self._scanner.clear()
        deadline_ns = time.monotonic_ns() + round(cfg.first_frame_timeout_s * 1e9)
        while time.monotonic_ns() < deadline_ns:
            if self._closing.is_set():
                raise _Closing(f"{self}: closing")
            if self._publish(self._scanner.feed(port.read(port.in_waiting or 1))):
                with self._lock:
                    self._port = port
                    self._link_up_ns = self._latest.stamp_ns
                    self._frame_stamps_ns.clear()  # the rate counts frames after the link came up
                return
        raise NotConnected(
            f"{self}: {cfg.port} acknowledged the start request but sent no valid frame within "
            f"{cfg.first_frame_timeout_s} s"
        )

    # -- reader thread ------------------------------------------------------------------------------------------

    def _publish(self, wrenches: list[np.ndarray]) -> bool:
        """Keep the newest of ``wrenches`` as the latest sample; returns whether there was one."""
        if not wrenches:
            return False
        stamp_ns = time.monotonic_ns()
        newest = wrenches[-1]
        newest.flags.writeable = False
        with self._lock:
            self._latest = WrenchSample(wrench=newest, stamp_ns=stamp_ns, hw_stamp_ns=None)
            self._frame_stamps_ns.extend([stamp_ns] * len(wrenches))
            self._forget_old_stamps(stamp_ns)
            waiters, self._waiters = self._waiters, []
        for loop, woken in waiters:
            try:
                loop.call_soon_threadsafe(_wake, woken)
            except RuntimeError:  # its loop has closed: nobody waits there any more
                pass
        return True

    def _forget_old_stamps(self, now_ns: int) -> None:
        oldest_ns = now_ns - round(self.config.rate_window_s * 1e9)
        stamps = self._frame_stamps_ns
        while stamps and stamps[0] < oldest_ns:
            stamps.popleft()

    def _reader_main(self, port: serial.Serial) -> None:
        """Reader thread body: an unexpected failure marks the link down for good, so ``read()`` says why."""
        try:
            self._read_forever(port)
        except Exception as exc:
            log.exception("%s: reader thread failed", self)
            with self._lock:
                self._port = None
                self._last_error = f"{self}: reader thread failed: {exc!r}; reconnect by close() and connect()"

    def _read_forever(self, port: serial.Serial | None) -> None:
        """Reader thread: feed frames from ``port``; on a dropped link, reconnect with backoff until closing."""
        while not self._closing.is_set():
            if port is None:
                port = self._reconnect()
                continue
            try:
                data = port.read(max(port.in_waiting, self._scanner.bytes_wanted))
            except (serial.SerialException, OSError) as exc:
                self._drop_link(port, f"serial error: {exc}")
                port = None
                continue
            self._publish(self._scanner.feed(data))
            with self._lock:
                silent_s = (time.monotonic_ns() - self._latest.stamp_ns) / 1e9
            if silent_s > self.config.restart_after_s and not self._closing.is_set():
                self._drop_link(port, f"no valid frame for {silent_s:.2f} s")
                port = None

    def _drop_link(self, port: serial.Serial, reason: str) -> None:
        message = f"{self}: link dropped ({reason}); reconnecting"
        log.warning(message)
        with self._lock:
            self._port = None
            self._last_error = message
            self._frame_stamps_ns.clear()
        try:
            port.close()
        except (serial.SerialException, OSError) as exc:
            log.warning("%s: closing the dropped port failed: %s", self, exc)

    def _reconnect(self) -> serial.Serial | None:
        """Open the link again, waiting ``backoff_initial_s`` doubling to ``backoff_max_s`` between attempts.
        Returns the port, or ``None`` when closing."""
        backoff_s = self.config.backoff_initial_s
        while not self._closing.is_set():
            try:
                port = self._open_link()
            except _Closing:
                return None
            except DriverError as exc:
                log.info("%s: reconnect failed: %s; next try in %.2f s", self, exc, backoff_s)
                with self._lock:
                    self._last_error = f"{exc}; reconnecting"
            else:
                with self._lock:
                    self._reconnects += 1
                log.warning("%s: reconnected", self)
                return port
            if self._closing.wait(backoff_s):
                return None
            backoff_s = min(2 * backoff_s, self.config.backoff_max_s)
        return None

    # -- closing ------------------------------------------------------------------------------------------------

    def _shut_down(self) -> None:
        self._closing.set()
        thread, self._thread = self._thread, None
        with self._lock:
            port = self._port
        if port is not None:
            port.cancel_read()  # wake the reader out of its blocking read
        if thread is not None:
            thread.join(JOIN_TIMEOUT_S)
            if thread.is_alive():
                log.error("%s: reader thread did not end within %s s", self, JOIN_TIMEOUT_S)
        with self._lock:  # the port the reader left open, if any (it may have reconnected meanwhile)
            port, self._port = self._port, None
        if port is None:
            return
        try:
            self._stop_stream(port, interruptible=False)
        except (DriverError, serial.SerialException, OSError) as exc:
            log.warning("%s: could not confirm the stream stopped: %s", self, exc)
        finally:
            port.close()


def _wake(woken: asyncio.Future[None]) -> None:
    """End a ``wait_newer`` (on its loop), unless it has ended already."""
    if not woken.done():
        woken.set_result(None)


# -- command line ------------------------------------------------------------------------------------------------

PRINT_PERIOD_S = 0.5


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of the hand check (``hydrosoft-stack check ft300``)."""
    parser.add_argument("--port", required=True, help="serial device, e.g. /dev/serial/by-id/usb-FTDI_...")
    parser.add_argument("--duration", type=float, default=3.0, help="seconds to read (default 3)")
    parser.add_argument("--slave-address", type=int, default=FT300Config.slave_address, help="Modbus address (9)")


async def _check(config: FT300Config, duration_s: float) -> int:
    sensor = FT300Sensor(config)
    try:
        await sensor.connect()
    except DriverError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    try:
        deadline_s = time.monotonic() + duration_s
        while time.monotonic() < deadline_s:
            await asyncio.sleep(PRINT_PERIOD_S)
            try:
                sample = await sensor.read()
                text = "F [N] " + " ".join(f"{v:8.2f}" for v in sample.wrench[:3])
                text += "  M [N m] " + " ".join(f"{v:7.3f}" for v in sample.wrench[3:])
            except DriverError as exc:
                text = f"no reading: {exc}"
            print(text, flush=True)
        health = sensor.health()
        print(f"health: {health}", flush=True)
    finally:
        await sensor.close()
    return 0 if health.frames > 0 else 1


def run(args: argparse.Namespace) -> int:
    """Connect, print the wrench every 0.5 s for ``--duration`` s, then the link health. 0 if frames arrived."""
    try:
        config = FT300Config(port=args.port, slave_address=args.slave_address)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return asyncio.run(_check(config, args.duration))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m hydrosoft.drivers.robotiq_ft300.sensor", description=__doc__)
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
