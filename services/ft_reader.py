"""The F/T reader service: one arm's wrenches from its Robotiq FT 300, less the stored tare.

One per arm, named ``ft_reader-ARM``. It waits up to ``PORT_WAIT_S`` for the sensor's port ``arm.ft_port`` to
appear (in sim mode sim_world links its simulated FT 300's pseudo-terminal there), connects the real driver
(``drivers.robotiq_ft300.FT300Sensor``) and loads the arm's stored tare (``services/arm/ft_bias.py``, a file in
``state_dir``). It never tares by itself: a reader started or restarted while the bubble presses on something
keeps subtracting the bias taken out of contact, so it still reads the load.

It publishes every new sample as ``wrench/ARM`` (``Wrench``, N and N m in the sensor frame) at the sensor's rate
(~100 Hz): less the stored bias, ``tared=True``; or, with no usable stored bias (none yet, or a file that is
corrupt or belongs to another sensor: counted as ``bias_file``), the raw reading with ``tared=False``, and the
service reports ``degraded``. The status note says which: the bias, when it was taken and its age, or why the
readings are untared.

Tare on request only: ``Tare`` on the cmd endpoint (``hydrosoft-stack ft tare ARM``). It is refused, with the reason,
unless the arm is at rest and the bubble shows no contact (``services/arm/tare_rules.py``, from ``arm_state/ARM`` and
``deformation/ARM``, each published after the check began, read only then: between tares the reader decodes
none of the commander's 125 states a second) before and after averaging the samples of ``TARE_S``, and those samples were
steady. An accepted tare is stored first (a tare that cannot be stored is refused), then used.

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
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, TypeVar, runtime_checkable

import numpy as np

from hydrosoft.drivers.base import ForceTorqueSensor, WrenchSample
from hydrosoft.drivers.errors import DeviceFault, DriverError, NotConnected, ProtocolError, Stale
from hydrosoft.drivers.robotiq_ft300.config import FT300Config
from hydrosoft.drivers.robotiq_ft300.sensor import FT300Sensor
from hydrosoft.services.bus import messages as msg
from hydrosoft.services.bus import service_cli
from hydrosoft.services.bus.sockets import LatestSubscriber, Stale as StaleInput
from hydrosoft.services.bus.config import StackConfig
from hydrosoft.services.arm.ft_bias import BiasFileError, StoredBias, bias_path, load_bias, save_bias
from hydrosoft.services.bus.runtime import Service
from hydrosoft.services.arm.tare_rules import (
    ARM_STATE_MAX_AGE_S,
    DEFORMATION_MAX_AGE_S,
    spread_refusal,
    tare_refusal,
)

M = TypeVar("M", bound=msg.Message)

MODULE = "ft_reader"
#: How long the port may take to appear (sim: until sim_world has linked its pty), s.
PORT_WAIT_S = 30.0
#: How often the port's path is looked for meanwhile, s.
PORT_POLL_S = 0.1
#: How long connecting may take, retries included, s (one attempt stops the stream, starts it, waits for a frame).
CONNECT_TIMEOUT_S = 10.0
#: Pause between connect attempts, s.
CONNECT_RETRY_S = 0.5
#: A tare averages the samples of this long, s (~50 frames at 100 Hz).
TARE_S = 0.5
#: The service publishes nothing and counts an error after this long without a new sample, s (10 frame periods).
STALE_AFTER_S = 0.1
#: How often a driver that cannot wake the reader (or that raised) is polled for a new sample, s (half the FT 300's
#: 10 ms frame period).
POLL_PERIOD_S = 0.005
#: How often the driver's CRC error count is read and the status note (the bias's age) renewed, s.
HEALTH_PERIOD_S = 1.0
#: Who a tare taken on request is stored as (``StoredBias.source``).
TARE_SOURCE = "ft tare"


def bias_of(wrenches: Sequence[np.ndarray]) -> np.ndarray:
    """The tare bias ``(6,)`` (N, N m): the mean of ``wrenches`` (each ``(6,)``). Raises ValueError when there are
    none or one is not 6 finite numbers."""
    stacked = np.asarray(wrenches, dtype=np.float64).reshape(-1, 6) if len(wrenches) else np.empty((0, 6))
    if stacked.shape[0] == 0 or stacked.shape[0] != len(wrenches) or not np.isfinite(stacked).all():
        raise ValueError(f"a tare needs at least one finite (6,) wrench, got {len(wrenches)} samples")
    return stacked.mean(axis=0)


def wrench_message(sample: WrenchSample, bias: np.ndarray | None, sensor: str) -> msg.Wrench:
    """The ``Wrench`` message of ``sample`` minus ``bias`` ``(6,)`` (``tared=True``), or of the raw sample when
    ``bias`` is None (``tared=False``), with the sample's hardware stamp."""
    wrench = np.asarray(sample.wrench, dtype=np.float64)
    return msg.Wrench(sensor=sensor, wrench=wrench if bias is None else wrench - bias, tared=bias is not None,
                      hw_stamp_ns=sample.hw_stamp_ns)


