"""The FT 300 protocol without I/O: CRC vectors, frames, Modbus requests and the frame scanner."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hydrosoft.drivers.errors import ProtocolError
from hydrosoft.drivers.robotiq_ft300.config import FT300Config
from hydrosoft.drivers.robotiq_ft300.protocol import (
    FC_READ_HOLDING_REGISTERS,
    FC_WRITE_MULTIPLE_REGISTERS,
    FRAME_HEADER,
    FRAME_SIZE,
    STOP_BURST,
    FrameScanner,
    check_write_registers_reply,
    crc16_modbus,
    decode_frame,
    encode_frame,
    exception_reply,
    quantize_wrench,
    split_request,
    start_stream_reply,
    start_stream_request,
    with_crc,
    write_registers_request,
)
from hydrosoft.drivers.robotiq_ft300.simulator import FT300Faults, inject_faults

from .support import CountingWrench

INT16 = st.integers(-(2**15), 2**15 - 1)


def frames_of(wrenches) -> bytes:
    return b"".join(encode_frame(w) for w in wrenches)


def counting_wrenches(count: int) -> list[np.ndarray]:
    source = CountingWrench()
    return [quantize_wrench(source()) for _ in range(count)]


def as_rows(wrenches) -> list[tuple[float, ...]]:
    return [tuple(w) for w in wrenches]


# -- CRC and fixed messages ---------------------------------------------------------------------------------------


def test_crc_matches_the_standard_check_value():
    assert crc16_modbus(b"123456789") == 0x4B37
    assert crc16_modbus(b"") == 0xFFFF


def test_start_request_and_reply_are_the_reference_bytes():
    assert start_stream_request() == bytes.fromhex("09 10 01 9A 00 01 02 02 00 CD CA")
    assert start_stream_reply() == bytes.fromhex("09 10 01 9A 00 01 21 52")
    assert STOP_BURST == b"\xff" * 50


def test_frame_layout_matches_the_manual():
    frame = encode_frame([1.0, -2.0, 200.0, 0.5, -0.001, 32.767])
    assert len(frame) == FRAME_SIZE
    assert frame[:2] == FRAME_HEADER
    assert frame[2:4] == (100).to_bytes(2, "little")  # Fx 1.00 N in 1/100 N
    assert frame[4:6] == (-200).to_bytes(2, "little", signed=True)
    assert frame[6:8] == FRAME_HEADER  # Fz 200.00 N = 20000 counts = 0x4E20: a header inside the payload
    assert frame[8:10] == (500).to_bytes(2, "little")  # Mx 0.5 N m in 1/1000 N m
    assert frame[14:] == crc16_modbus(frame[:14]).to_bytes(2, "little")  # CRC over the header too


# -- frames -------------------------------------------------------------------------------------------------------


@given(st.lists(INT16, min_size=6, max_size=6))
def test_frame_round_trip_is_exact_at_the_frame_resolution(counts):
    wrench = np.array(counts, dtype=float) / np.array([100, 100, 100, 1000, 1000, 1000])
    decoded = decode_frame(encode_frame(wrench))
    np.testing.assert_array_equal(decoded, wrench)


def test_encoding_rounds_to_the_resolution():
    decoded = decode_frame(encode_frame([1.234, -0.006, 0, 0.0004, 0.0006, -1.2345]))
    np.testing.assert_allclose(decoded, [1.23, -0.01, 0, 0.0, 0.001, -1.234], atol=1e-12)


@pytest.mark.parametrize(
    ("wrench", "message"),
    [
        ([0.0] * 5, "shape"),
        ([0, 0, float("nan"), 0, 0, 0], "non-finite"),
        ([0, 0, 0, 0, 0, 33.0], "component 5"),
        ([-327.69, 0, 0, 0, 0, 0], "component 0"),
    ],
)
def test_encoding_refuses_what_a_frame_cannot_carry(wrench, message):
    with pytest.raises(ValueError, match=message):
        encode_frame(wrench)


def test_decoding_refuses_bad_frames():
    frame = encode_frame([1, 2, 3, 0.1, 0.2, 0.3])
    with pytest.raises(ProtocolError, match="16 bytes"):
        decode_frame(frame[:-1])
    with pytest.raises(ProtocolError, match="header"):
        decode_frame(b"\x21" + frame[1:])
    flipped = bytearray(frame)
    flipped[5] ^= 0x10
    with pytest.raises(ProtocolError, match="CRC"):
        decode_frame(bytes(flipped))


# -- Modbus ----------------------------------------------------------------------------------------------------------


def test_write_reply_check_accepts_the_echo_and_names_failures():
    check_write_registers_reply(start_stream_reply(), 9, 410, 1)
    with pytest.raises(ProtocolError, match="illegal data address"):
        check_write_registers_reply(exception_reply(9, FC_WRITE_MULTIPLE_REGISTERS, 2), 9, 410, 1)
    with pytest.raises(ProtocolError, match="unexpected reply 09 10 01 9a 00 02"):
        check_write_registers_reply(with_crc(bytes.fromhex("09 10 01 9A 00 02")), 9, 410, 1)
    with pytest.raises(ProtocolError, match="unexpected reply"):
        check_write_registers_reply(start_stream_reply()[:-1] + b"\x00", 9, 410, 1)


@given(
    slave=st.integers(1, 247),
    register=st.integers(0, 0xFFFF),
    values=st.lists(st.integers(0, 0xFFFF), min_size=1, max_size=10),
)
def test_write_request_round_trips_through_the_parser(slave, register, values):
    request = write_registers_request(slave, register, values)
    assert split_request(request[:-1]) is None  # incomplete
    parsed, size = split_request(request + b"\x09")
    assert size == len(request)
    assert (parsed.slave, parsed.function, parsed.first_register) == (slave, FC_WRITE_MULTIPLE_REGISTERS, register)
    assert parsed.values == tuple(values) and parsed.count == len(values)


def test_parser_reads_function_3_and_refuses_bad_requests():
    read = with_crc(bytes([9, FC_READ_HOLDING_REGISTERS, 0, 180, 0, 6]))
    parsed, size = split_request(read)
    assert (parsed.function, parsed.first_register, parsed.count, size) == (3, 180, 6, 8)
    with pytest.raises(ProtocolError, match="CRC"):
        split_request(start_stream_request()[:-1] + b"\x00")
    with pytest.raises(ProtocolError, match="function 0x2b"):
        split_request(bytes([9, 0x2B, 0, 0]))
    with pytest.raises(ProtocolError, match="byte count"):
        split_request(bytes.fromhex("09 10 01 9A 00 01 03 02 00"))
    with pytest.raises(ValueError, match="registers"):
        write_registers_request(9, 410, [])


# -- the frame scanner -----------------------------------------------------------------------------------------


def test_header_inside_payload_does_not_misalign_the_scanner():
    # Every value 200.00 N or 20.000 N m: each payload is 20 4E repeated, so a reader that frames on the header
    # alone cannot tell where frames start. Begin mid-frame, right at an inner header.
    wrenches = [[200.0, 200.0, 200.0, 20.0, 20.0, 20.0 + 0.001 * k] for k in range(6)]
    stream = frames_of(wrenches)
    scanner = FrameScanner()
    found = scanner.feed(stream[6:])  # frame 0 cut: starts at its Fz, which is 20 4E
    assert as_rows(found) == as_rows(quantize_wrench(w) for w in wrenches[1:])
    assert scanner.bytes_skipped == FRAME_SIZE - 6
    assert scanner.crc_errors >= 1  # the inner headers of the cut frame were tried and refused


def test_scanner_resyncs_after_a_corrupted_frame():
    wrenches = counting_wrenches(10)
    stream = bytearray(frames_of(wrenches))
    stream[4 * FRAME_SIZE + 7] ^= 0x01  # one bit in frame 4
    scanner = FrameScanner()
    found = scanner.feed(bytes(stream))
    assert as_rows(found) == as_rows(wrenches[:4] + wrenches[5:])
    assert (scanner.frames, scanner.resyncs) == (9, 1)
    assert scanner.crc_errors >= 1 and scanner.bytes_skipped >= FRAME_SIZE


def test_scanner_resyncs_after_a_lost_byte_and_garbage():
    wrenches = counting_wrenches(10)
    frames = [encode_frame(w) for w in wrenches]
    frames[3] = frames[3][:9] + frames[3][10:]  # a byte lost in frame 3
    frames[6] = FRAME_HEADER + b"\x01\x02\x20" + frames[6]  # garbage with a false header before frame 6
    scanner = FrameScanner()
    found = scanner.feed(b"".join(frames))
    assert as_rows(found) == as_rows(wrenches[:3] + wrenches[4:])
    assert scanner.resyncs == 2


def test_scanner_keeps_a_trailing_header_byte_and_waits_for_the_rest():
    frames = frames_of(counting_wrenches(3))
    scanner = FrameScanner()
    assert scanner.feed(b"\x00\x11\x20") == []
    assert scanner.pending_bytes == 1 and scanner.bytes_skipped == 2
    assert scanner.feed(frames[1:FRAME_SIZE]) == []  # first frame complete, but unconfirmed until the next header
    assert len(scanner.feed(frames[FRAME_SIZE : FRAME_SIZE + 2])) == 1
    assert len(scanner.feed(frames[FRAME_SIZE + 2 :])) == 2  # aligned now: each frame comes out when complete


@settings(max_examples=60, deadline=None)
@given(
    garbage=st.binary(max_size=40),
    cuts=st.lists(st.integers(0, 30 * FRAME_SIZE), max_size=20),
)
def test_scanner_output_does_not_depend_on_chunking(garbage, cuts):
    wrenches = counting_wrenches(30)
    stream = garbage + frames_of(wrenches)
    bounds = [0, *sorted(c for c in cuts if c < len(stream)), len(stream)]
    whole = FrameScanner().feed(stream)
    chunked_scanner = FrameScanner()
    chunked = [w for a, b in zip(bounds, bounds[1:]) for w in chunked_scanner.feed(stream[a:b])]
    assert as_rows(chunked) == as_rows(whole)
    # Garbage in front costs nothing: every frame after it is found (a false frame would need a CRC match).
    assert as_rows(whole) == as_rows(wrenches)


def emitted_at(scanner: FrameScanner, stream: bytes, chunk_sizes) -> list[int]:
    """Feed ``stream`` in chunks whose sizes ``chunk_sizes(scanner)`` picks: the stream position (bytes read) at which
    each frame came out, in order."""
    positions, read = [], 0
    while read < len(stream):
        chunk = stream[read : read + chunk_sizes(scanner)]
        read += len(chunk)
        positions += [read] * len(scanner.feed(chunk))
    return positions


@settings(max_examples=60, deadline=None)
@given(garbage=st.binary(max_size=40), damaged=st.sets(st.integers(0, 30 * FRAME_SIZE - 1), max_size=4))
def test_reading_the_bytes_the_scanner_wants_delays_no_frame(garbage, damaged):
    """The reader thread asks for ``bytes_wanted`` bytes at a time: each frame still comes out at the byte it would
    byte by byte (no read ends past the byte that completes one), after garbage and damaged bytes too."""
    stream = bytearray(garbage + frames_of(counting_wrenches(30)))
    for index in damaged:
        stream[len(garbage) + index] ^= 0x5A
    stream = bytes(stream)
    byte_by_byte = emitted_at(FrameScanner(), stream, lambda scanner: 1)
    assert len(byte_by_byte) >= 30 - 3 * len(damaged) - 1
    assert emitted_at(FrameScanner(), stream, lambda scanner: scanner.bytes_wanted) == byte_by_byte
    aligned = FrameScanner()
    assert aligned.bytes_wanted == FRAME_SIZE + 2  # a first frame needs the next one's header behind it
    aligned.feed(frames_of(counting_wrenches(2)) + FRAME_HEADER + b"\x01")
    assert aligned.bytes_wanted == FRAME_SIZE - 3  # aligned: the rest of the frame begun


def test_scanner_never_yields_a_corrupted_frame_under_heavy_faults():
    """20 000 frames through a line that flips bits, drops bytes and inserts garbage: everything found was sent,
    in the order sent, and most intact frames get through."""
    wrenches = counting_wrenches(20_000)
    faults = FT300Faults(bit_flip_rate=0.004, drop_rate=0.002, garbage_rate=0.02)
    rng = np.random.default_rng(7)
    scanner = FrameScanner()
    found_index = []
    index_of = {w: k for k, w in enumerate(as_rows(wrenches))}
    intact = flips = drops = 0
    for wrench in wrenches:
        delivered, counts = inject_faults(encode_frame(wrench), faults, rng)
        intact += counts.bit_flips == 0 and counts.dropped_bytes == 0
        flips += counts.bit_flips
        drops += counts.dropped_bytes
        for found in scanner.feed(delivered):
            found_index.append(index_of[tuple(found)])  # KeyError: a wrench that was never sent
    assert flips > 500 and drops > 250
    assert found_index == sorted(set(found_index))  # in order, no duplicates
    assert scanner.frames == len(found_index)
    assert len(found_index) <= intact
    assert len(found_index) >= 0.85 * intact  # an intact frame is lost only beside a damaged one
    assert scanner.crc_errors > 0 and scanner.resyncs > 0


def test_fault_injection_is_seeded_and_counted():
    frame = encode_frame([1, 2, 3, 0.1, 0.2, 0.3])
    clean, counts = inject_faults(frame, FT300Faults(), np.random.default_rng(0))
    assert clean == frame and counts == (0, 0, 0)
    dropped, counts = inject_faults(frame, FT300Faults(drop_rate=1.0), np.random.default_rng(0))
    assert dropped == b"" and counts.dropped_bytes == FRAME_SIZE
    flipped, counts = inject_faults(frame, FT300Faults(bit_flip_rate=1.0), np.random.default_rng(0))
    differing_bits = sum(bin(a ^ b).count("1") for a, b in zip(flipped, frame))
    assert counts.bit_flips == FRAME_SIZE and differing_bits == FRAME_SIZE
    again, _ = inject_faults(frame, FT300Faults(bit_flip_rate=1.0), np.random.default_rng(0))
    assert again == flipped
    with pytest.raises(ValueError, match="probability"):
        FT300Faults(drop_rate=1.5)


# -- config ---------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"port": ""}, "port is empty"),
        ({"max_age_s": 0.005}, "max_age_s"),
        ({"restart_after_s": 0.04}, "restart_after_s"),
        ({"read_timeout_s": -1.0}, "read_timeout_s"),
        ({"stop_silence_s": 0.015}, "stop_silence_s"),
        ({"backoff_initial_s": 3.0}, "backoff_max_s"),
        ({"slave_address": 300}, "slave_address"),
    ],
)
def test_config_refuses_inconsistent_settings(overrides, message):
    with pytest.raises(ValueError, match=message):
        FT300Config(**({"port": "/dev/null"} | overrides))
