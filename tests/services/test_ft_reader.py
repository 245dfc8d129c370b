"""The F/T reader service: its plain parts (tare, messages, polling a fake sensor) and the service as a real process
reading a ``SimulatedFT300`` the test starts behind the config's ``ft_port``: it waits for the port, publishes the
simulator's wrench minus the stored tare, rejects corrupted frames and publishes nothing while the sensor stalls;
and it tares only on request, only with the arm at rest and the bubble out of contact (fake ``arm_state`` and
``deformation`` publishers stand in for the arm commander and the bubble camera), and a reader killed and started
again under load keeps the stored tare.

The process gets a private run_dir and is stopped by its pid; the simulator is stopped by the test; every wait has
a timeout.
"""

from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest
from service_process import ServiceProcess

from hydrosoft.drivers.base import WrenchSample
from hydrosoft.drivers.errors import NotConnected, ProtocolError, Stale
from hydrosoft.drivers.robotiq_ft300.simulator import FT300Faults, SimulatedFT300
from hydrosoft.services.bus import sockets as bus_layer
from hydrosoft.services.bus import messages as msg
from hydrosoft.services.bus.sockets import Bus, LatestSubscriber
from hydrosoft.services.bus.config import load_config
from hydrosoft.services.arm.ft_bias import StoredBias, bias_path, load_bias, save_bias
from hydrosoft.services.commands.ft import request_tare
from hydrosoft.services.ft_reader import (
    bias_of,
    error_kind,
    fresh_input,
    next_sample,
    samples_over,
    wait_for_port,
    wrench_message,
)

SCENARIO_TIMEOUT_S = 40.0
TEST_TIMEOUT_S = 10.0
BIAS = np.array([1.5, -2.0, 3.25, 0.1, -0.2, 0.3])  # what the sensor reads at rest, N and N m
PUSH = np.array([0.5, 0.25, -4.0, 0.02, 0.0, -0.01])  # the contact wrench applied after the tare
FORCE_ATOL_N, TORQUE_ATOL_NM = 0.011, 0.0011  # one unit of the frame's 0.01 N / 0.001 N m resolution
STALL_S = 0.4  # below the driver's restart_after_s (0.5 s): the link stays up, the samples stop


class ScriptedSensor:
    """A ``ForceTorqueSensor`` whose ``read`` returns or raises the scripted items in turn, then repeats the last."""

    def __init__(self, *items) -> None:
        self.items = list(items)
        self.reads = 0

    async def connect(self) -> None:
        return None

    async def read(self) -> WrenchSample:
        item = self.items[min(self.reads, len(self.items) - 1)]
        self.reads += 1
        if isinstance(item, Exception):
            raise item
        return item

    async def close(self) -> None:
        return None


class WakingScriptedSensor(ScriptedSensor):
    """A ``ScriptedSensor`` that can wake its reader (``ft_reader.WakingSensor``): each ``wait_newer`` is recorded and
    returns at once, as a new sample's arrival would end it."""

    def __init__(self, *items) -> None:
        super().__init__(*items)
        self.waits: list[tuple[int, float]] = []

    async def wait_newer(self, after_ns: int, timeout_s: float) -> None:
        self.waits.append((after_ns, timeout_s))


def sample(stamp_ns: int, value: float = 0.0) -> WrenchSample:
    return WrenchSample(np.full(6, value), stamp_ns, None)


def run(coroutine):
    return asyncio.run(asyncio.wait_for(coroutine, TEST_TIMEOUT_S))


def assert_wrench_near(wrench: np.ndarray, expected: np.ndarray) -> None:
    np.testing.assert_allclose(wrench[:3], expected[:3], atol=FORCE_ATOL_N)
    np.testing.assert_allclose(wrench[3:], expected[3:], atol=TORQUE_ATOL_NM)


# --- plain parts ---------------------------------------------------------------------------------------------------


