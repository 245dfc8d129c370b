"""The F/T tare on the simulated devices, as processes: sim_world (the pushing scene, which starts with the bubble
pressing about 1.9 N into the cube), the arm commander (the real ur_rtde client, holding the arm), the bubble camera
and the F/T reader (the real serial driver on the simulated FT 300, which adds ``sim.ft_bias`` to every frame).

Ground truth is sim_world's ``eval/contact_forces``: the net force the bubble applies to the cube. The reader's
force reads it from the start (sim_world stored the sensor's zero-load offset as the tare), ``ft tare`` is refused
while the bubble presses, and a reader SIGKILLed and started again while the bubble presses still reads the load.
With the cube moved away from under the bubble (``sim.object_offset_m``) and no stored tare, the reader starts
untared, ``ft tare`` is accepted on the rendered membrane, stored, and a restarted reader loads it.

Every process is stopped by its pid; each wait has a timeout.
"""

from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest
from service_process import ServiceProcess
from stack_process import READY_TIMEOUT_S, stack_config

from hydrosoft.services.commands import cli
from hydrosoft.services.bus import messages as msg
from hydrosoft.services.bus.sockets import Bus, LatestSubscriber, Stale
from hydrosoft.services.bus.config import load_config
from hydrosoft.services.arm.ft_bias import bias_path, load_bias

pytestmark = pytest.mark.slow

READER = "ft_reader-bubble"
#: The reader's force may differ from the truth by this much, N: the frames' 0.01 N per axis (the simulated sensor's
#: noise is turned off here, ``noise_free``) and the plant's settling between the two samples compared.
FORCE_ATOL_N = 0.05
WINDOW_S = 1.0
TIMEOUT_S = 30.0


async def force_and_truth(config, window_s: float = WINDOW_S) -> dict[str, object]:
    """Over ``window_s``: the reader's wrenches, the newest true net force of the bubble on the cube (N, base
    frame) and the reader's newest status."""
    with Bus() as bus:
        wrenches = LatestSubscriber(bus, config.endpoint(READER), ["wrench/bubble"])
        truth = LatestSubscriber(bus, config.endpoint("sim_world"), ["eval/contact_forces"])
        status = LatestSubscriber(bus, config.endpoint(READER, "status"), [f"status/{READER}"])
        seen: dict[str, object] = {"wrenches": [], "truth": None, "status": None}
        end_s = None
        while end_s is None or time.monotonic() < end_s or seen["truth"] is None or seen["status"] is None:
            if await wrenches.wait(0.2):
                seen["wrenches"].append(wrenches.latest("wrench/bubble", 1.0, msg.Wrench).value)
                end_s = end_s or time.monotonic() + window_s
            for subscriber, topic, kind, key in ((truth, "eval/contact_forces", msg.EvalContactForces, "truth"),
                                                 (status, f"status/{READER}", msg.ServiceStatus, "status")):
                try:
                    value = subscriber.latest(topic, 2.0, kind).value
                except Stale:
                    continue
                seen[key] = value
    forces = seen["truth"]
    seen["truth"] = forces.forces[forces.bodies.index("bubble")].sum(axis=0)
    return seen


def measure(config) -> dict[str, object]:
    return asyncio.run(asyncio.wait_for(force_and_truth(config), TIMEOUT_S))


def assert_reads_the_load(seen: dict[str, object]) -> None:
    true_n = float(np.linalg.norm(seen["truth"]))
    assert true_n > 1.0, seen["truth"]  # the bubble presses on the cube
    assert len(seen["wrenches"]) >= 20, len(seen["wrenches"])
    for message in seen["wrenches"]:
        assert message.tared
        assert abs(float(np.linalg.norm(message.wrench[:3])) - true_n) < FORCE_ATOL_N, (message.wrench, true_n)


def noise_free(config_path):
    """``config_path`` with the simulated FT 300's signal noise off (``sim.ft_noise = 0``): this module checks the
    reader's tare arithmetic frame by frame, to the sensor's resolution (the tare's steadiness rule under the
    datasheet's noise is ``tests/services/arm/test_tare_rules.py``'s)."""
    text = config_path.read_text()
    assert "ft_noise = 1.0" in text
    config_path.write_text(text.replace("ft_noise = 1.0", "ft_noise = 0.0", 1))
    return config_path


