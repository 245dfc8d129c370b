"""The bubble camera service: its frame pipeline (no sockets), the bus-fed depth camera, and the service as a real
process fed by a test publisher of rendered ``DepthFrame``s on sim_world's endpoint: zero deformation with no
object, positive where a rendered cube pushes in, garbage and wrong frames counted, a silent camera reported. In
lab mode, the service reads a recorded 16-bit FFV1 stream through ``OpenCVDepthCamera`` and a captured reference
file, and publishes exactly ``membrane_deformation(depth, reference)``.

The process gets a private run_dir and is stopped by its pid; every wait has a timeout.
"""

from __future__ import annotations

import asyncio
import time

import cv2
import msgspec
import numpy as np
import pytest
from service_process import ServiceProcess
import zmq

from hydrosoft.drivers.base import DepthFrame
from hydrosoft.drivers.bubble.deformation import membrane_deformation
from hydrosoft.drivers.bubble.reference import Reference, save_reference
from hydrosoft.drivers.bubble.render import render_depth, to_counts
from hydrosoft.drivers.errors import NotConnected, ProtocolError, Stale
from hydrosoft.geometry.sdf import Box
from hydrosoft.services.bus import messages as msg
from hydrosoft.services.bubble_camera import (
    BadFrame,
    BubbleDepth,
    error_kind,
    membrane_radii,
)
from hydrosoft.services.bus import sockets as bus_layer
from hydrosoft.services.bus.sockets import Bus, LatestSubscriber, Publisher
from hydrosoft.services.bus.config import ConfigError, load_config, parse_config
from hydrosoft.services.sim.devices import BusDepthCamera, depth_topic

SCENARIO_TIMEOUT_S = 40.0
FRAME_PERIOD_S = 0.05  # the test camera's 20 Hz
SILENCE_S = 0.6  # longer than the service's stale limit, 5 frame periods
DEPTH_TABLE = "depth = { width = 160, height = 120, fx = 40.0, fy = 40.0, cx = 79.5, cy = 59.5, fps = 20.0 }\n"
PRESSED = (0.0, 0.0, -0.05, 1.0, 0.0, 0.0, 0.0)  # pushing.toml's cube in the bubble frame: 5 mm into the membrane
HALF_COUNT_M = 0.5e-4 + 1e-7  # the uint16 rounding of a 0.1 mm depth unit, and float32's


def config_text(run_dir: str = "/tmp/hydrosoft-test-unused") -> str:
    return f'run_dir = "{run_dir}"\nmode = "sim"\n[scene]\ntask = "pushing"\n[[arms]]\nname = "bubble"\n{DEPTH_TABLE}'


def frame_counts(bubble: BubbleDepth, pose=None) -> np.ndarray:
    """The uint16 image sim_world renders: the nominal membrane, or the pushing cube at ``pose``."""
    if pose is None:
        return to_counts(bubble.reference_m, bubble.depth_scale_m)
    depth = render_depth(bubble.camera, membrane_radii(parse_config(config_text()), "bubble"),
                         (0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0), Box((0.025, 0.025, 0.025)), pose)
    return to_counts(depth, bubble.depth_scale_m)


# --- the frame pipeline, without sockets ---------------------------------------------------------------------------


def test_the_nominal_membrane_gives_zero_deformation_and_a_pressed_cube_a_positive_patch():
    bubble = BubbleDepth.nominal(parse_config(config_text()), "bubble")
    depth, deformation = bubble.messages(DepthFrame(frame_counts(bubble), 1e-4, 10, 7))
    assert np.abs(deformation.deformation).max() <= HALF_COUNT_M
    assert (depth.depth == frame_counts(bubble)).all() and (depth.fx_px, depth.cy_px) == (40.0, 59.5)
    assert depth.hw_stamp_ns == deformation.hw_stamp_ns == 7 and deformation.bubble == "bubble"
    _, pressed = bubble.messages(DepthFrame(frame_counts(bubble, PRESSED), 1e-4, 11, 8))
    assert pressed.deformation.max() == pytest.approx(0.005, abs=2e-4)
    assert (pressed.deformation > 1e-3).sum() > 2000 and pressed.deformation.min() >= -HALF_COUNT_M
    msg.encode(depth, "depth/bubble")  # both pass the bus's checks
    msg.encode(pressed, "deformation/bubble")


