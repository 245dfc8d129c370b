"""The FT 300's serial protocol, pure (no I/O): CRC-16/Modbus, stream frames, the Modbus requests that start the
stream and the burst that stops it, and a scanner that finds frames in an arbitrary byte stream.

Facts (Robotiq FT 300 manual, "data stream" section; ROS driver ``rq_sensor_com.cpp``; summarised in
``docs/devices.md`` section 7):

- The line is 19200 baud 8N1. Out of the box the sensor is a Modbus RTU slave, address 9.
- Writing 0x0200 to holding register 410 (function 16) starts the stream; the sensor echoes the request's address
  and count, then sends 16-byte frames at about 100 Hz (83 % of the line at 19200 baud).
- A frame is ``20 4E | Fx Fy Fz (int16 LE, 1/100 N) | Mx My Mz (int16 LE, 1/1000 N m) | CRC (LE)`` with the CRC
  over the 14 bytes before it, header included. Values are in the sensor frame.
- About 50 bytes of 0xFF stop the stream; the sensor is then a Modbus slave again.
- Modbus request fields are big-endian; stream values and every CRC are little-endian.
- ``20 4E`` can occur inside a frame (Fx = 200.00 N is 0x4E20), so frames are found by header AND CRC.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from hydrosoft.drivers.errors import ProtocolError

BAUD_RATE = 19200
SLAVE_ADDRESS = 9
STREAM_RATE_HZ = 100.0
FRAME_PERIOD_S = 1.0 / STREAM_RATE_HZ

# Stream frame (manual, data stream section).
FRAME_HEADER = b"\x20\x4e"
HEADER_SIZE = len(FRAME_HEADER)
FRAME_SIZE = 16
CRC_SIZE = 2
_FRAME_BODY = struct.Struct("<2s6h")  # header, Fx Fy Fz Mx My Mz counts: the 14 bytes the CRC covers
COUNTS_PER_UNIT = np.array([100.0, 100.0, 100.0, 1000.0, 1000.0, 1000.0])  # counts per N (forces), per N m (moments)
INT16_MIN, INT16_MAX = -(2**15), 2**15 - 1

# Stopping the stream (manual: "send 0xFF for about 0.5 s"; ROS driver and the Python example: 50 bytes).
STOP_BYTE = 0xFF
STOP_BURST_SIZE = 50
STOP_BURST = bytes([STOP_BYTE]) * STOP_BURST_SIZE

# Modbus RTU (Modbus application protocol v1.1b3, sections 6.3 and 6.12; registers from the FT 300 manual).
FC_READ_HOLDING_REGISTERS = 0x03
FC_WRITE_MULTIPLE_REGISTERS = 0x10
EXCEPTION_FLAG = 0x80
MODBUS_EXCEPTIONS = {
    0x01: "illegal function",
    0x02: "illegal data address",
    0x03: "illegal data value",
    0x04: "slave device failure",
}
ILLEGAL_DATA_ADDRESS = 0x02
STREAM_REGISTER = 410
STREAM_START_VALUE = 0x0200
MAX_WRITE_REGISTERS = 123  # Modbus limit for function 16
WRITE_REPLY_SIZE = 8  # slave, function, first register, count, CRC
EXCEPTION_REPLY_SIZE = 5  # slave, function | 0x80, exception code, CRC
_WRITE_HEADER = struct.Struct(">BBHHB")  # slave, function, first register, count, byte count
_WRITE_REPLY = struct.Struct(">BBHH")  # slave, function, first register, count
_READ_REQUEST = struct.Struct(">BBHH")  # slave, function, first register, count

# CRC-16/Modbus: reflected polynomial 0xA001 (0x8005), initial value 0xFFFF, no final xor.
CRC_POLYNOMIAL = 0xA001
CRC_INITIAL = 0xFFFF


def _crc_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ CRC_POLYNOMIAL if crc & 1 else crc >> 1
        table.append(crc)
    return tuple(table)


_CRC_TABLE = _crc_table()


def crc16_modbus(data: bytes | bytearray | memoryview) -> int:
    """CRC-16/Modbus of ``data`` (check value: ``crc16_modbus(b"123456789") == 0x4B37``). Sent low byte first."""
    crc = CRC_INITIAL
    for byte in data:
        crc = (crc >> 8) ^ _CRC_TABLE[(crc ^ byte) & 0xFF]
    return crc


def with_crc(message: bytes) -> bytes:
    """``message`` followed by its CRC-16/Modbus, low byte first (Modbus RTU and stream frames alike)."""
    return message + crc16_modbus(message).to_bytes(CRC_SIZE, "little")


def crc_matches(message: bytes | bytearray | memoryview) -> bool:
    """Whether the last two bytes of ``message`` are the CRC (LE) of the bytes before them."""
    if len(message) < CRC_SIZE:
        return False
    return crc16_modbus(message[:-CRC_SIZE]) == int.from_bytes(message[-CRC_SIZE:], "little")


def encode_frame(wrench: Sequence[float] | np.ndarray) -> bytes:
    """One 16-byte stream frame carrying ``wrench (6,)`` ``[Fx, Fy, Fz, Mx, My, Mz]`` in N and N m (sensor frame).

    Values are rounded to the frame's resolution (0.01 N, 0.001 N m). Raises ``ValueError`` for a wrong shape, a
    non-finite value or one outside int16 counts (|F| > 327.67 N, |M| > 32.767 N m).
    """
    values = np.asarray(wrench, dtype=np.float64)
    if values.shape != (6,):
        raise ValueError(f"a wrench has shape (6,), got {values.shape}")
    if not np.all(np.isfinite(values)):
        raise ValueError(f"wrench has a non-finite value: {values.tolist()}")
    counts = np.rint(values * COUNTS_PER_UNIT)
    outside = (counts < INT16_MIN) | (counts > INT16_MAX)
    if np.any(outside):
        axis = int(np.argmax(outside))
        raise ValueError(
            f"wrench component {axis} = {values[axis]} does not fit a frame "
            f"(limits +-{INT16_MAX / COUNTS_PER_UNIT[axis]}, in N or N m)"
        )
    return with_crc(_FRAME_BODY.pack(FRAME_HEADER, *(int(c) for c in counts)))


def _decode_counts(frame: bytes | bytearray | memoryview) -> np.ndarray:
    header_and_counts = _FRAME_BODY.unpack_from(frame)
    return np.array(header_and_counts[1:], dtype=np.float64) / COUNTS_PER_UNIT


def decode_frame(frame: bytes | bytearray | memoryview) -> np.ndarray:
    """The wrench ``(6,)`` float64 (N, N m, sensor frame) in one 16-byte stream frame.

    Raises ``ProtocolError`` for a wrong length, a wrong header or a CRC that does not match.
    """
    if len(frame) != FRAME_SIZE:
        raise ProtocolError(f"a stream frame has {FRAME_SIZE} bytes, got {len(frame)}")
    if frame[:HEADER_SIZE] != FRAME_HEADER:
        raise ProtocolError(f"stream frame header is {bytes(frame[:HEADER_SIZE]).hex(' ')}, expected 20 4e")
    if not crc_matches(frame):
        received = int.from_bytes(frame[-CRC_SIZE:], "little")
        raise ProtocolError(
            f"stream frame CRC 0x{received:04x} does not match the computed 0x{crc16_modbus(frame[:-CRC_SIZE]):04x}"
        )
    return _decode_counts(frame)


def quantize_wrench(wrench: Sequence[float] | np.ndarray) -> np.ndarray:
    """``wrench (6,)`` as a frame carries it: what ``decode_frame(encode_frame(wrench))`` returns."""
    return _decode_counts(encode_frame(wrench))


def _check_slave(slave: int) -> None:
    if not 0 <= slave <= 247:
        raise ValueError(f"Modbus slave address {slave} is outside 0..247")


def _check_register(register: int) -> None:
    if not 0 <= register <= 0xFFFF:
        raise ValueError(f"Modbus register {register} is outside 0..65535")


def write_registers_request(slave: int, first_register: int, values: Sequence[int]) -> bytes:
    """Modbus RTU function 16 (write multiple registers): ``values`` (each 0..65535) from ``first_register``."""
    _check_slave(slave)
    _check_register(first_register)
    if not 1 <= len(values) <= MAX_WRITE_REGISTERS:
        raise ValueError(f"function 16 writes 1..{MAX_WRITE_REGISTERS} registers, got {len(values)}")
    if any(not 0 <= v <= 0xFFFF for v in values):
        raise ValueError(f"register values must be 0..65535, got {list(values)}")
    header = _WRITE_HEADER.pack(slave, FC_WRITE_MULTIPLE_REGISTERS, first_register, len(values), 2 * len(values))
    return with_crc(header + struct.pack(f">{len(values)}H", *values))


def write_registers_reply(slave: int, first_register: int, count: int) -> bytes:
    """The slave's normal reply to a function-16 request: its address, the first register and the count."""
    return with_crc(_WRITE_REPLY.pack(slave, FC_WRITE_MULTIPLE_REGISTERS, first_register, count))