def test_the_bias_is_the_mean_and_the_message_subtracts_it():
    bias = bias_of([BIAS - 0.1, BIAS + 0.1, BIAS])
    np.testing.assert_allclose(bias, BIAS, atol=1e-12)
    message = wrench_message(WrenchSample(BIAS + PUSH, 5, None), bias, "left")
    np.testing.assert_allclose(message.wrench, PUSH, atol=1e-12)
    assert message.tared and message.sensor == "left" and message.hw_stamp_ns is None
    msg.encode(message, "wrench/left")
    raw = wrench_message(WrenchSample(BIAS + PUSH, 5, None), None, "left")  # no bias: the raw reading, flagged
    assert not raw.tared
    np.testing.assert_array_equal(raw.wrench, BIAS + PUSH)
    with pytest.raises(ValueError, match="at least one"):
        bias_of([])
    with pytest.raises(ValueError, match="finite"):
        bias_of([np.array([np.nan, 0, 0, 0, 0, 0])])


def test_next_sample_skips_a_sample_it_has_seen_and_raises_the_drivers_error_after_the_timeout():
    sensor = ScriptedSensor(sample(10), sample(10), Stale("old"), sample(20))
    assert run(next_sample(sensor, after_ns=10, poll_s=0.001)).stamp_ns == 20
    assert sensor.reads == 4
    with pytest.raises(NotConnected, match="unplugged"):
        run(next_sample(ScriptedSensor(NotConnected("unplugged")), after_ns=0, timeout_s=0.05, poll_s=0.01))
    tic_s = time.monotonic()
    with pytest.raises(Stale, match="no new F/T sample"):  # the same sample again and again is stale too
        run(next_sample(ScriptedSensor(sample(10)), after_ns=10, timeout_s=0.1, poll_s=0.01))
    assert time.monotonic() - tic_s >= 0.1


def test_next_sample_waits_for_a_waking_sensor_to_wake_it_and_never_polls_it():
    sensor = WakingScriptedSensor(sample(10), sample(20))
    tic_s = time.monotonic()
    got = run(next_sample(sensor, after_ns=10, timeout_s=5.0, poll_s=30.0))  # a poll would outlast the test
    assert got.stamp_ns == 20 and sensor.reads == 2
    assert time.monotonic() - tic_s < 1.0
    assert len(sensor.waits) == 1 and sensor.waits[0][0] == 10 and 4.0 < sensor.waits[0][1] <= 5.0  # the time left
    stale = WakingScriptedSensor(sample(10))  # woken without a newer sample (its timeout): Stale at the deadline
    with pytest.raises(Stale, match="no new F/T sample"):
        run(next_sample(stale, after_ns=10, timeout_s=0.05, poll_s=30.0))


def test_the_tare_averages_new_samples_over_its_duration_and_fails_on_a_silent_sensor():
    class Counting(ScriptedSensor):
        async def read(self) -> WrenchSample:
            self.reads += 1
            return sample(time.monotonic_ns(), float(self.reads % 2))  # alternating 0 and 1

    wrenches = run(samples_over(Counting(), duration_s=0.05))
    assert wrenches.shape[1] == 6 and wrenches.shape[0] >= 2
    np.testing.assert_allclose(bias_of(list(wrenches)), 0.5, atol=0.1)
    with pytest.raises(Stale):
        run(samples_over(ScriptedSensor(Stale("silent")), duration_s=0.05))


def arm_state(speed: float = 0.0) -> msg.ArmState:
    return msg.ArmState(arm="bubble", tcp_pose=np.array([0.0, 0.0, 0.1, 1.0, 0.0, 0.0, 0.0]),
                        tcp_speed=np.array([speed, 0.0, 0.0, 0.0, 0.0, 0.0]), running=True, protective_stop=False,
                        emergency_stop=False, servo_active=False)