def test_a_pixel_without_return_is_nan_in_the_deformation():
    bubble = BubbleDepth.nominal(parse_config(config_text()), "bubble")
    counts = frame_counts(bubble)
    counts[5, 7] = 0
    _, deformation = bubble.messages(DepthFrame(counts, 1e-4, 10, None))
    assert np.isnan(deformation.deformation[5, 7]) and np.isnan(deformation.deformation).sum() == 1


@pytest.mark.parametrize("counts, scale_m, text", [
    (np.zeros((120, 161), np.uint16), 1e-4, "must be"),
    (np.zeros((120, 160), np.int32), 1e-4, "uint16"),
    (np.zeros((120, 160), np.uint16), 1e-3, "units"),
])
def test_frames_that_do_not_fit_the_camera_are_bad_frames(counts, scale_m, text):
    bubble = BubbleDepth.nominal(parse_config(config_text()), "bubble")
    with pytest.raises(BadFrame, match=text) as info:
        bubble.messages(DepthFrame(counts, scale_m, 10, None))
    assert error_kind(info.value) == "bad_frame"


def test_error_kinds_and_an_arm_that_is_no_bubble():
    assert [error_kind(e) for e in (Stale("x"), NotConnected("x"), ProtocolError("x"))] == [
        "stale", "not_connected", "protocol"]
    with pytest.raises(ConfigError, match="ellipsoid"):
        membrane_radii(parse_config('[[arms]]\nname = "table"\n'), "table")


# --- the bus-fed depth camera --------------------------------------------------------------------------------------


def test_bus_depth_camera_hands_out_each_new_frame_once_then_goes_stale(tmp_path):
    endpoint = f"ipc://{tmp_path}/sim_world.data"
    image = np.arange(12, dtype=np.uint16).reshape(3, 4)

    def frame(bubble: str, hw_stamp_ns: int) -> msg.DepthFrame:
        return msg.DepthFrame(bubble=bubble, depth=image, depth_scale_m=1e-4, fx_px=1.0, fy_px=1.0, cx_px=1.5,
                              cy_px=1.0, hw_stamp_ns=hw_stamp_ns)

    async def scenario() -> None:
        with Bus() as bus:
            out = Publisher(bus, endpoint, source="test")
            camera = BusDepthCamera(LatestSubscriber(bus, endpoint, [depth_topic("left")]), "left", timeout_s=0.3)
            with pytest.raises(NotConnected):
                await camera.read()
            await camera.connect()
            while True:  # until the subscription is up
                await out.send(frame("left", 1), depth_topic("left"))
                try:
                    await camera.read()
                    break
                except Stale:
                    pass
            with pytest.raises(Stale):
                while True:  # the warm-up frames still queued, then nothing new
                    await camera.read()
            await out.send(frame("left", 20), depth_topic("left"))
            received = await camera.read()
            assert received.hw_stamp_ns == 20 and received.depth_scale_m == 1e-4
            np.testing.assert_array_equal(received.depth, image)
            tic_s = time.monotonic()
            with pytest.raises(Stale, match="no new depth frame"):
                await camera.read()  # never handed out twice
            assert time.monotonic() - tic_s >= 0.29
            await out.send(frame("right", 30), depth_topic("left"))
            with pytest.raises(ProtocolError, match="'right'"):
                await camera.read()
            await camera.close()
            with pytest.raises(NotConnected):
                await camera.read()

    asyncio.run(asyncio.wait_for(scenario(), 20.0))


# --- the service as a process ------------------------------------------------------------------------------------