@dataclass
class CurrentBias:
    """The bias the reader subtracts: ``stored`` (None: none usable, readings go out untared) and, then, why not
    (``untared_because``)."""

    stored: StoredBias | None
    untared_because: str = ""

    @property
    def bias(self) -> np.ndarray | None:
        """The bias ``(6,)`` (N, N m), or None when untared."""
        return None if self.stored is None else self.stored.vector

    def note(self) -> str:
        """The status note: the bias and its age, or why the readings are untared."""
        if self.stored is not None:
            return self.stored.describe()
        return f"NOT TARED: {self.untared_because}; readings are raw (tared=False)"


def stored_tare(path: Path, arm: str, port: str) -> tuple[CurrentBias, str | None]:
    """The tare stored at ``path`` for ``arm``'s sensor on ``port`` and, when the file exists but cannot be used,
    the error to count (``bias_file``). Never a zero bias in place of a missing or broken one."""
    try:
        stored = load_bias(path, arm, port)
    except BiasFileError as error:
        return CurrentBias(None, f"stored bias unusable ({error})"), str(error)
    if stored is None:
        return CurrentBias(None, f"no stored bias ({path}): run `hydrosoft-stack ft tare {arm}` with the bubble "
                                 "clear of everything"), None
    return CurrentBias(stored), None


def error_kind(error: DriverError) -> str:
    """The short name under which the service counts a driver error."""
    for kind, name in ((Stale, "stale"), (NotConnected, "not_connected"), (ProtocolError, "protocol"),
                       (DeviceFault, "device_fault")):
        if isinstance(error, kind):
            return name
    return "driver"


@runtime_checkable
class WakingSensor(ForceTorqueSensor, Protocol):
    """A sensor that can wake its reader when a new sample arrives (``FT300Sensor``)."""

    async def wait_newer(self, after_ns: int, timeout_s: float) -> None: ...


async def next_sample(sensor: ForceTorqueSensor, after_ns: int, timeout_s: float = STALE_AFTER_S,
                      poll_s: float = POLL_PERIOD_S) -> WrenchSample:
    """The sensor's newest sample stamped after ``after_ns`` (``time.monotonic_ns``), waiting up to ``timeout_s``:
    woken as it arrives by a ``WakingSensor``, else polling every ``poll_s``. Raises the driver's last error
    (``Stale``, ``NotConnected``, ...) or, when it kept handing out the same sample, ``Stale``."""
    deadline_ns = time.monotonic_ns() + round(timeout_s * 1e9)
    waking = isinstance(sensor, WakingSensor)
    while True:
        error: DriverError | None = None
        try:
            sample = await sensor.read()
            if sample.stamp_ns > after_ns:
                return sample
        except DriverError as err:
            error = err
        now_ns = time.monotonic_ns()
        if now_ns >= deadline_ns:
            raise error or Stale(f"no new F/T sample within {timeout_s} s")
        if waking and error is None:
            await sensor.wait_newer(after_ns, (deadline_ns - now_ns) / 1e9)
        else:
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