def test_a_tare_input_is_read_only_when_asked_old_queued_ones_never_count_and_a_fresh_one_is_awaited(tmp_path):
    """The tare's subscribers are not read between tares (nothing decoded at the commander's 125 Hz): what queued
    meanwhile is drained and never taken, even when younger than the age limit (it is the oldest of what was sent:
    the publisher drops the newer ones while the queue is full), a message published after the ask is awaited up to
    the age limit, and none gives None."""
    endpoint = f"ipc://{tmp_path}/arm"
    topic = "arm_state/bubble"

    async def scenario():
        with Bus() as bus:
            arm = bus_layer.Publisher(bus, endpoint, source="arm_commander-bubble")
            states = LatestSubscriber(bus, endpoint, [topic])
            await asyncio.sleep(0.2)  # connected
            for k in range(40):
                await arm.send(arm_state(speed=1.0 + k), topic)
                await asyncio.sleep(0.002)
            await asyncio.sleep(0.3)
            unread = states.received[topic]
            none_fresh = await fresh_input(states, topic, msg.ArmState, 0.2)
            read_old = states.received[topic]

            async def publish_soon():
                await asyncio.sleep(0.05)
                await arm.send(arm_state(speed=0.0), topic)

            for _ in range(3):  # young, but sent before the ask: a moving arm that has stopped since
                await arm.send(arm_state(speed=7.0), topic)
            await asyncio.sleep(0.02)
            sender = asyncio.create_task(publish_soon())
            tic_s = time.monotonic()
            fresh = await fresh_input(states, topic, msg.ArmState, 0.2)
            waited_s = time.monotonic() - tic_s
            await sender
            return unread, none_fresh, read_old, fresh, waited_s

    unread, none_fresh, read_old, fresh, waited_s = run(scenario())
    assert unread == 0 and none_fresh is None  # nothing decoded until asked; 0.3 s old states are not fresh
    assert read_old > 0  # the old ones queued meanwhile were drained, none of them taken
    assert fresh is not None and fresh.tcp_speed[0] == 0.0 and waited_s < 0.2


def test_error_kinds_and_the_port_wait():
    assert [error_kind(e) for e in (Stale("x"), NotConnected("x"), ProtocolError("x"))] == [
        "stale", "not_connected", "protocol"]
    tic_s = time.monotonic()
    with pytest.raises(NotConnected, match="did not appear within 0.2 s"):
        run(wait_for_port("/nonexistent/ft300", timeout_s=0.2))
    assert time.monotonic() - tic_s >= 0.2


# --- the service as a process ------------------------------------------------------------------------------------


def reader_config(tmp_path):
    """A config with a private run_dir (state_dir under it) and one arm, ``bubble``: its path, the config, the port."""
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    port = run_dir / "ft300-bubble"
    config_path = tmp_path / "sim.toml"
    config_path.write_text(f'run_dir = "{run_dir}"\nmode = "sim"\n[[arms]]\nname = "bubble"\nft_port = "{port}"\n')
    return config_path, load_config(config_path), port


def test_the_service_publishes_the_simulators_wrench_minus_the_tare_and_nothing_while_it_stalls(tmp_path):
    config_path, config, port = reader_config(tmp_path)
    save_bias(bias_path(config.state_path(), "bubble"), StoredBias(
        arm="bubble", port=str(port), bias=tuple(map(float, BIAS)), taken_unix_ns=time.time_ns(), samples=50,
        source="test"))
    name = "ft_reader-bubble"
    applied = {"wrench": BIAS}
    simulator = SimulatedFT300(lambda: applied["wrench"], link=port)

    async def scenario() -> dict[str, object]:
        seen: dict[str, object] = {}
        with Bus() as bus:
            wrenches = LatestSubscriber(bus, config.endpoint(name), ["wrench/bubble"])
            status = LatestSubscriber(bus, config.endpoint(name, "status"), [f"status/{name}"])

            async def collect(duration_s: float) -> list[msg.Wrench]:
                """Every wrench message received within ``duration_s`` (the subscriber keeps only the newest
                per topic, so it is read after each arrival)."""
                received, end_s = [], time.monotonic() + duration_s
                while (left_s := end_s - time.monotonic()) > 0:
                    if await wrenches.wait(left_s):
                        received.append(wrenches.latest("wrench/bubble", 1.0, msg.Wrench).value)
                return received

            async def status_until(condition) -> msg.ServiceStatus:
                while True:
                    await status.wait(1.5)
                    try:
                        report = status.latest(f"status/{name}", 3.0, msg.ServiceStatus).value
                    except bus_layer.Stale:  # none received yet
                        continue
                    if condition(report):
                        return report

            await collect(0.5)  # let the subscription come up
            applied["wrench"] = BIAS + PUSH
            await collect(0.1)  # frames already under way carry the old wrench
            seen["pushed"] = await collect(1.0)
            simulator.set_faults(FT300Faults(bit_flip_rate=0.005, garbage_rate=0.2))
            seen["faulty"] = await collect(1.5)
            seen["crc"] = await status_until(lambda s: s.errors.get("crc", 0) > 0)
            simulator.set_faults(FT300Faults())
            stall_s = time.monotonic()
            simulator.stall(STALL_S)
            seen["during_stall"] = [(m.stamp_ns * 1e-9 - stall_s) for m in await collect(STALL_S)]
            seen["degraded"] = await status_until(lambda s: s.state == "degraded" or s.errors.get("stale", 0) > 0)
            seen["after_stall"] = await collect(0.5)
            seen["recovered"] = await status_until(lambda s: s.state == "ready")
        return seen

    process = ServiceProcess("ft_reader", name, config_path, tmp_path / "ft_reader.log")
    try:
        time.sleep(0.5)  # the service waits for the port to appear
        assert process.proc.poll() is None, process.log()
        simulator.start()
        process.wait_ready()
        seen = asyncio.run(asyncio.wait_for(scenario(), SCENARIO_TIMEOUT_S))
    finally:
        rc = process.stop()
        simulator.stop()
    assert rc == 0, process.log()
    assert len(seen["pushed"]) >= 40, len(seen["pushed"])  # the sensor's ~100 Hz, on two busy cores
    for message in seen["pushed"] + seen["faulty"] + seen["after_stall"]:
        assert message.tared and message.sensor == "bubble" and message.source == name
        assert_wrench_near(message.wrench, PUSH)  # tared, and no corrupted frame gets through
    assert len({m.seq for m in seen["pushed"]}) == len(seen["pushed"])
    assert len(seen["faulty"]) >= 40 and len(seen["after_stall"]) >= 20
    assert seen["crc"].errors["crc"] >= 1
    assert not [t for t in seen["during_stall"] if 0.15 < t < STALL_S - 0.05], seen["during_stall"]
    assert seen["degraded"].errors.get("stale", 0) >= 1