class Services:
    """The services this module starts, each stopped by its pid (``stop_all``)."""

    def __init__(self, config_path, tmp_path) -> None:
        self.config_path, self.tmp_path = config_path, tmp_path
        self.processes: list[ServiceProcess] = []

    def start(self, module: str, name: str) -> ServiceProcess:
        process = ServiceProcess(module, name, self.config_path, self.tmp_path / f"{name}.{len(self.processes)}.log")
        self.processes.append(process)
        process.wait_ready(READY_TIMEOUT_S)
        return process

    def stop_all(self) -> dict[str, int]:
        return {f"{p.name}.{i}": p.stop() for i, p in reversed(list(enumerate(self.processes)))}

    def logs(self) -> str:
        return "\n".join(process.log() for process in self.processes)


def test_the_reader_reads_the_true_load_from_the_start_refuses_a_tare_in_contact_and_after_a_kill(tmp_path, capsys):
    config_path = noise_free(stack_config(tmp_path))
    config = load_config(config_path)
    (tmp_path / "run").mkdir()  # the launcher's job, here done by the test
    assert any(config.sim.ft_bias), "deploy/sim.toml's simulated sensor has an offset to tare away"
    services = Services(config_path, tmp_path)
    try:
        services.start("sim_world", "sim_world")
        services.start("arm_commander", "arm_commander-bubble")
        reader = services.start("ft_reader", READER)
        services.start("bubble_camera", "bubble_camera-bubble")
        at_start = measure(config)

        time.sleep(1.0)  # the reader's subscribers have the arm's state and the membrane
        refused = cli.main(["ft", "tare", "bubble", "--config", str(config_path)])
        refusal = capsys.readouterr().err

        reader.kill()  # as a crash would, while the bubble presses
        services.start("ft_reader", READER)
        after_kill = measure(config)
    finally:
        codes = services.stop_all()
    assert all(code in (0, -9) for code in codes.values()), (codes, services.logs())

    assert_reads_the_load(at_start)
    assert at_start["status"].note.startswith("tared: bias [1.200 -0.800 2.500 0.040 -0.030 0.020]")
    assert "by sim_world" in at_start["status"].note
    assert refused == 1 and "tare refused: the bubble is in contact" in refusal, refusal
    assert_reads_the_load(after_kill)
    assert after_kill["status"].state == "ready" and after_kill["status"].note.startswith("tared: bias [1.200")


def test_out_of_contact_at_rest_a_tare_is_accepted_stored_and_reloaded_by_a_restarted_reader(tmp_path, capsys):
    config_path = noise_free(stack_config(tmp_path, object_offset_m=(0.2, 0.0)))  # the cube far from the bubble
    config = load_config(config_path)
    (tmp_path / "run").mkdir()
    stored = bias_path(config.state_path(), "bubble")
    services = Services(config_path, tmp_path)
    try:
        services.start("sim_world", "sim_world")
        stored.unlink()  # no tare stored yet: sim_world's is removed
        services.start("arm_commander", "arm_commander-bubble")
        reader = services.start("ft_reader", READER)
        services.start("bubble_camera", "bubble_camera-bubble")
        untared = measure(config)

        time.sleep(1.0)  # the reader's subscribers have the arm's state and the membrane
        accepted = cli.main(["ft", "tare", "bubble", "--config", str(config_path)])
        printed = capsys.readouterr()
        tared = measure(config)

        reader.kill()
        services.start("ft_reader", READER)
        reloaded = measure(config)
    finally:
        codes = services.stop_all()
    assert all(code in (0, -9) for code in codes.values()), (codes, services.logs())

    assert float(np.linalg.norm(untared["truth"])) == 0.0  # nothing touches the bubble
    assert untared["wrenches"] and not any(m.tared for m in untared["wrenches"])
    for message in untared["wrenches"]:  # the raw reading: the sensor's offset
        np.testing.assert_allclose(message.wrench, config.sim.ft_bias, atol=0.011)
    assert untared["status"].state == "degraded" and untared["status"].note.startswith("NOT TARED: no stored bias")

    assert accepted == 0, printed
    assert printed.out.startswith("tared bubble: bias [1.200 -0.800 2.500 0.040 -0.030 0.020] N, N m"), printed
    kept = load_bias(stored, "bubble", config.arm("bubble").ft_port)
    np.testing.assert_allclose(kept.vector, config.sim.ft_bias, atol=0.006)
    assert kept.source == "ft tare" and kept.samples >= 20
    for seen in (tared, reloaded):
        assert seen["wrenches"] and all(m.tared for m in seen["wrenches"])
        for message in seen["wrenches"]:
            np.testing.assert_allclose(message.wrench, np.zeros(6), atol=0.011)
        assert seen["status"].state == "ready" and "by ft tare" in seen["status"].note, seen["status"]