def exception_reply(slave: int, function: int, code: int) -> bytes:
    """A Modbus exception reply: ``function | 0x80`` and the exception ``code`` (see ``MODBUS_EXCEPTIONS``)."""
    return with_crc(bytes([slave, function | EXCEPTION_FLAG, code]))


def start_stream_request(slave: int = SLAVE_ADDRESS) -> bytes:
    """The request that starts the stream, 0x0200 into register 410; for slave 9:
    ``09 10 01 9A 00 01 02 02 00 CD CA``."""
    return write_registers_request(slave, STREAM_REGISTER, [STREAM_START_VALUE])


def start_stream_reply(slave: int = SLAVE_ADDRESS) -> bytes:
    """The sensor's reply to ``start_stream_request`` (for slave 9: ``09 10 01 9A 00 01 21 52``)."""
    return write_registers_reply(slave, STREAM_REGISTER, 1)


def check_write_registers_reply(reply: bytes, slave: int, first_register: int, count: int) -> None:
    """Raise ``ProtocolError`` unless ``reply`` is the normal reply to a function-16 write of ``count`` registers
    at ``first_register``; a Modbus exception reply is named in the message."""
    if (
        len(reply) == EXCEPTION_REPLY_SIZE
        and reply[0] == slave
        and reply[1] == FC_WRITE_MULTIPLE_REGISTERS | EXCEPTION_FLAG
        and crc_matches(reply)
    ):
        code = reply[2]
        raise ProtocolError(
            f"slave {slave} refused the write to register {first_register}: Modbus exception {code} "
            f"({MODBUS_EXCEPTIONS.get(code, 'unknown code')})"
        )
    expected = write_registers_reply(slave, first_register, count)
    if reply != expected:
        raise ProtocolError(f"unexpected reply {reply.hex(' ') or '(none)'}, expected {expected.hex(' ')}")


