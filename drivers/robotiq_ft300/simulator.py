"""A simulated FT 300 on a pseudo-terminal: the real driver (or any serial client) talks to it as to the sensor.

``SimulatedFT300`` opens a pty, sets its slave side to raw mode and, on a background thread, behaves like the
device (``protocol.py`` has the facts): idle as a Modbus slave until it receives the start-stream request, which it
answers as the sensor does; then it writes 16-byte frames with real CRCs at ``rate_hz`` from ``wrench_source``
until a 0xFF byte arrives. Each frame carries the source's wrench plus ``bias`` and, with ``noise_scale``, the
sensor's signal noise drawn afresh per frame (``noise.py``: the datasheet's figures, the model the material fit
weighs by), rounded to the frame's resolution. Its path is the pty's slave (``slave_path``) or, with ``link``, a symlink to it, which
survives a simulated unplug and replug as ``/dev/serial/by-id`` links do.

Fault knobs for tests, each counted in ``stats()``: bit flips, dropped bytes and inserted garbage on stream frames
(``FT300Faults``; Modbus replies are never corrupted), ``stall(duration_s)`` (the device stops writing, replies
included, while still obeying commands), ``disconnect()`` (the pty is closed and the link removed, so the client
sees an I/O error) and ``reconnect()`` (a new pty, idle, behind the same link).

Run it alone with ``python -m hydrosoft.drivers.robotiq_ft300.simulator --link /tmp/ft300`` (``add_arguments`` /
``run`` serve ``hydrosoft-stack simulate ft300``).
"""

from __future__ import annotations

import argparse
import logging
import os
import select
import signal
import sys
import threading
import time
import tty
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import NamedTuple

import numpy as np

from hydrosoft.drivers.errors import ProtocolError
from hydrosoft.drivers.robotiq_ft300.noise import frame_noise
from hydrosoft.drivers.robotiq_ft300.protocol import (
    FC_WRITE_MULTIPLE_REGISTERS,
    FRAME_HEADER,
    ILLEGAL_DATA_ADDRESS,
    SLAVE_ADDRESS,
    STOP_BYTE,
    STREAM_RATE_HZ,
    STREAM_REGISTER,
    STREAM_START_VALUE,
    ModbusRequest,
    encode_frame,
    exception_reply,
    quantize_wrench,
    split_request,
    write_registers_reply,
)

log = logging.getLogger(__name__)

GARBAGE_MAX_BYTES = 8  # an inserted run of garbage is 1..8 bytes long
HISTORY_FRAMES = 100_000  # clean wrenches kept for ``sent_wrenches`` (over 16 min at 100 Hz)
MAX_LAG_FRAMES = 5  # when the thread falls further behind its schedule, it restarts the schedule from now
IDLE_WAIT_S = 0.05  # longest sleep of the thread while idle; commands wake it at once through a pipe
COMMAND_TIMEOUT_S = 2.0  # wait for the thread to carry out stop/stall/disconnect/reconnect
JOIN_TIMEOUT_S = 2.0  # wait for the thread to end on ``stop``
READ_CHUNK = 4096
NOISE_STREAM = 0xF7300  # first word of the noise generator's seed, apart from the fault generator's


@dataclass(frozen=True)
class FT300Faults:
    """Line faults applied to stream frames; rates are probabilities in [0, 1].

    bit_flip_rate: per frame byte, chance to flip one random bit of it.
    drop_rate: per frame byte, chance to lose it.
    garbage_rate: per frame, chance to insert 1..8 random bytes before it (half of them start with ``20 4E``,
        a false header).
    """

    bit_flip_rate: float = 0.0
    drop_rate: float = 0.0
    garbage_rate: float = 0.0

    def __post_init__(self) -> None:
        for field in fields(self):
            value = getattr(self, field.name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"FT300Faults.{field.name}={value} is not a probability in [0, 1]")


#: A clean line: frames go out as they are, and the fault generator is not drawn from.
NO_FAULTS = FT300Faults()


