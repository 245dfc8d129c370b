"""The real ``FT300Sensor`` (pyserial) against the simulated device on a pty, with line faults, stalls and unplugs."""

from __future__ import annotations

import argparse
import asyncio
import time

import numpy as np
import pytest

from hydrosoft.drivers.base import ForceTorqueSensor
from hydrosoft.drivers.errors import DriverError, NotConnected, Stale
from hydrosoft.drivers.robotiq_ft300 import sensor as sensor_module
from hydrosoft.drivers.robotiq_ft300.protocol import quantize_wrench
from hydrosoft.drivers.robotiq_ft300.sensor import FT300Sensor
from hydrosoft.drivers.robotiq_ft300.simulator import FT300Faults

from .support import CountingWrench, fast_config, run_async, wait_for_sample

POLL_S = 0.002
WRENCH = np.array([12.34, -5.67, 89.01, 0.123, -0.456, 1.789])


async def wait_for_error(sensor: FT300Sensor, kind: type[DriverError], timeout_s: float = 1.0) -> DriverError:
    """The first error of type ``kind`` that ``read()`` raises (other errors are passed over), within ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            await sensor.read()
        except DriverError as exc:
            if isinstance(exc, kind):
                return exc
        await asyncio.sleep(POLL_S)
    raise TimeoutError(f"read() did not raise {kind.__name__} within {timeout_s} s")


def test_reads_the_simulated_wrench_at_the_stream_rate(make_simulator):
    simulator = make_simulator(wrench_source=lambda: WRENCH)

    async def scenario():
        sensor = FT300Sensor(fast_config(simulator.port_path))
        assert isinstance(sensor, ForceTorqueSensor)
        with pytest.raises(NotConnected, match="not connected"):
            await sensor.read()
        async with sensor:
            sample = await wait_for_sample(sensor)
            await asyncio.sleep(1.1)
            later = await wait_for_sample(sensor)
            health = sensor.health()
        return sample, later, health

    sample, later, health = run_async(scenario())
    np.testing.assert_allclose(sample.wrench[:3], WRENCH[:3], atol=0.01)  # N
    np.testing.assert_allclose(sample.wrench[3:], WRENCH[3:], atol=0.001)  # N m
    assert sample.hw_stamp_ns is None and later.stamp_ns > sample.stamp_ns
    with pytest.raises(ValueError):
        later.wrench[0] = 0.0  # the shared sample is read-only
    assert health.connected and 85.0 < health.rate_hz < 115.0
    assert health.frames >= 100 and (health.crc_errors, health.bytes_skipped, health.reconnects) == (0, 0, 0)
    assert health.last_frame_age_s < 0.05


def test_line_faults_never_reach_read(make_simulator):
    simulator = make_simulator(wrench_source=CountingWrench(), seed=3)

    async def scenario():
        samples = {}
        async with FT300Sensor(fast_config(simulator.port_path, max_age_s=0.1)) as sensor:
            simulator.set_faults(FT300Faults(bit_flip_rate=0.004, drop_rate=0.003, garbage_rate=0.05))
            deadline = time.monotonic() + 2.5
            while time.monotonic() < deadline:
                try:
                    sample = await sensor.read()
                    samples[sample.stamp_ns] = sample.wrench
                except Stale:
                    pass  # a run of damaged frames
                await asyncio.sleep(POLL_S)
            return samples, sensor.health()

    samples, health = run_async(scenario())
    stats = simulator.stats()
    sent = {tuple(w) for w in simulator.sent_wrenches()}
    assert stats.bit_flips > 0 and stats.dropped_bytes > 0 and stats.garbage_bytes > 0
    assert stats.frames_corrupted >= 10
    assert len(samples) > 100
    assert all(tuple(w) in sent for w in samples.values())  # not one returned wrench was damaged
    # Every damaged frame was refused: frames accepted never exceed the intact ones, and the scanner saw damage.
    assert health.frames <= stats.frames_sent - stats.frames_corrupted
    assert health.frames >= 0.8 * (stats.frames_sent - stats.frames_corrupted)
    assert health.crc_errors > 0 and health.bytes_skipped > 0 and health.resyncs > 0
    assert health.reconnects == 0


def test_stall_raises_stale_then_recovers_without_reconnecting(make_simulator):
    simulator = make_simulator(wrench_source=lambda: WRENCH)

    async def scenario():
        async with FT300Sensor(fast_config(simulator.port_path, restart_after_s=1.0)) as sensor:
            before = await wait_for_sample(sensor)
            simulator.stall(0.4)
            stale = await wait_for_error(sensor, Stale, timeout_s=0.3)
            during = sensor.health()
            after = await wait_for_sample(sensor, after_ns=before.stamp_ns + 300_000_000)
            return stale, during, after, sensor.health()

    stale, during, after, health = run_async(scenario())
    assert "old" in str(stale) and simulator.port_path in str(stale)
    assert during.last_frame_age_s > 0.05
    np.testing.assert_allclose(after.wrench, quantize_wrench(WRENCH))
    assert simulator.stats().stalls == 1 and health.reconnects == 0 and health.connected


def test_wait_newer_wakes_as_a_frame_arrives_and_times_out_during_a_stall(make_simulator):
    simulator = make_simulator(wrench_source=CountingWrench())

    async def scenario():
        async with FT300Sensor(fast_config(simulator.port_path, restart_after_s=1.0)) as sensor:
            first = await wait_for_sample(sensor)
            tic_s = time.monotonic()
            await sensor.wait_newer(first.stamp_ns, 5.0)
            woken_s = time.monotonic() - tic_s
            newer = await sensor.read()
            tic_s = time.monotonic()
            await sensor.wait_newer(0, 5.0)  # one is there already: no wait
            at_once_s = time.monotonic() - tic_s
            simulator.stall(0.6)
            await wait_for_error(sensor, Stale, timeout_s=0.3)  # the frames stopped
            frames = sensor.health().frames
            tic_s = time.monotonic()
            await sensor.wait_newer(time.monotonic_ns(), 0.1)
            stalled_s = time.monotonic() - tic_s
            return first, newer, woken_s, at_once_s, stalled_s, sensor.health().frames - frames

    first, newer, woken_s, at_once_s, stalled_s, frames_meanwhile = run_async(scenario())
    assert newer.stamp_ns > first.stamp_ns and woken_s < 1.0  # a frame comes every 10 ms; not the 5 s timeout
    assert at_once_s < 0.5
    assert 0.1 <= stalled_s < 1.0 and frames_meanwhile == 0  # the timeout ended it, raising nothing


def test_long_stall_restarts_the_stream(make_simulator):
    simulator = make_simulator(wrench_source=lambda: WRENCH)

    async def scenario():
        async with FT300Sensor(fast_config(simulator.port_path, restart_after_s=0.2)) as sensor:
            simulator.stall(0.6)
            down = await wait_for_error(sensor, NotConnected, timeout_s=0.5)
            after = await wait_for_sample(sensor, after_ns=time.monotonic_ns())
            return down, after, sensor.health()

    down, after, health = run_async(scenario())
    assert "no valid frame" in str(down)
    np.testing.assert_allclose(after.wrench, quantize_wrench(WRENCH))
    assert health.reconnects == 1 and health.connected
    assert simulator.stats().start_requests >= 2  # the restart asked for the stream again (maybe during the stall)


def test_unplug_raises_not_connected_and_replug_recovers(make_simulator):
    simulator = make_simulator(wrench_source=lambda: WRENCH)

    async def scenario():
        async with FT300Sensor(fast_config(simulator.port_path)) as sensor:
            await wait_for_sample(sensor)
            simulator.disconnect()
            down = await wait_for_error(sensor, NotConnected, timeout_s=0.5)
            await asyncio.sleep(0.3)  # reconnect attempts fail meanwhile: the link path is gone
            still_down = sensor.health()
            simulator.reconnect()
            after = await wait_for_sample(sensor, after_ns=time.monotonic_ns())
            return down, still_down, after, sensor.health()

    down, still_down, after, health = run_async(scenario())
    assert simulator.port_path in str(down)
    assert not still_down.connected and simulator.port_path in still_down.last_error
    np.testing.assert_allclose(after.wrench, quantize_wrench(WRENCH))
    stats = simulator.stats()
    assert (stats.disconnects, stats.reconnects) == (1, 1)
    assert health.reconnects == 1 and health.connected


def test_close_stops_the_stream(make_simulator):
    simulator = make_simulator(wrench_source=lambda: WRENCH)

    async def scenario():
        sensor = FT300Sensor(fast_config(simulator.port_path))
        await sensor.connect()
        assert simulator.streaming
        await sensor.close()
        await sensor.close()  # twice is fine
        with pytest.raises(NotConnected):
            await sensor.read()

    run_async(scenario())
    stats = simulator.stats()
    assert not simulator.streaming
    assert (stats.start_requests, stats.stop_bursts) == (1, 1)


def test_connect_stops_a_stream_left_running(make_simulator):
    simulator = make_simulator(wrench_source=lambda: WRENCH, streaming=True)

    async def scenario():
        async with FT300Sensor(fast_config(simulator.port_path)) as sensor:
            return await wait_for_sample(sensor)

    sample = run_async(scenario())
    np.testing.assert_allclose(sample.wrench, quantize_wrench(WRENCH))
    stats = simulator.stats()
    assert stats.stop_bursts == 2  # the one found running at connect, and ours at close
    assert stats.start_requests == 1


def test_connect_failures_name_the_port(make_simulator, tmp_path):
    missing = str(tmp_path / "no-such-port")
    with pytest.raises(NotConnected, match=f"cannot open {missing}"):
        run_async(FT300Sensor(fast_config(missing)).connect())
    deaf = make_simulator(slave_address=5)  # answers only address 5: our request goes unanswered
    with pytest.raises(NotConnected, match=f"no reply on {deaf.port_path}"):
        run_async(FT300Sensor(fast_config(deaf.port_path)).connect())


def test_hand_check_prints_the_wrench(make_simulator, capsys):
    simulator = make_simulator(wrench_source=lambda: WRENCH)
    args = argparse.Namespace(port=simulator.port_path, duration=0.6, slave_address=9)
    assert sensor_module.run(args) == 0
    output = capsys.readouterr().out
    assert "12.34" in output and "-0.456" in output and "health: FT300Health(connected=True" in output
    assert simulator.stats().stop_bursts == 1