# --- tare on request ---------------------------------------------------------------------------------------------

READER = "ft_reader-bubble"
STILL = np.zeros(6)
CONTACT_PATCH_M = 0.005  # the pushing scene's press at its start


def still_membrane(pressed_m: float = 0.0) -> np.ndarray:
    """A bubble camera's deformation image ``(120, 160)`` (m): sim's 0.2 mm noise, and a patch pressed in by
    ``pressed_m``."""
    image = np.random.default_rng(7).normal(0.0, 2e-4, (120, 160)).astype(np.float32)
    image[40:70, 60:100] += pressed_m
    return image


async def play_devices(config, world: dict, stop: asyncio.Event) -> None:
    """Publish ``world["speed"]`` as ``arm_state/bubble`` on the arm commander's endpoint (25 Hz) and
    ``world["membrane"]`` as ``deformation/bubble`` on the bubble camera's (every other period) until ``stop``."""
    with Bus() as bus:
        arm = bus_layer.Publisher(bus, config.endpoint("arm_commander-bubble"), source="arm_commander-bubble")
        camera = bus_layer.Publisher(bus, config.endpoint("bubble_camera-bubble"), source="bubble_camera-bubble")
        tick = 0
        while not stop.is_set():
            await arm.send(msg.ArmState(arm="bubble", tcp_pose=np.array([0.0, 0.0, 0.1, 1.0, 0.0, 0.0, 0.0]),
                                        tcp_speed=world["speed"], running=True, protective_stop=False,
                                        emergency_stop=False, servo_active=False), "arm_state/bubble")
            if tick % 2 == 0:
                await camera.send(msg.MembraneDeformation(bubble="bubble", deformation=world["membrane"],
                                                          reference_stamp_ns=1), "deformation/bubble")
            tick += 1
            await asyncio.sleep(0.04)


async def reader_output(config, window_s: float) -> tuple[list[msg.Wrench], msg.ServiceStatus]:
    """The reader's wrenches over ``window_s`` (after the first) and then its next status."""
    with Bus() as bus:
        wrenches = LatestSubscriber(bus, config.endpoint(READER), ["wrench/bubble"])
        status = LatestSubscriber(bus, config.endpoint(READER, "status"), [f"status/{READER}"])
        received, end_s = [], None
        while end_s is None or time.monotonic() < end_s:
            if await wrenches.wait(1.0):
                received.append(wrenches.latest("wrench/bubble", 1.0, msg.Wrench).value)
                end_s = end_s or time.monotonic() + window_s
        while True:
            await status.wait(1.5)
            try:
                return received, status.latest(f"status/{READER}", 3.0, msg.ServiceStatus).value
            except bus_layer.Stale:
                continue