def stamped(message: msg.Message, seq: int) -> list:
    """The wire frames of ``message`` as sim_world's publisher would send them."""
    message = msgspec.structs.replace(message, seq=seq, stamp_ns=time.monotonic_ns(), source="sim_world")
    return msg.encode(message, depth_topic("bubble"))


def test_the_service_publishes_deformation_counts_bad_input_and_reports_a_silent_camera(tmp_path):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    config_path = tmp_path / "sim.toml"
    config_path.write_text(config_text(str(run_dir)))
    config = load_config(config_path)
    bubble = BubbleDepth.nominal(config, "bubble")
    images = {"nominal": frame_counts(bubble), "pressed": frame_counts(bubble, PRESSED)}
    name = "bubble_camera-bubble"

    async def scenario() -> dict[str, object]:
        seen: dict[str, object] = {}
        with Bus() as bus:
            camera = bus.socket(zmq.PUB, config.endpoint("sim_world"), bind=True)
            output = LatestSubscriber(bus, config.endpoint(name), ["deformation/bubble", "depth/bubble"])
            status = LatestSubscriber(bus, config.endpoint(name, "status"), [f"status/{name}"])
            sent = {"seq": 0}

            async def send(frames: list) -> None:
                await camera.send_multipart(frames)
                await asyncio.sleep(FRAME_PERIOD_S)

            async def show(image: str) -> msg.MembraneDeformation:
                """Publish ``image`` until its deformation comes back (matched by its hardware stamp)."""
                while True:
                    sent["seq"] += 1
                    stamp_ns = time.monotonic_ns()
                    await send(stamped(msg.DepthFrame(bubble="bubble", depth=images[image], depth_scale_m=1e-4,
                                                      fx_px=40.0, fy_px=40.0, cx_px=79.5, cy_px=59.5,
                                                      hw_stamp_ns=stamp_ns), sent["seq"]))
                    if "deformation/bubble" in output.drain():
                        received = output.latest("deformation/bubble", 1.0, msg.MembraneDeformation).value
                        if received.hw_stamp_ns == stamp_ns:
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

            seen["nominal"] = await show("nominal")
            seen["pressed"] = await show("pressed")
            seen["depth"] = output.latest("depth/bubble", 1.0, msg.DepthFrame).value
            await send([b"depth/bubble", b"\xc1 not msgpack"])
            small = msg.DepthFrame(bubble="bubble", depth=np.zeros((10, 10), np.uint16), depth_scale_m=1e-4,
                                   fx_px=40.0, fy_px=40.0, cx_px=4.5, cy_px=4.5)
            sent["seq"] += 1
            await send(stamped(small, sent["seq"]))
            await asyncio.sleep(SILENCE_S)  # the camera falls silent
            seen["silent"] = await status_until(lambda s: s.state == "degraded")
            seen["recovered_deformation"] = await show("pressed")
            seen["recovered"] = await status_until(
                lambda s: s.state == "ready" and {"garbage", "bad_frame", "stale"} <= set(s.errors))
        return seen

    process = ServiceProcess("bubble_camera", name, config_path, tmp_path / "bubble_camera.log")
    try:
        process.wait_ready()
        seen = asyncio.run(asyncio.wait_for(scenario(), SCENARIO_TIMEOUT_S))
    finally:
        rc = process.stop()
    assert rc == 0, process.log()
    assert np.abs(seen["nominal"].deformation).max() <= HALF_COUNT_M
    for pressed in (seen["pressed"], seen["recovered_deformation"]):
        assert pressed.deformation.max() == pytest.approx(0.005, abs=2e-4)
        assert (pressed.deformation > 1e-3).sum() > 2000 and pressed.source == name
    np.testing.assert_array_equal(seen["depth"].depth, images["pressed"])
    assert seen["silent"].errors["stale"] >= 1
    errors = seen["recovered"].errors
    assert errors["garbage"] >= 1 and errors["bad_frame"] >= 1, errors