class FaultCounts(NamedTuple):
    """What ``inject_faults`` did to one frame."""

    bit_flips: int
    dropped_bytes: int
    garbage_bytes: int


def inject_faults(frame: bytes, faults: FT300Faults, rng: np.random.Generator) -> tuple[bytes, FaultCounts]:
    """``frame`` as a faulty line delivers it, and what was done to it. Draws the same number of random values
    whatever the rates, so a seeded ``rng`` gives the same faults for the same sequence of frames."""
    size = len(frame)
    flip = rng.random(size) < faults.bit_flip_rate
    bits = rng.integers(0, 8, size)
    keep = rng.random(size) >= faults.drop_rate
    insert_garbage = rng.random() < faults.garbage_rate
    garbage_size = int(rng.integers(1, GARBAGE_MAX_BYTES + 1))
    garbage = rng.integers(0, 256, garbage_size, dtype=np.uint8).tobytes()
    false_header = rng.random() < 0.5

    damaged = np.frombuffer(frame, dtype=np.uint8) ^ np.where(flip, np.left_shift(1, bits), 0).astype(np.uint8)
    delivered = damaged[keep].tobytes()
    if insert_garbage:
        if false_header:
            garbage = (FRAME_HEADER + garbage)[:garbage_size]
        delivered = garbage + delivered
    return delivered, FaultCounts(int(flip.sum()), int(size - keep.sum()), garbage_size if insert_garbage else 0)


@dataclass(frozen=True)
class SimulatorStats:
    """Counts since the simulator started.

    frames_sent: stream frames written (faulty or not); frames_corrupted: those with a bit flipped or a byte lost
    (garbage goes between frames and leaves them intact);
    bit_flips, dropped_bytes, garbage_bytes: the faults themselves; stalls, disconnects, reconnects: fault
    commands carried out; start_requests: start-stream requests obeyed; stop_bursts: times a 0xFF stopped the
    stream; bad_request_bytes: bytes dropped while parsing Modbus requests (bad CRC, unknown function);
    overflow_bytes: bytes the pty would not take (nobody reading); source_errors: frames skipped because the
    wrench source raised or gave a wrench no frame can carry.
    """

    frames_sent: int = 0
    frames_corrupted: int = 0
    bit_flips: int = 0
    dropped_bytes: int = 0
    garbage_bytes: int = 0
    stalls: int = 0
    disconnects: int = 0
    reconnects: int = 0
    start_requests: int = 0
    stop_bursts: int = 0
    bad_request_bytes: int = 0
    overflow_bytes: int = 0
    source_errors: int = 0


def _zero_wrench() -> np.ndarray:
    return np.zeros(6)


