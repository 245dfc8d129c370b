"""The F/T reader service: one arm's tared wrenches from its Robotiq FT 300.

One per arm, named ``ft_reader-ARM``. It waits up to ``PORT_WAIT_S`` for the sensor's port ``arm.ft_port`` to
appear (in sim mode sim_world links its simulated FT 300's pseudo-terminal there), connects the real driver
(``drivers.robotiq_ft300.FT300Sensor``) and tares it: the bias is the mean of the samples of the first ``TARE_S``
(the arm must not touch anything meanwhile; a tare the sensor interrupts starts again). Then it publishes every
new sample minus that bias as ``wrench/ARM`` (``Wrench``, ``tared=True``, N and N m in the sensor frame) at the
sensor's rate (~100 Hz).

A sensor that sends nothing new for ``STALE_AFTER_S`` (stale, unplugged or reconnecting: the driver reconnects on
its own) is counted under the driver error's kind (``stale``, ``not_connected``, ...) once per ``STALE_AFTER_S``,
and the service reports ``degraded`` until samples come again; no wrench is published meanwhile, and a sample is
never published twice. Frames that fail their CRC are counted as ``crc`` from the driver's health every
``HEALTH_PERIOD_S``. None of these ends the service.

Run: ``python -m hydrosoft.services.ft_reader CONFIG [--name ft_reader-ARM]``.
"""

from __future__ import annotations

import argparse
import asyncio
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from hydrosoft.drivers.base import ForceTorqueSensor, WrenchSample
from hydrosoft.drivers.errors import DeviceFault, DriverError, NotConnected, ProtocolError, Stale
from hydrosoft.drivers.robotiq_ft300.config import FT300Config
from hydrosoft.drivers.robotiq_ft300.sensor import FT300Sensor
from hydrosoft.services import messages as msg
from hydrosoft.services.config import StackConfig
from hydrosoft.services import arm_service_main, service_main
from hydrosoft.services.runtime import Service

MODULE = "ft_reader"
#: How long the port may take to appear (sim: until sim_world has linked its pty), s.
PORT_WAIT_S = 30.0
#: How often the port's path is looked for meanwhile, s.
PORT_POLL_S = 0.1
#: How long connecting may take, retries included, s (one attempt stops the stream, starts it, waits for a frame).
CONNECT_TIMEOUT_S = 10.0
#: Pause between connect attempts, s.
CONNECT_RETRY_S = 0.5
#: The tare averages the samples of this long after connecting, s (~20 frames at 100 Hz).
TARE_S = 0.2
#: The service publishes nothing and counts an error after this long without a new sample, s (10 frame periods).
STALE_AFTER_S = 0.1
#: How often the driver is polled for a new sample, s (half the FT 300's 10 ms frame period).
POLL_PERIOD_S = 0.005
#: How often the driver's CRC error count is read, s.
HEALTH_PERIOD_S = 1.0


def bias_of(wrenches: Sequence[np.ndarray]) -> np.ndarray:
    """The tare bias ``(6,)`` (N, N m): the mean of ``wrenches`` (each ``(6,)``). Raises ValueError when there are
    none or one is not 6 finite numbers."""
    stacked = np.asarray(wrenches, dtype=np.float64).reshape(-1, 6) if len(wrenches) else np.empty((0, 6))
    if stacked.shape[0] == 0 or stacked.shape[0] != len(wrenches) or not np.isfinite(stacked).all():
        raise ValueError(f"a tare needs at least one finite (6,) wrench, got {len(wrenches)} samples")
    return stacked.mean(axis=0)


def wrench_message(sample: WrenchSample, bias: np.ndarray, sensor: str) -> msg.Wrench:
    """The ``Wrench`` message of ``sample`` minus ``bias`` ``(6,)`` (tared), with the sample's hardware stamp."""
    return msg.Wrench(sensor=sensor, wrench=np.asarray(sample.wrench, dtype=np.float64) - bias, tared=True,
                      hw_stamp_ns=sample.hw_stamp_ns)


def error_kind(error: DriverError) -> str:
    """The short name under which the service counts a driver error."""
    for kind, name in ((Stale, "stale"), (NotConnected, "not_connected"), (ProtocolError, "protocol"),
                       (DeviceFault, "device_fault")):
        if isinstance(error, kind):
            return name
    return "driver"


