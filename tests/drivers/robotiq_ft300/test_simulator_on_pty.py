"""The simulator on its pty, seen by a raw serial client: it answers and streams as the device does."""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import serial

from hydrosoft.drivers.robotiq_ft300.noise import SIGNAL_NOISE
from hydrosoft.drivers.robotiq_ft300.protocol import (
    FC_WRITE_MULTIPLE_REGISTERS,
    FRAME_SIZE,
    STOP_BURST,
    WRITE_REPLY_SIZE,
    FrameScanner,
    encode_frame,
    exception_reply,
    quantize_wrench,
    start_stream_reply,
    start_stream_request,
    write_registers_request,
)
from hydrosoft.drivers.robotiq_ft300.sensor import FT300Sensor
from hydrosoft.drivers.robotiq_ft300.simulator import FT300Faults, SimulatedFT300, inject_faults

from .support import fast_config, run_async, wait_for_sample

READ_TIMEOUT_S = 0.5
PROCESS_TIMEOUT_S = 10.0


def open_client(path: str) -> serial.Serial:
    return serial.Serial(path, 19200, timeout=READ_TIMEOUT_S)


def read_frames(port: serial.Serial, count: int, timeout_s: float = 2.0) -> list[np.ndarray]:
    scanner = FrameScanner()
    found: list[np.ndarray] = []
    deadline = time.monotonic() + timeout_s
    while len(found) < count and time.monotonic() < deadline:
        found += scanner.feed(port.read(port.in_waiting or 1))
    return found


def test_idle_until_started_then_streams_then_stops_on_the_burst(make_simulator):
    wrench = np.array([1.5, -2.25, 30.0, 0.125, -0.5, 1.0])
    simulator = make_simulator(wrench_source=lambda: wrench)
    with open_client(simulator.port_path) as port:
        assert port.read(1) == b""  # idle: nothing until asked
        port.write(start_stream_request())
        assert port.read(WRITE_REPLY_SIZE) == start_stream_reply()
        frames = read_frames(port, 20)
        assert len(frames) == 20
        np.testing.assert_array_equal(frames[-1], wrench)
        port.write(STOP_BURST)
        deadline = time.monotonic() + READ_TIMEOUT_S
        while simulator.streaming and time.monotonic() < deadline:
            time.sleep(0.001)
        port.reset_input_buffer()
        assert port.read(1) == b""  # silent once it has read the burst
    stats = simulator.stats()
    assert not simulator.streaming
    assert (stats.start_requests, stats.stop_bursts) == (1, 1)
    assert stats.frames_sent >= 20


def test_unknown_register_gets_a_modbus_exception(make_simulator):
    simulator = make_simulator()
    with open_client(simulator.port_path) as port:
        port.write(write_registers_request(9, 411, [1]))
        assert port.read(5) == exception_reply(9, FC_WRITE_MULTIPLE_REGISTERS, 2)
        port.write(start_stream_request(slave=5))  # another slave's request: no answer
        assert port.read(1) == b""
        port.write(b"\x09\x10\x01\x9a\x00\x01\x02\x02\x00\x00\x00")  # bad CRC: ignored
        assert port.read(1) == b""
    assert simulator.stats().bad_request_bytes > 0
    assert not simulator.streaming


def test_rate_is_close_to_the_setting(make_simulator):
    simulator = make_simulator(rate_hz=100.0)
    with open_client(simulator.port_path) as port:
        port.write(start_stream_request())
        port.read(WRITE_REPLY_SIZE)
        start = time.monotonic()
        frames = read_frames(port, 50)
        elapsed_s = time.monotonic() - start
    assert len(frames) == 50
    assert 0.4 < elapsed_s < 0.8  # 50 frames at 100 Hz; loose for two shared cores


def test_frames_follow_the_wrench_and_a_clean_line_leaves_the_fault_generator_alone(make_simulator):
    applied = {"wrench": np.array([1.0, 2.0, 3.0, 0.1, 0.2, 0.3])}
    simulator = make_simulator(wrench_source=lambda: applied["wrench"], seed=7)
    with open_client(simulator.port_path) as port:
        port.write(start_stream_request())
        port.read(WRITE_REPLY_SIZE)
        before = read_frames(port, 10)
        applied["wrench"] = np.array([-4.0, 5.0, -6.0, 0.4, -0.5, 0.6])
        time.sleep(0.05)
        port.reset_input_buffer()
        after = read_frames(port, 10)
        clean = port.read(FRAME_SIZE)  # the stream's writes are whole frames: it stays aligned
        faults = FT300Faults(bit_flip_rate=1.0)
        simulator.set_faults(faults)
        damaged = clean
        while damaged == clean:
            damaged = port.read(FRAME_SIZE)
    np.testing.assert_array_equal(before[-1], [1.0, 2.0, 3.0, 0.1, 0.2, 0.3])
    np.testing.assert_array_equal(after[-1], [-4.0, 5.0, -6.0, 0.4, -0.5, 0.6])
    np.testing.assert_array_equal(simulator.sent_wrenches()[-1], [-4.0, 5.0, -6.0, 0.4, -0.5, 0.6])
    # the first faulty frame is the seed's first draw: the clean frames before it drew nothing
    assert damaged == inject_faults(encode_frame(applied["wrench"]), faults, np.random.default_rng(7))[0]