class SimulatedFT300:
    """An FT 300 on a pty, run by a background thread. Use as a context manager, or ``start()`` and ``stop()``.

    Args:
        wrench_source: called once per frame, returns the wrench ``(6,)`` [Fx, Fy, Fz, Mx, My, Mz] in N and N m
            (sensor frame) to send; zeros when ``None``. It runs on the simulator's thread.
        rate_hz: stream rate (the sensor's is about 100 Hz).
        link: path of a symlink to the pty slave, created on start and after each reconnect, removed on stop and
            disconnect. An existing symlink there is replaced; any other file is refused.
        slave_address: Modbus address it answers to (factory 9).
        faults: line faults applied to stream frames; change them later with ``set_faults``.
        seed: seed of the fault generator (drawn from only for frames sent while some fault rate is set).
        streaming: start out streaming, as a sensor left streaming by an earlier run.
        bias: ``(6,)`` the sensor's zero-load reading (N, N m), added to every wrench sent, as a real sensor's
            offset (a tare removes it); zeros by default.
        noise_scale: the signal noise added to every frame, as a multiple of the datasheet's (``noise.SIGNAL_NOISE``,
            0.1 N and 0.005/0.003 N m per frame at 1); 0 (the default) sends the wrench noise-free. Drawn from a
            generator seeded by ``seed`` of its own, so the same seed gives the same noise.
    """

    def __init__(
        self,
        wrench_source: Callable[[], np.ndarray] | None = None,
        *,
        rate_hz: float = STREAM_RATE_HZ,
        link: str | os.PathLike[str] | None = None,
        slave_address: int = SLAVE_ADDRESS,
        faults: FT300Faults = NO_FAULTS,
        seed: int = 0,
        streaming: bool = False,
        bias: np.ndarray | None = None,
        noise_scale: float = 0.0,
    ) -> None:
        if not rate_hz > 0:
            raise ValueError(f"rate_hz={rate_hz} must be positive")
        if not (np.isfinite(noise_scale) and noise_scale >= 0):
            raise ValueError(f"noise_scale={noise_scale} must be a finite number, 0 or more")
        self.bias = np.zeros(6) if bias is None else np.array(bias, dtype=np.float64).reshape(6)
        if not np.isfinite(self.bias).all():
            raise ValueError(f"bias={self.bias} must be 6 finite numbers")
        self.bias.flags.writeable = False
        self._source = wrench_source or _zero_wrench
        self._period_ns = round(1e9 / rate_hz)
        self.rate_hz = rate_hz
        self.link = Path(link) if link is not None else None
        self.slave_address = slave_address
        self._faults = faults
        self._rng = np.random.default_rng(seed)
        self.noise_scale = float(noise_scale)
        self._noise_rng = np.random.default_rng((NOISE_STREAM, seed))
        self._initially_streaming = streaming

        self._lock = threading.Lock()
        self._stats = SimulatorStats()
        self._history: deque[np.ndarray] = deque(maxlen=HISTORY_FRAMES)
        self._last_encoded: tuple[bytes, bytes, np.ndarray] | None = None  # (wrench bytes, frame, carried wrench)
        self._commands: deque[tuple[Callable[[], object], Future]] = deque()
        self._master_fd: int | None = None
        self._slave_fd: int | None = None
        self._slave_path: str | None = None
        self._streaming = False
        self._next_frame_ns = 0
        self._stall_until_ns = 0
        self._request_buffer = bytearray()
        self._wake_r: int | None = None
        self._wake_w: int | None = None
        self._running = False
        self._thread: threading.Thread | None = None

    def __repr__(self) -> str:
        return f"SimulatedFT300({self.port_path if self._slave_path else 'stopped'})"

    # -- public API (any thread) ---------------------------------------------------------------------------------

    @property
    def slave_path(self) -> str:
        """The pty slave device, ``/dev/pts/N`` (it changes on reconnect). Raises ``RuntimeError`` when stopped
        or disconnected."""
        if self._slave_path is None:
            raise RuntimeError(f"{self!r} has no pty (not started, or disconnected)")
        return self._slave_path

    @property
    def port_path(self) -> str:
        """What a client opens: the link when there is one, else the pty slave."""
        return str(self.link) if self.link is not None else self.slave_path

    @property
    def streaming(self) -> bool:
        """Whether the device is in stream mode (frames are due, whatever the stall)."""
        with self._lock:
            return self._streaming

    def stats(self) -> SimulatorStats:
        """A snapshot of the counters."""
        with self._lock:
            return self._stats

    def sent_wrenches(self) -> np.ndarray:
        """``(K, 6)`` the wrenches of the last frames sent (up to ``HISTORY_FRAMES``), as the frames carry them
        (``bias`` and noise included, rounded to 0.01 N, 0.001 N m), before any fault was applied."""
        with self._lock:
            return np.array(self._history).reshape(-1, 6)

    def set_faults(self, faults: FT300Faults) -> None:
        """Apply ``faults`` from the next frame on."""
        with self._lock:
            self._faults = faults

    def start(self) -> SimulatedFT300:
        """Open the pty (and the link) and start the device thread; returns ``self``."""
        if self._thread is not None:
            raise RuntimeError(f"{self!r} is already running")
        self._open_pty()
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        if self._initially_streaming:
            self._begin_stream()
        self._running = True
        self._thread = threading.Thread(target=self._run, name="SimulatedFT300", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the thread, close the pty and remove the link. Safe to call more than once."""
        thread = self._thread
        if thread is None:
            return
        if thread.is_alive():
            self._call(self._end_thread)
            thread.join(JOIN_TIMEOUT_S)
            if thread.is_alive():
                log.error("%r: thread did not end within %s s", self, JOIN_TIMEOUT_S)
        self._thread = None
        self._close_pty()
        for fd in (self._wake_r, self._wake_w):
            if fd is not None:
                os.close(fd)
        self._wake_r = self._wake_w = None

    def __enter__(self) -> SimulatedFT300:
        return self.start()

    def __exit__(self, *exc_info: object) -> None:
        self.stop()

    def stall(self, duration_s: float) -> None:
        """Write nothing (frames or replies) for ``duration_s`` from now; commands are still obeyed."""
        if not duration_s > 0:
            raise ValueError(f"stall duration_s={duration_s} must be positive")
        self._call(lambda: self._begin_stall(duration_s))

    def disconnect(self) -> None:
        """Unplug: close the pty (the client's next read fails) and remove the link."""
        self._call(self._unplug)

    def reconnect(self) -> None:
        """Plug back in: a new pty, idle (not streaming), behind the same link."""
        self._call(self._replug)

    # -- thread side ---------------------------------------------------------------------------------------------

    def _call(self, command: Callable[[], object]) -> object:
        """Run ``command`` on the device thread and return its result (raises ``RuntimeError`` when stopped)."""
        thread = self._thread
        if thread is None or not thread.is_alive():
            raise RuntimeError(f"{self!r} is not running")
        future: Future = Future()
        with self._lock:
            self._commands.append((command, future))
        os.write(self._wake_w, b"\0")
        return future.result(timeout=COMMAND_TIMEOUT_S)

    def _run(self) -> None:
        try:
            while self._running:
                self._serve_once()
        except Exception:
            log.exception("%r: device thread failed", self)
            raise

    def _serve_once(self) -> None:
        waiting_on = [self._wake_r] + ([self._master_fd] if self._master_fd is not None else [])
        readable, _, _ = select.select(waiting_on, [], [], self._wait_s())
        if self._wake_r in readable:
            while True:
                try:
                    if not os.read(self._wake_r, READ_CHUNK):
                        break
                except BlockingIOError:
                    break
            self._run_commands()
        if self._master_fd is not None and self._master_fd in readable:
            try:
                data = os.read(self._master_fd, READ_CHUNK)
            except OSError:  # EIO: no client holds the slave open (we keep it open, so only while unplugging)
                data = b""
            self._handle_input(data)
        self._send_due_frames()

    def _wait_s(self) -> float:
        if not self._streaming or self._master_fd is None:
            return IDLE_WAIT_S
        return min(IDLE_WAIT_S, max(0.0, (self._next_frame_ns - time.monotonic_ns()) / 1e9))

    def _run_commands(self) -> None:
        while True:
            with self._lock:
                if not self._commands:
                    return
                command, future = self._commands.popleft()
            try:
                future.set_result(command())
            except Exception as exc:  # the caller re-raises it from future.result()
                future.set_exception(exc)

    def _end_thread(self) -> None:
        self._running = False

    def _count(self, **increments: int) -> None:
        with self._lock:
            values = {name: getattr(self._stats, name) + n for name, n in increments.items()}
            self._stats = replace(self._stats, **values)

    def _begin_stall(self, duration_s: float) -> None:
        self._stall_until_ns = time.monotonic_ns() + round(duration_s * 1e9)
        self._count(stalls=1)

    def _stalled(self, now_ns: int) -> bool:
        return now_ns < self._stall_until_ns

    def _unplug(self) -> None:
        if self._master_fd is None:
            return
        self._close_pty()
        self._count(disconnects=1)

    def _replug(self) -> None:
        if self._master_fd is not None:
            raise RuntimeError(f"{self!r} is already connected")
        self._open_pty()
        self._count(reconnects=1)

    def _open_pty(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)
        os.set_blocking(master, False)
        self._master_fd, self._slave_fd = master, slave
        self._slave_path = os.ttyname(slave)
        with self._lock:
            self._streaming = False
        self._stall_until_ns = 0
        self._request_buffer.clear()
        if self.link is not None:
            try:
                self._point_link()
            except OSError:
                self._close_pty()
                raise

    def _point_link(self) -> None:
        if self.link.exists() and not self.link.is_symlink():
            raise FileExistsError(f"{self.link} exists and is not a symlink; refusing to replace it")
        temporary = self.link.with_name(f".{self.link.name}.{os.getpid()}.tmp")
        temporary.unlink(missing_ok=True)
        os.symlink(self._slave_path, temporary)
        os.replace(temporary, self.link)

    def _close_pty(self) -> None:
        if self.link is not None and self.link.is_symlink() and os.readlink(self.link) == self._slave_path:
            self.link.unlink()
        for fd in (self._master_fd, self._slave_fd):
            if fd is not None:
                os.close(fd)
        self._master_fd = self._slave_fd = None
        self._slave_path = None
        with self._lock:
            self._streaming = False

    def _write(self, data: bytes) -> None:
        """Write to the line; what the pty will not take is lost, as on a serial line nobody reads."""
        try:
            written = os.write(self._master_fd, data)
        except (BlockingIOError, OSError):
            written = 0
        if written < len(data):
            self._count(overflow_bytes=len(data) - written)

    def _begin_stream(self) -> None:
        with self._lock:
            self._streaming = True
        self._next_frame_ns = time.monotonic_ns() + self._period_ns

    def _handle_input(self, data: bytes) -> None:
        if self._streaming:
            if STOP_BYTE in data:  # the stream stops on the 0xFF burst; other bytes are ignored while streaming
                with self._lock:
                    self._streaming = False
                self._count(stop_bursts=1)
                self._request_buffer.clear()
            return
        self._request_buffer += data
        self._parse_requests()

    def _parse_requests(self) -> None:
        buffer = self._request_buffer
        while buffer:
            if buffer[0] == STOP_BYTE:  # the tail of a stop burst, between requests
                del buffer[:1]
                continue
            try:
                parsed = split_request(buffer)
            except ProtocolError:
                del buffer[:1]
                self._count(bad_request_bytes=1)
                continue
            if parsed is None:
                return
            request, size = parsed
            del buffer[:size]
            if request.slave == self.slave_address:
                self._answer(request)
                if self._streaming:
                    buffer.clear()
                    return

    def _answer(self, request: ModbusRequest) -> None:
        if request.function == FC_WRITE_MULTIPLE_REGISTERS and request.first_register == STREAM_REGISTER:
            reply = write_registers_reply(self.slave_address, request.first_register, request.count)
            self._reply(reply)
            if request.values[0] == STREAM_START_VALUE:
                self._count(start_requests=1)
                self._begin_stream()
        else:  # only the stream register is simulated
            self._reply(exception_reply(self.slave_address, request.function, ILLEGAL_DATA_ADDRESS))

    def _reply(self, reply: bytes) -> None:
        if not self._stalled(time.monotonic_ns()):
            self._write(reply)

    def _send_due_frames(self) -> None:
        if not self._streaming or self._master_fd is None:
            return
        now_ns = time.monotonic_ns()
        if now_ns < self._next_frame_ns:
            return
        if now_ns - self._next_frame_ns > MAX_LAG_FRAMES * self._period_ns:
            self._next_frame_ns = now_ns
        while self._next_frame_ns <= now_ns:
            self._next_frame_ns += self._period_ns
            if not self._stalled(now_ns):
                self._send_frame()

    def _send_frame(self) -> None:
        try:
            wrench = np.asarray(self._source(), dtype=np.float64) + self.bias
            if self.noise_scale:
                wrench = wrench + frame_noise(self._noise_rng, (6,), self.noise_scale)
            frame, carried = self._encoded(wrench)
        except Exception:
            log.exception("%r: wrench source failed; frame skipped", self)
            self._count(source_errors=1)
            return
        with self._lock:
            faults = self._faults
            self._history.append(carried)
        if faults == NO_FAULTS:  # a clean line: the frame as it is, and nothing drawn from the fault generator
            self._count(frames_sent=1)
            self._write(frame)
            return
        delivered, counts = inject_faults(frame, faults, self._rng)
        self._count(
            frames_sent=1,
            frames_corrupted=int(counts.bit_flips > 0 or counts.dropped_bytes > 0),
            bit_flips=counts.bit_flips,
            dropped_bytes=counts.dropped_bytes,
            garbage_bytes=counts.garbage_bytes,
        )
        self._write(delivered)

    def _encoded(self, wrench: np.ndarray) -> tuple[bytes, np.ndarray]:
        """The frame carrying ``wrench (6,)`` and the wrench as the frame carries it (read-only); a wrench equal to
        the previous one (a plant at rest) reuses the previous pair. Raises ``ValueError`` as ``encode_frame``."""
        key = wrench.tobytes()
        if self._last_encoded is None or self._last_encoded[0] != key:
            frame = encode_frame(wrench)
            carried = quantize_wrench(wrench)
            carried.flags.writeable = False
            self._last_encoded = (key, frame, carried)
        return self._last_encoded[1], self._last_encoded[2]


# -- command line ------------------------------------------------------------------------------------------------


def parse_wrench(text: str) -> np.ndarray:
    """``"fx,fy,fz,mx,my,mz"`` (N, N m) as a ``(6,)`` array; ``argparse.ArgumentTypeError`` otherwise."""
    try:
        values = np.array([float(part) for part in text.split(",")])
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"wrench {text!r}: {exc}") from exc
    if values.shape != (6,):
        raise argparse.ArgumentTypeError(f"wrench {text!r} needs 6 comma-separated numbers, got {values.size}")
    try:
        encode_frame(values)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from exc
    return values


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``hydrosoft-stack simulate ft300``."""
    parser.add_argument("--link", required=True, help="symlink to create to the simulator's pty (clients open it)")
    parser.add_argument("--rate", type=float, default=STREAM_RATE_HZ, help="stream rate in Hz (default 100)")
    parser.add_argument(
        "--wrench",
        type=parse_wrench,
        default=np.zeros(6),
        help="constant wrench fx,fy,fz,mx,my,mz in N and N m (default zeros)",
    )
    parser.add_argument("--bit-flip-rate", type=float, default=0.0, help="per frame byte, chance of a bit flip")
    parser.add_argument("--drop-rate", type=float, default=0.0, help="per frame byte, chance it is lost")
    parser.add_argument("--garbage-rate", type=float, default=0.0, help="per frame, chance of garbage before it")
    parser.add_argument("--noise", type=float, default=0.0,
                        help="signal noise per frame, as a multiple of the datasheet's (default 0: none)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the fault and noise generators")


def run(args: argparse.Namespace) -> int:
    """Serve one simulated FT 300 at ``args.link`` until SIGINT or SIGTERM, then print its counters. Returns 0, or 2
    when the settings are refused (bad rate or fault rate, a file in the way of the link)."""
    wrench = np.array(args.wrench, dtype=np.float64)
    try:
        faults = FT300Faults(args.bit_flip_rate, args.drop_rate, args.garbage_rate)
        simulator = SimulatedFT300(lambda: wrench, rate_hz=args.rate, link=args.link, faults=faults, seed=args.seed,
                                   noise_scale=args.noise)
        simulator.start()
    except (ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    finished = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: finished.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        print(f"FT 300 simulator at {simulator.link} -> {simulator.slave_path}, {args.rate:g} Hz; Ctrl-C stops")
        sys.stdout.flush()
        finished.wait()
    finally:
        simulator.stop()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    print(f"stopped: {simulator.stats()}", flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m hydrosoft.drivers.robotiq_ft300.simulator", description=__doc__)
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