def test_the_reader_tares_only_on_request_at_rest_out_of_contact_and_a_killed_reader_keeps_the_tare(tmp_path):
    config_path, config, port = reader_config(tmp_path)
    stored = bias_path(config.state_path(), "bubble")
    stored.parent.mkdir(parents=True)
    stored.write_text('{"arm": "bubble", "bias": [0.0, ')  # a tare cut off mid-write
    load = {"wrench": STILL}
    simulator = SimulatedFT300(lambda: load["wrench"], link=port, bias=BIAS)
    world = {"speed": np.array([0.0, 0.01, 0.0, 0.0, 0.0, 0.0]), "membrane": still_membrane()}

    async def requests() -> dict[str, object]:
        seen: dict[str, object] = {}
        stop = asyncio.Event()
        devices = asyncio.create_task(play_devices(config, world, stop))
        try:
            seen["untared"] = await reader_output(config, 0.5)
            seen["moving"] = await request_tare(config, "bubble")
            world["speed"] = np.zeros(6)
            world["membrane"] = still_membrane(CONTACT_PATCH_M)
            await asyncio.sleep(0.3)
            seen["contact"] = await request_tare(config, "bubble")
            world["membrane"] = still_membrane()
            await asyncio.sleep(0.3)
            seen["clear"] = await request_tare(config, "bubble")
            seen["tared"] = await reader_output(config, 0.5)
        finally:
            stop.set()
            await devices
        return seen

    first = ServiceProcess("ft_reader", READER, config_path, tmp_path / "ft_reader.log")
    second = None
    try:
        simulator.start()
        first.wait_ready()
        seen = asyncio.run(asyncio.wait_for(requests(), SCENARIO_TIMEOUT_S))
        first.kill()  # a crash; meanwhile the bubble starts pressing
        load["wrench"] = PUSH
        second = ServiceProcess("ft_reader", READER, config_path, tmp_path / "ft_reader_2.log")
        second.wait_ready()
        after_kill = asyncio.run(asyncio.wait_for(reader_output(config, 0.5), SCENARIO_TIMEOUT_S))
    finally:
        first.stop()
        rc = second.stop() if second is not None else None
        simulator.stop()
    assert rc == 0, second.log() if second is not None else first.log()

    untared, status = seen["untared"]
    assert untared and not any(m.tared for m in untared)  # a corrupt file is no zero bias: raw, flagged
    for message in untared:
        assert_wrench_near(message.wrench, BIAS)
    assert status.state == "degraded" and status.errors.get("bias_file", 0) == 1, status
    assert status.note.startswith("NOT TARED: stored bias unusable") and str(stored) in status.note, status.note

    assert not seen["moving"].ok and "is moving (10.0 mm/s" in seen["moving"].error, seen["moving"]
    assert not seen["contact"].ok and "in contact" in seen["contact"].error, seen["contact"]
    assert seen["moving"].bias is None and seen["contact"].bias is None
    clear = seen["clear"]
    assert clear.ok and clear.error == "", clear
    assert_wrench_near(clear.bias, BIAS)
    kept = load_bias(stored, "bubble", str(port))  # stored before it was used
    np.testing.assert_array_equal(kept.vector, clear.bias)
    assert kept.taken_unix_ns == clear.taken_unix_ns and kept.samples >= 20 and kept.source == "ft tare"
    tared, status = seen["tared"]
    assert tared and all(m.tared for m in tared)
    for message in tared:
        assert_wrench_near(message.wrench, STILL)
    assert status.state == "ready" and status.note.startswith("tared: bias [1.500 -2.000 3.250"), status

    loaded, status = after_kill
    assert loaded and all(m.tared for m in loaded)
    for message in loaded:  # the stored tare, not a new one under load: the load still reads
        assert_wrench_near(message.wrench, PUSH)
    assert status.state == "ready" and "by ft tare" in status.note and status.errors == {}, status