# --- lab mode: a recorded stream through the OpenCV driver, a captured reference ----------------------------------

LAB_PRESS_M = (0.0, 0.002, 0.004, 0.005)  # the recorded stream: the cube this far into the membrane
REFERENCE_OFFSET_M = 3e-4  # the captured membrane sits this much further than the nominal one


def write_depth_video(path, frames: list[np.ndarray], fps: float) -> None:
    """A 16-bit grey FFV1 video of ``frames`` (uint16)."""
    height, width = frames[0].shape
    writer = cv2.VideoWriter(str(path), cv2.CAP_FFMPEG, cv2.VideoWriter_fourcc(*"FFV1"), fps, (width, height),
                             [cv2.VIDEOWRITER_PROP_DEPTH, cv2.CV_16U, cv2.VIDEOWRITER_PROP_IS_COLOR, 0])
    assert writer.isOpened()
    for frame in frames:
        writer.write(frame)
    writer.release()


def test_in_lab_mode_the_service_publishes_the_deformation_of_a_recorded_stream(tmp_path):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    bubble = BubbleDepth.nominal(parse_config(config_text()), "bubble")
    frames = [frame_counts(bubble, (0.0, 0.0, -(0.055 - press), 1.0, 0.0, 0.0, 0.0)) for press in LAB_PRESS_M]
    write_depth_video(tmp_path / "depth.mkv", frames, fps=20.0)
    reference_m = (bubble.reference_m + np.float32(REFERENCE_OFFSET_M)).astype(np.float32)
    save_reference(tmp_path / "reference.npz", Reference(reference_m, 1e-4, 30, time.time_ns()))
    lab_table = DEPTH_TABLE.replace(" }", f', device = "{tmp_path / "depth.mkv"}", '
                                         f'reference = "{tmp_path / "reference.npz"}" }}')
    config_path = tmp_path / "lab.toml"
    config_path.write_text(config_text(str(run_dir)).replace('mode = "sim"', 'mode = "lab"')
                           .replace(DEPTH_TABLE, lab_table))
    config = load_config(config_path)
    name = "bubble_camera-bubble"

    async def scenario() -> list[tuple[msg.DepthFrame, msg.MembraneDeformation]]:
        pairs: dict[bytes, tuple[msg.DepthFrame, msg.MembraneDeformation]] = {}
        with Bus() as bus:
            output = LatestSubscriber(bus, config.endpoint(name), ["deformation/bubble", "depth/bubble"])
            while len(pairs) < len(frames):  # every recorded frame once (the stream plays again after its end)
                await output.wait(1.0)
                output.drain()
                try:
                    depth = output.latest("depth/bubble", 1.0, msg.DepthFrame).value
                    deformation = output.latest("deformation/bubble", 1.0, msg.MembraneDeformation).value
                except bus_layer.Stale:
                    continue
                if depth.hw_stamp_ns == deformation.hw_stamp_ns:
                    pairs[depth.depth.tobytes()] = (depth, deformation)
        return list(pairs.values())

    process = ServiceProcess("bubble_camera", name, config_path, tmp_path / "bubble_camera.log")
    try:
        process.wait_ready()
        pairs = asyncio.run(asyncio.wait_for(scenario(), SCENARIO_TIMEOUT_S))
    finally:
        rc = process.stop()
    assert rc == 0, process.log()
    sent = {frame.tobytes(): frame for frame in frames}
    for depth, deformation in pairs:
        assert depth.depth.tobytes() in sent  # bit-exact counts of a recorded frame
        depth_m = depth.depth.astype(np.float32) * np.float32(depth.depth_scale_m)
        np.testing.assert_array_equal(deformation.deformation, membrane_deformation(depth_m, reference_m))
    deepest = max(float(np.nanmax(deformation.deformation)) for _, deformation in pairs)
    assert deepest == pytest.approx(0.005 + REFERENCE_OFFSET_M, abs=2e-4)  # the captured reference, not nominal