def test_link_is_refused_over_a_regular_file(tmp_path):
    occupied = tmp_path / "taken"
    occupied.write_text("not a link")
    with pytest.raises(FileExistsError, match="not a symlink"):
        SimulatedFT300(link=occupied).start()
    assert occupied.read_text() == "not a link"


def read_line(process: subprocess.Popen, timeout_s: float) -> str:
    ready, _, _ = select.select([process.stdout], [], [], timeout_s)
    if not ready:
        raise TimeoutError(f"no output from pid {process.pid} within {timeout_s} s")
    return process.stdout.readline()


def test_command_line_simulator_serves_the_real_driver_and_stops_on_sigint(tmp_path):
    link = tmp_path / "ft300"
    process = subprocess.Popen(
        [sys.executable, "-m", "hydrosoft.drivers.robotiq_ft300.simulator", "--link", str(link),
         "--wrench", "1.5,-2,3,0.1,0.2,-0.3"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        banner = read_line(process, PROCESS_TIMEOUT_S)
        assert str(link) in banner and "/dev/pts/" in banner

        async def read_once():
            async with FT300Sensor(fast_config(str(link))) as sensor:
                return await wait_for_sample(sensor)

        sample = run_async(read_once())
        np.testing.assert_allclose(sample.wrench, [1.5, -2, 3, 0.1, 0.2, -0.3], atol=1e-9)
        process.send_signal(signal.SIGINT)
        assert process.wait(PROCESS_TIMEOUT_S) == 0
        rest = process.stdout.read()
        assert "stopped:" in rest and "start_requests=1" in rest and "stop_bursts=1" in rest
        assert not os.path.lexists(link)
    finally:
        if process.poll() is None:
            os.kill(process.pid, signal.SIGKILL)
            process.wait(PROCESS_TIMEOUT_S)


def test_its_frames_carry_the_sensors_offset_on_top_of_the_wrench(make_simulator):
    wrench = np.array([0.5, 0.0, 1.9, 0.0, 0.01, 0.0])
    bias = np.array([1.2, -0.8, 2.5, 0.04, -0.03, 0.02])
    simulator = make_simulator(wrench_source=lambda: wrench, bias=bias)
    np.testing.assert_array_equal(simulator.bias, bias)
    with open_client(simulator.port_path) as port:
        port.write(start_stream_request())
        assert port.read(WRITE_REPLY_SIZE) == start_stream_reply()
        frames = read_frames(port, 5)
        port.write(STOP_BURST)
    np.testing.assert_allclose(frames[-1], wrench + bias, atol=1e-9)
    np.testing.assert_allclose(simulator.sent_wrenches()[-1], wrench + bias, atol=1e-9)
    with pytest.raises(ValueError, match="finite"):
        SimulatedFT300(bias=np.array([0.0, 0.0, np.nan, 0.0, 0.0, 0.0]))


def test_with_noise_each_frame_carries_the_datasheet_noise_drawn_from_its_seed(make_simulator):
    wrench = np.array([0.5, 0.0, 1.9, 0.0, 0.01, 0.0])
    noisy = [make_simulator(wrench_source=lambda: wrench, rate_hz=1000.0, noise_scale=1.0, seed=7) for _ in range(2)]
    quiet = make_simulator(wrench_source=lambda: wrench, rate_hz=1000.0, noise_scale=0.0)
    received = {}
    for name, simulator in (("noisy", noisy[0]), ("twin", noisy[1]), ("quiet", quiet)):
        with open_client(simulator.port_path) as port:
            port.write(start_stream_request())
            assert port.read(WRITE_REPLY_SIZE) == start_stream_reply()
            received[name] = np.array(read_frames(port, 400, timeout_s=10.0)[:400])
            port.write(STOP_BURST)
    assert len(received["noisy"]) == 400 and len(received["quiet"]) == 400
    assert np.all(np.abs(received["noisy"].mean(axis=0) - wrench) < 4 * SIGNAL_NOISE / np.sqrt(400))
    np.testing.assert_allclose(received["noisy"].std(axis=0), SIGNAL_NOISE, rtol=0.15)
    np.testing.assert_array_equal(received["noisy"][:100], received["twin"][:100])  # the same seed, the same noise
    np.testing.assert_array_equal(received["quiet"], np.broadcast_to(quantize_wrench(wrench), (400, 6)))
    for bad in (-0.1, np.nan):
        with pytest.raises(ValueError, match="noise_scale"):
            SimulatedFT300(noise_scale=bad)