async def samples_over(sensor: ForceTorqueSensor, duration_s: float = TARE_S) -> np.ndarray:
    """The new samples' wrenches ``(K, 6)`` of ``sensor`` over ``duration_s``. Raises the driver's error when it
    sends nothing new for ``STALE_AFTER_S``."""
    end_ns = time.monotonic_ns() + round(duration_s * 1e9)
    wrenches, last_ns = [], 0
    while last_ns < end_ns or not wrenches:
        sample = await next_sample(sensor, last_ns)
        wrenches.append(sample.wrench)
        last_ns = sample.stamp_ns
    return np.asarray(wrenches, dtype=np.float64).reshape(-1, 6)


async def fresh_input(subscriber: LatestSubscriber, topic: str, kind: type[M], max_age_s: float) -> M | None:
    """The first ``kind`` message on ``topic`` published after this call began, waiting up to ``max_age_s`` (s) for
    it; None when none comes. For a subscriber read only now and then (the tare's): what queued since its last read
    is the oldest of what was sent meanwhile (the bus's high-water marks' and the socket buffers' worth: the
    publisher drops the newer ones while they are full), so none of it counts, however young; it is drained, and a
    message published after the call follows within a publishing period."""
    loop = asyncio.get_running_loop()
    asked_s = loop.time()
    deadline_s = asked_s + max_age_s
    while True:
        try:
            received = subscriber.latest(topic, max_age_s, kind)
            if received.age_s <= loop.time() - asked_s:  # published after the call began
                return received.value
        except StaleInput:
            pass
        remaining_s = deadline_s - loop.time()
        if remaining_s <= 0:
            return None
        await subscriber.wait(remaining_s)


class TareServer:
    """Answers ``Tare`` requests for ``arm``'s sensor: checks the arm and the bubble (``arm.tare_rules``), averages,
    checks again, stores the bias at ``path`` and only then hands it to the publishing loop (``current``).

    Args:
        sensor: the connected sensor. current: the reader's tare, replaced on success. arm, port: whose sensor.
        path: the bias file. arm_states, deformations: subscribers of ``arm_state/ARM`` and ``deformation/ARM``,
        read only while a tare is checked (``fresh_input``), so that no message is decoded between tares.
    """

    def __init__(self, service: Service, sensor: ForceTorqueSensor, current: CurrentBias, arm: str, port: str,
                 path: Path, arm_states: LatestSubscriber, deformations: LatestSubscriber) -> None:
        self.service, self.sensor, self.current, self.arm, self.port, self.path = (service, sensor, current, arm,
                                                                                    port, path)
        self._arm_states, self._deformations = arm_states, deformations

    async def refusal(self) -> str | None:
        """Why a tare may not be taken now (``tare_rules.tare_refusal`` on the newest fresh inputs), or None."""
        arm_state = await fresh_input(self._arm_states, msg.topic_for(msg.ArmState, self.arm), msg.ArmState,
                                      ARM_STATE_MAX_AGE_S)
        deformation = await fresh_input(self._deformations, msg.topic_for(msg.MembraneDeformation, self.arm),
                                        msg.MembraneDeformation, DEFORMATION_MAX_AGE_S)
        return tare_refusal(arm_state, deformation, self.arm)

    async def handle(self, request: msg.Request) -> msg.Reply:
        """The reply to ``request`` (a ``Tare``; anything else is refused); the outcome is logged."""
        if not isinstance(request, msg.Tare):
            return request.reply(ok=False, error=f"ft_reader-{self.arm} answers only Tare, not "
                                                 f"{type(request).__name__}")
        refused = await self.refusal()
        if refused is None:
            try:
                wrenches = await samples_over(self.sensor)
            except DriverError as error:
                refused = f"the sensor failed while averaging: {error}"
            else:
                refused = spread_refusal(wrenches) or await self.refusal()
        if refused is None:
            stored = StoredBias(arm=self.arm, port=self.port, bias=tuple(float(v) for v in bias_of(list(wrenches))),
                                taken_unix_ns=time.time_ns(), samples=len(wrenches), source=TARE_SOURCE)
            try:
                await asyncio.to_thread(save_bias, self.path, stored)
            except OSError as error:
                refused = f"the bias cannot be stored at {self.path}: {error}"
        if refused is not None:
            self.service.log.warning("tare requested by %r refused: %s", request.source, refused)
            return msg.TareReply(ok=False, error=f"tare refused: {refused}")
        self.current.stored, self.current.untared_because = stored, ""
        spread = wrenches.max(axis=0) - wrenches.min(axis=0)
        self.service.log.info("tare requested by %r taken and stored in %s: %s; peak-to-peak over its %d samples "
                              "%.3f N, %.4f N m", request.source, self.path, stored.describe(), len(wrenches),
                              spread[:3].max(), spread[3:].max())
        return msg.TareReply(ok=True, bias=stored.vector, taken_unix_ns=stored.taken_unix_ns)