def test_bad_input_and_an_unplugged_sensor_are_counted_and_never_end_the_reader(tmp_path):
    """Every malformation (``fuzz.py``) of the reader's inputs (``arm_state``, ``deformation``) and of its tare
    request, a request of another kind, and a sensor unplugged and plugged in again: each counted, every request
    answered, the reader up throughout and reading again afterwards."""
    import zmq
    from fuzz import Malformed, frames_of, malformed

    config_path, config, port = reader_config(tmp_path)
    simulator = SimulatedFT300(lambda: STILL, link=port, bias=BIAS)
    state = msg.ArmState(arm="bubble", tcp_pose=np.array([0.0, 0.0, 0.1, 1.0, 0.0, 0.0, 0.0]), tcp_speed=STILL,
                         running=True, protective_stop=False, emergency_stop=False, servo_active=False)
    membrane = msg.MembraneDeformation(bubble="bubble", deformation=still_membrane(), reference_stamp_ns=1)

    async def scenario() -> dict[str, object]:
        seen: dict[str, object] = {"replies": []}
        with Bus() as bus:
            arm = bus.socket(zmq.PUB, config.endpoint("arm_commander-bubble"), bind=True)
            camera = bus.socket(zmq.PUB, config.endpoint("bubble_camera-bubble"), bind=True)
            requests = bus.socket(zmq.DEALER, config.endpoint(READER, "cmd"), bind=False)
            await asyncio.sleep(0.5)  # the reader's subscriptions come up
            await arm.send_multipart(frames_of(state, "arm_state/bubble"))  # a newer message than stale_stamp's
            await camera.send_multipart(frames_of(membrane, "deformation/bubble"))
            broken = malformed(state, "arm_state/bubble") + malformed(membrane, "deformation/bubble")
            for item in broken:
                await (arm if item.frames[0].startswith(b"arm") else camera).send_multipart(item.frames)
                await asyncio.sleep(0.01)
            requests_sent = malformed(msg.Tare(), "cmd/tare") + [
                Malformed("another kind", "handler", msg.encode(msg.GetStatus()))]
            for number, item in enumerate(requests_sent, start=1):
                await requests.send_multipart([number.to_bytes(8, "big"), *item.frames])
                frames = await asyncio.wait_for(requests.recv_multipart(), 5.0)
                seen["replies"].append((item.name, msg.decode(frames[1:])[1]))
            seen["kinds"] = {item.kind for item in broken + requests_sent} - {"handler"}
            seen["refused"] = await request_tare(config, "bubble")  # still answered: no fresh input to judge by
        simulator.disconnect()
        seen["unplugged"] = await degraded_status(config)
        simulator.reconnect()
        seen["plugged"] = await reader_output(config, 0.5)
        return seen

    process = ServiceProcess("ft_reader", READER, config_path, tmp_path / "ft_reader.log")
    try:
        simulator.start()
        process.wait_ready()
        seen = asyncio.run(asyncio.wait_for(scenario(), SCENARIO_TIMEOUT_S))
        alive = process.proc.poll() is None
    finally:
        rc = process.stop()
        simulator.stop()
    assert alive and rc == 0, process.log()
    assert all(not reply.ok and reply.error for _, reply in seen["replies"]), seen["replies"]
    assert "answers only Tare" in seen["replies"][-1][1].error
    assert not seen["refused"].ok and "no fresh arm state" in seen["refused"].error
    status = seen["unplugged"]
    assert status.state == "degraded" and status.errors.get("not_connected", 0) + status.errors.get("stale", 0) > 0
    wrenches, status = seen["plugged"]
    assert len(wrenches) >= 20 and not any(m.tared for m in wrenches)  # no stored bias here: raw, flagged
    missing = {kind for kind in seen["kinds"] if status.errors.get(kind, 0) == 0}
    assert not missing, (missing, status.errors)


async def degraded_status(config, window_s: float = 1.0) -> msg.ServiceStatus:
    """The reader's first ``degraded`` status after ``window_s`` (an unplugged sensor: no wrench meanwhile)."""
    with Bus() as bus:
        status = LatestSubscriber(bus, config.endpoint(READER, "status"), [f"status/{READER}"])
        end_s = time.monotonic() + window_s
        while True:
            await status.wait(1.5)
            try:
                report = status.latest(f"status/{READER}", 3.0, msg.ServiceStatus).value
            except bus_layer.Stale:
                continue
            if time.monotonic() > end_s and report.state == "degraded":
                return report
