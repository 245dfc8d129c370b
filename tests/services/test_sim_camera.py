"""sim_camera: its truth reader over a real bus (each truth once, the newest, then stale), then the service as
a real process fed by a test publisher of object pose truths on sim_world's endpoint: not ready before it has
rendered, each image the simulated tag camera's render of the truth it was sent, bit for bit, in order, stamped
with the truth's stamp; a message that is not a truth counted and not rendered; silent truth reported as degraded
with its reason, and ready again once truths come back.

The process gets a private run_dir and is stopped by its pid; every wait has a timeout.
"""

from __future__ import annotations

import asyncio
import time

import msgspec
import numpy as np
import pytest
import zmq
from service_process import ServiceProcess

from hydrosoft.drivers.errors import Stale
from hydrosoft.services.bus import messages as msg
from hydrosoft.services.bus import sockets as bus_layer
from hydrosoft.services.bus.config import load_config
from hydrosoft.services.bus.sockets import Bus, LatestSubscriber, Publisher
from hydrosoft.services.sim.tag_camera import tag_camera
from hydrosoft.services.sim_camera import TruthFeed

SCENARIO_TIMEOUT_S = 60.0
NOT_READY_S = 1.5  # the service must not report ready this long while no truth comes
IMAGE_WAIT_S = 3.0  # a truth's image comes within this (a render is about 3 ms), or the truth was lost
SILENCE_S = 0.6  # longer than the service's stale limit, 5 frame periods of 20 Hz
CUBE_POSE = np.array([0.0, 0.0, 0.024215, 1.0, 0.0, 0.0, 0.0])  # pushing.toml's cube, base frame
#: Poses the truths carry, in order: the cube slid and turned a little each time.
POSES = [CUBE_POSE + np.array([0.004 * i, -0.003 * i, 0.0, 0.0, 0.0, 0.0, 0.0]) for i in range(4)]
for _pose in POSES[2:]:
    _pose[3:] = [np.cos(0.1), 0.0, 0.0, np.sin(0.1)]


def truth(pose: np.ndarray) -> msg.EvalObjectPose:
    return msg.EvalObjectPose(object="object", pose=pose)


def test_the_truth_feed_hands_out_the_newest_truth_once_then_goes_stale(tmp_path):
    endpoint = f"ipc://{tmp_path}/sim_world.data"

    async def scenario() -> None:
        with Bus() as bus:
            out = Publisher(bus, endpoint, source="sim_world")
            feed = TruthFeed(LatestSubscriber(bus, endpoint, [TruthFeed.topic]), timeout_s=0.3)
            while True:  # until the subscription is up
                await out.send(truth(POSES[0]))
                try:
                    await feed.read()
                    break
                except Stale:
                    pass
            with pytest.raises(Stale):
                while True:  # the warm-up truths still queued, then nothing new
                    await feed.read()
            await out.send(truth(POSES[1]))
            newest = await out.send(truth(POSES[2]))
            await asyncio.sleep(0.05)
            received = await feed.read()  # the newest only: POSES[1] is dropped
            assert received.stamp_ns == newest.stamp_ns
            np.testing.assert_array_equal(received.pose, POSES[2])
            tic_s = time.monotonic()
            with pytest.raises(Stale, match="no object pose truth from sim_world"):
                await feed.read()  # never handed out twice
            assert time.monotonic() - tic_s >= 0.29

    asyncio.run(asyncio.wait_for(scenario(), 20.0))
    with pytest.raises(ValueError, match="timeout_s"):
        TruthFeed(None, 0.0)


# --- the service as a process ------------------------------------------------------------------------------------


def test_the_service_renders_each_truth_bit_for_bit_and_reports_silent_truth(tmp_path):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    config_path = tmp_path / "sim.toml"
    config_path.write_text(f'run_dir = "{run_dir}"\nmode = "sim"\n[scene]\ntask = "pushing"\n[camera]\nfps = 20.0\n'
                           '[[arms]]\nname = "bubble"\n')
    config = load_config(config_path)
    reference = tag_camera(config, lambda: CUBE_POSE)  # the camera sim_world rendered in its own process before
    expected = [reference.render(pose) for pose in POSES]
    name = "sim_camera"

    async def scenario(process: ServiceProcess) -> dict[str, object]:
        seen: dict[str, object] = {"images": []}
        with Bus() as bus:
            out = bus.socket(zmq.PUB, config.endpoint("sim_world"), bind=True)
            seq = iter(range(1, 1000))
            images = LatestSubscriber(bus, config.endpoint(name), ["image/tag_camera"])
            status = LatestSubscriber(bus, config.endpoint(name, "status"), [f"status/{name}"])
            loop = asyncio.get_running_loop()
            with pytest.raises(AssertionError, match="not READY"):
                await loop.run_in_executor(None, process.wait_ready, NOT_READY_S)  # no truth yet: not ready

            async def show(pose: np.ndarray) -> msg.CameraImage:
                """Publish ``pose`` until its image comes back (matched by its exposure stamp); sent again only when
                no image came for ``IMAGE_WAIT_S`` (lost before the subscription was up), so each is rendered once."""
                while True:
                    sent = msgspec.structs.replace(truth(pose), seq=next(seq), stamp_ns=time.monotonic_ns(),
                                                   source="sim_world")
                    await out.send_multipart(msg.encode(sent, TruthFeed.topic))
                    deadline_s = loop.time() + IMAGE_WAIT_S
                    while loop.time() < deadline_s:
                        if "image/tag_camera" in await images.wait(deadline_s - loop.time()):
                            image = images.latest("image/tag_camera", 5.0, msg.CameraImage).value
                            if image.hw_stamp_ns == sent.stamp_ns:
                                return image

            async def status_until(condition) -> msg.ServiceStatus:
                while True:
                    await status.wait(1.5)
                    try:
                        report = status.latest(f"status/{name}", 3.0, msg.ServiceStatus).value
                    except bus_layer.Stale:  # none received yet
                        continue
                    if condition(report):
                        return report

            # the first truth the service gets is POSES[0]: its warm-up is its first image
            seen["images"].append(await show(POSES[0]))
            await loop.run_in_executor(None, process.wait_ready, 10.0)
            seen["images"].append(await show(POSES[1]))
            await out.send_multipart([TruthFeed.topic.encode(), b"\xc1 not msgpack"])  # counted, not rendered
            await asyncio.sleep(0.2)
            seen["images"].append(await show(POSES[2]))
            await asyncio.sleep(SILENCE_S)  # sim_world falls silent
            seen["silent"] = await status_until(lambda s: s.state == "degraded")
            seen["images"].append(await show(POSES[3]))
            seen["recovered"] = await status_until(lambda s: s.state == "ready")
        return seen

    process = ServiceProcess("sim_camera", name, config_path, tmp_path / "sim_camera.log")
    try:
        seen = asyncio.run(asyncio.wait_for(scenario(process), SCENARIO_TIMEOUT_S))
    finally:
        rc = process.stop()
    assert rc == 0, process.log()
    for image, want in zip(seen["images"], expected, strict=True):
        assert image.source == name and image.camera == "tag_camera"
        np.testing.assert_array_equal(image.frame, want)
    silent = seen["silent"]
    assert silent.errors["stale_truth"] >= 1 and "no object pose truth from sim_world" in silent.note, silent
    assert seen["recovered"].note == "" and seen["recovered"].errors["garbage"] == 1, seen["recovered"]