async def serve(service: Service, config: StackConfig, arm: str) -> None:
    """Publish ``arm``'s wrenches, less the stored tare, and serve tare requests until cancelled (module
    docstring)."""
    port = config.arm(arm).ft_port
    await wait_for_port(port)
    sensor = FT300Sensor(FT300Config(port=port))
    service.on_shutdown(sensor.close)
    await connect(sensor)
    path = bias_path(config.state_path(), arm)
    current, error_text = stored_tare(path, arm, port)
    if error_text is not None:
        service.count_error("bias_file", error_text)
    service.note = current.note()
    service.log.info("%s", service.note)
    out = service.publisher(config.endpoint(service.name))
    topic = msg.topic_for(msg.Wrench, arm)
    arm_states = service.subscriber(config.endpoint(f"arm_commander-{arm}"), [msg.topic_for(msg.ArmState, arm)])
    deformations = service.subscriber(config.endpoint(f"bubble_camera-{arm}"),
                                      [msg.topic_for(msg.MembraneDeformation, arm)])
    tares = TareServer(service, sensor, current, arm, port, path, arm_states, deformations)
    requests = service.request_server(config.endpoint(service.name, "cmd"), tares.handle)
    await service.ready()
    health_task = asyncio.create_task(_health_forever(service, sensor, current))
    request_task = service.supervise(asyncio.create_task(requests.serve(), name=f"{service.name}.requests"))
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
                await out.send(wrench_message(sample, current.bias, arm), topic)
            except msg.MessageError as error:
                service.count_error(error.kind, f"cannot publish the wrench: {error}")
                continue
            healthy = "ready" if current.stored is not None else "degraded"
            if service.state != service.effective_state(healthy):
                service.note = current.note()
                await service.set_state(healthy)
    finally:
        health_task.cancel()
        request_task.cancel()


async def _health_forever(service: Service, sensor: FT300Sensor, current: CurrentBias) -> None:
    """Every ``HEALTH_PERIOD_S``, renew the status note (the bias's age) and count the frames ``sensor`` rejected
    for their CRC."""
    counted = sensor.health().crc_errors
    while True:
        await asyncio.sleep(HEALTH_PERIOD_S)
        service.note = current.note()
        total = sensor.health().crc_errors
        if total > counted:
            service.count_error("crc", f"{total - counted} F/T frames failed their CRC in {HEALTH_PERIOD_S} s "
                                       f"({total} since start)")
        counted = total


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments: CONFIG [--name MODULE-ARM] (``service_cli``)."""
    service_cli.add_arm_arguments(parser, MODULE)


def run(args: argparse.Namespace) -> int:
    """Run the service until SIGINT/SIGTERM; the exit code (2: a bad config or name)."""
    return service_cli.run_arm(args, MODULE, serve)


def main(argv: list[str] | None = None) -> int:
    return service_cli.main(MODULE, __doc__, argv, add_arguments, run)


if __name__ == "__main__":
    service_cli.exit_process(main())
