"""The F/T tare on the simulated devices, as processes: sim_world (the pushing scene, which starts with the bubble
pressing about 1.9 N into the cube), the arm commander (the real ur_rtde client, holding the arm), the bubble camera
and the F/T reader (the real serial driver on the simulated FT 300, which adds ``sim.ft_bias`` to every frame).

Ground truth is sim_world's ``eval/contact_forces``: the net force the bubble applies to the cube. The reader's
force reads it from the start (sim_world stored the sensor's zero-load offset as the tare), ``ft tare`` is refused
while the bubble presses, and a reader SIGKILLed and started again while the bubble presses still reads the load.

Every process is stopped by its pid; each wait has a timeout.
"""

from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest
from service_process import ServiceProcess
from stack_process import READY_TIMEOUT_S, stack_config

from hydrosoft.services import cli
from hydrosoft.services import messages as msg
from hydrosoft.services.bus import Bus, LatestSubscriber, Stale
from hydrosoft.services.config import load_config

pytestmark = pytest.mark.slow

READER = "ft_reader-bubble"
#: The reader's force may differ from the truth by this much, N: the frames' 0.01 N per axis (the simulated sensor
#: has no other noise) and the plant's settling between the two samples compared.
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


def test_the_reader_reads_the_true_load_from_the_start_refuses_a_tare_in_contact_and_after_a_kill(tmp_path, capsys):
    config_path = stack_config(tmp_path)
    config = load_config(config_path)
    (tmp_path / "run").mkdir()  # the launcher's job, here done by the test
    assert any(config.sim.ft_bias), "deploy/sim.toml's simulated sensor has an offset to tare away"
    processes: list[ServiceProcess] = []

    def start(module: str, name: str, log: str) -> ServiceProcess:
        process = ServiceProcess(module, name, config_path, tmp_path / log)
        processes.append(process)
        process.wait_ready(READY_TIMEOUT_S)
        return process

    try:
        start("sim_world", "sim_world", "sim_world.log")
        start("arm_commander", "arm_commander-bubble", "arm_commander.log")
        reader = start("ft_reader", READER, "ft_reader.log")
        start("bubble_camera", "bubble_camera-bubble", "bubble_camera.log")
        at_start = measure(config)

        time.sleep(1.0)  # the reader's subscribers have the arm's state and the membrane
        refused = cli.main(["ft", "tare", "bubble", "--config", str(config_path)])
        refusal = capsys.readouterr().err

        reader.kill()  # as a crash would, while the bubble presses
        start("ft_reader", READER, "ft_reader_restarted.log")
        after_kill = measure(config)
    finally:
        codes = {process.name: process.stop() for process in reversed(processes)}
    logs = "\n".join(process.log() for process in processes)
    assert all(code in (0, -9) for code in codes.values()), (codes, logs)

    assert_reads_the_load(at_start)
    assert at_start["status"].note.startswith("tared: bias [1.200 -0.800 2.500 0.040 -0.030 0.020]")
    assert "by sim_world" in at_start["status"].note
    assert refused == 1 and "tare refused: the bubble is in contact" in refusal, refusal
    assert_reads_the_load(after_kill)
    assert after_kill["status"].state == "ready" and after_kill["status"].note.startswith("tared: bias [1.200")