@dataclass(frozen=True)
class ModbusRequest:
    """One parsed Modbus RTU request: function 16 carries ``values``, function 3 asks for ``count`` registers."""

    slave: int
    function: int
    first_register: int
    count: int
    values: tuple[int, ...] = ()


def split_request(buffer: bytes | bytearray) -> tuple[ModbusRequest, int] | None:
    """The Modbus request at the start of ``buffer`` and its length in bytes, or ``None`` while it is incomplete.

    Understands functions 3 and 16 (what the FT 300's host sends). Raises ``ProtocolError`` for another function,
    an inconsistent byte count or a bad CRC; the caller drops a byte and tries again (a slave ignores bad frames).
    """
    if len(buffer) < 2:
        return None
    slave, function = buffer[0], buffer[1]
    if function == FC_READ_HOLDING_REGISTERS:
        size = _READ_REQUEST.size + CRC_SIZE
        if len(buffer) < size:
            return None
        _, _, first, count = _READ_REQUEST.unpack_from(buffer)
        request = ModbusRequest(slave, function, first, count)
    elif function == FC_WRITE_MULTIPLE_REGISTERS:
        if len(buffer) < _WRITE_HEADER.size:
            return None
        _, _, first, count, byte_count = _WRITE_HEADER.unpack_from(buffer)
        if byte_count != 2 * count or not 1 <= count <= MAX_WRITE_REGISTERS:
            raise ProtocolError(f"function 16 request with count {count} and byte count {byte_count}")
        size = _WRITE_HEADER.size + byte_count + CRC_SIZE
        if len(buffer) < size:
            return None
        values = struct.unpack_from(f">{count}H", buffer, _WRITE_HEADER.size)
        request = ModbusRequest(slave, function, first, count, values)
    else:
        raise ProtocolError(f"unsupported Modbus function 0x{function:02x}")
    if not crc_matches(buffer[:size]):
        raise ProtocolError(f"Modbus request CRC mismatch in {bytes(buffer[:size]).hex(' ')}")
    return request, size