async def next_sample(sensor: ForceTorqueSensor, after_ns: int, timeout_s: float = STALE_AFTER_S,
                      poll_s: float = POLL_PERIOD_S) -> WrenchSample:
    """The sensor's newest sample stamped after ``after_ns`` (``time.monotonic_ns``), polling every ``poll_s`` for
    up to ``timeout_s``. Raises the driver's last error (``Stale``, ``NotConnected``, ...) or, when it kept
    handing out the same sample, ``Stale``."""
    deadline_ns = time.monotonic_ns() + round(timeout_s * 1e9)
    while True:
        error: DriverError | None = None
        try:
            sample = await sensor.read()
            if sample.stamp_ns > after_ns:
                return sample
        except DriverError as err:
            error = err
        if time.monotonic_ns() >= deadline_ns:
            raise error or Stale(f"no new F/T sample within {timeout_s} s")
        await asyncio.sleep(poll_s)


async def wait_for_port(port: str, timeout_s: float = PORT_WAIT_S) -> None:
    """Return once the serial port ``port`` exists; raises NotConnected after ``timeout_s``."""
    deadline_s = time.monotonic() + timeout_s
    while not Path(port).exists():
        if time.monotonic() > deadline_s:
            raise NotConnected(f"serial port {port} did not appear within {timeout_s} s (sim: is sim_world up?)")
        await asyncio.sleep(PORT_POLL_S)


async def connect(sensor: ForceTorqueSensor, timeout_s: float = CONNECT_TIMEOUT_S) -> None:
    """Connect ``sensor``, retrying every ``CONNECT_RETRY_S``; raises the last error after ``timeout_s``."""
    deadline_s = time.monotonic() + timeout_s
    while True:
        try:
            await sensor.connect()
            return
        except DriverError:
            if time.monotonic() + CONNECT_RETRY_S > deadline_s:
                raise
        await asyncio.sleep(CONNECT_RETRY_S)


async def tare(sensor: ForceTorqueSensor, duration_s: float = TARE_S) -> np.ndarray:
    """The bias ``(6,)`` of ``sensor``: the mean of its new samples over ``duration_s``. Raises the driver's error
    when it sends nothing new for ``STALE_AFTER_S``."""
    end_ns = time.monotonic_ns() + round(duration_s * 1e9)
    wrenches, last_ns = [], 0
    while last_ns < end_ns or not wrenches:
        sample = await next_sample(sensor, last_ns)
        wrenches.append(sample.wrench)
        last_ns = sample.stamp_ns
    return bias_of(wrenches)


async def serve(service: Service, config: StackConfig, arm: str) -> None:
    """Publish ``arm``'s tared wrenches until cancelled (module docstring)."""
    port = config.arm(arm).ft_port
    await wait_for_port(port)
    sensor = FT300Sensor(FT300Config(port=port))
    service.on_shutdown(sensor.close)
    await connect(sensor)
    while True:
        try:
            bias = await tare(sensor)
            break
        except DriverError as error:
            service.count_error(error_kind(error), f"tare failed, starting it again: {error}")
    service.log.info("tared: bias %s N, N m", np.array2string(bias, precision=3))
    out = service.publisher(config.endpoint(service.name))
    topic = msg.topic_for(msg.Wrench, arm)
    await service.ready()
    health_task = asyncio.create_task(_count_crc_errors_forever(service, sensor))
    try:
        last_ns = 0
        while True:
            try:
                sample = await next_sample(sensor, last_ns)
            except DriverError as error:
                service.count_error(error_kind(error), str(error))
                if service.state != "degraded":
                    await service.set_state("degraded")
                continue
            last_ns = sample.stamp_ns
            try:
                await out.send(wrench_message(sample, bias, arm), topic)
            except msg.MessageError as error:
                service.count_error(error.kind, f"cannot publish the wrench: {error}")
                continue
            if service.state != "ready":
                await service.set_state("ready")
    finally:
        health_task.cancel()


async def _count_crc_errors_forever(service: Service, sensor: FT300Sensor) -> None:
    """Every ``HEALTH_PERIOD_S``, count the frames ``sensor`` rejected for their CRC."""
    counted = sensor.health().crc_errors
    while True:
        await asyncio.sleep(HEALTH_PERIOD_S)
        total = sensor.health().crc_errors
        if total > counted:
            service.count_error("crc", f"{total - counted} F/T frames failed their CRC in {HEALTH_PERIOD_S} s "
                                       f"({total} since start)")
        counted = total


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments: CONFIG [--name MODULE-ARM] (``arm_service_main``)."""
    arm_service_main.add_arguments(parser, MODULE)


def run(args: argparse.Namespace) -> int:
    """Run the service until SIGINT/SIGTERM; the exit code (2: a bad config or name)."""
    return arm_service_main.run(args, MODULE, serve)


def main(argv: list[str] | None = None) -> int:
    return service_main.main(MODULE, __doc__, argv, add_arguments, run)


if __name__ == "__main__":
    service_main.exit_process(main())