class FrameScanner:
    """Finds valid stream frames in byte chunks of any size and counts what it had to throw away.

    A frame is accepted only where the header ``20 4E`` starts 16 bytes whose CRC matches. While aligned, frames
    follow each other back to back. After any loss (at the start, after skipped bytes or a failed CRC) the scanner
    moves one byte at a time and, before accepting a candidate, also requires the next frame's header right after
    it: a ``20 4E`` inside a payload then needs a chance CRC match (1 in 65536) AND a header 16 bytes later to be
    mistaken for a frame. The first frame after a loss therefore comes out when the next frame's first two bytes
    arrive (one frame period later). The output does not depend on how the bytes are split into chunks.

    Counters (since creation): ``frames`` accepted; ``crc_errors``: candidates at a header whose CRC failed
    (corrupted frames, and headers seen inside payloads while out of step); ``bytes_skipped``: bytes dropped
    while looking for a frame; ``resyncs``: times alignment was found again after being lost (the first
    alignment is not counted).
    """

    def __init__(self) -> None:
        self._buffer = bytearray()
        self._aligned = False
        self._ever_aligned = False
        self.frames = 0
        self.crc_errors = 0
        self.bytes_skipped = 0
        self.resyncs = 0

    @property
    def pending_bytes(self) -> int:
        """Bytes held back until more data decides whether they start a frame."""
        return len(self._buffer)

    @property
    def bytes_wanted(self) -> int:
        """The fewest more bytes that can complete a frame (at least 1): a reader that asks for this many (or for all
        that are waiting, when more) gets every frame as soon as its last byte arrives, in one read per frame."""
        needed = FRAME_SIZE if self._aligned else FRAME_SIZE + HEADER_SIZE
        return max(1, needed - len(self._buffer))

    def clear(self) -> None:
        """Start over on a new link: forget buffered bytes and the alignment (its first alignment is not counted as
        a resync); counters are kept."""
        self._buffer.clear()
        self._aligned = self._ever_aligned = False

    def _skip(self, count: int) -> None:
        del self._buffer[:count]
        self.bytes_skipped += count
        self._aligned = False

    def feed(self, chunk: bytes | bytearray | memoryview) -> list[np.ndarray]:
        """Append ``chunk`` and return the wrenches ``(6,)`` (N, N m) of every frame completed by it, in order."""
        buffer = self._buffer
        buffer += chunk
        wrenches = []
        while True:
            start = buffer.find(FRAME_HEADER)
            if start < 0:
                keep = 1 if buffer[-1:] == FRAME_HEADER[:1] else 0  # could be the first byte of a header
                if len(buffer) > keep:
                    self._skip(len(buffer) - keep)
                break
            if start > 0:
                self._skip(start)
            needed = FRAME_SIZE if self._aligned else FRAME_SIZE + HEADER_SIZE
            if len(buffer) < needed:
                break
            if not crc_matches(buffer[:FRAME_SIZE]):
                self.crc_errors += 1
                self._skip(1)
                continue
            if not self._aligned and buffer[FRAME_SIZE : FRAME_SIZE + HEADER_SIZE] != FRAME_HEADER:
                self._skip(1)
                continue
            wrenches.append(_decode_counts(buffer))
            del buffer[:FRAME_SIZE]
            self.frames += 1
            if not self._aligned:
                self.resyncs += self._ever_aligned
                self._aligned = self._ever_aligned = True
        return wrenches

