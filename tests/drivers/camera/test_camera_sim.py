"""SimCamera: a Camera that renders the pose source's object on schedule; the tracker recovers that pose."""

import asyncio
import math
import time

import numpy as np
import pytest

from hydrosoft.drivers.base import Camera, ImageFrame
from hydrosoft.drivers.camera.config import CameraIntrinsics, SimCameraConfig
from hydrosoft.drivers.poses import look_at, rotation_angle_rad
from hydrosoft.drivers.camera.sim import SimCamera
from hydrosoft.drivers.camera.tags import box_layout
from hydrosoft.drivers.errors import DeviceFault, NotConnected, ProtocolError
from hydrosoft.services.tag_detection import ObjectPose, detect_tags, make_detector, object_pose_from_tags

INTRINSICS = CameraIntrinsics(640, 480, 500.0, 500.0, 319.5, 239.5)
LAYOUT = box_layout((0.05, 0.05, 0.05), 0.032)
T_BASE_CAMERA = look_at([0.3, 0.0, 0.45], [0.0, 0.0, 0.025], [-1.0, 0.0, 0.0])
TEST_TIMEOUT_S = 10.0


def run(coroutine):
    return asyncio.run(asyncio.wait_for(coroutine, TEST_TIMEOUT_S))


def make_camera(source, fps=50.0):
    return SimCamera(SimCameraConfig(fps=fps, seed=1), INTRINSICS, T_BASE_CAMERA, LAYOUT, source)


def test_is_a_camera_and_frames_show_the_pose_the_source_gave():
    poses = iter([np.array([0.0, 0.0, 0.025, math.cos(yaw / 2), 0, 0, math.sin(yaw / 2)]) for yaw in (0.0, 0.5, 1.0)])
    given = []

    def source():
        given.append(next(poses))
        return given[-1]

    camera = make_camera(source)
    assert isinstance(camera, Camera)

    async def three_frames():
        await camera.connect()
        frames = [await camera.read() for _ in range(3)]
        await camera.close()
        return frames

    frames = run(three_frames())
    for frame, truth in zip(frames, given):
        assert isinstance(frame, ImageFrame) and frame.image.shape == (480, 640, 3)
        result = object_pose_from_tags(detect_tags(frame.image, make_detector()), LAYOUT, INTRINSICS, T_BASE_CAMERA)
        assert isinstance(result, ObjectPose), result
        assert np.linalg.norm(result.T_base_object[:3] - truth[:3]) < 1e-3
        assert math.degrees(rotation_angle_rad(result.T_base_object[3:], truth[3:])) < 0.5


def test_frames_come_at_the_configured_rate_with_stamps():
    camera = make_camera(lambda: np.array([0.0, 0.0, 0.025, 1.0, 0, 0, 0]), fps=20.0)

    async def five_frames():
        await camera.connect()
        start_ns = time.monotonic_ns()
        frames = [await camera.read() for _ in range(5)]
        return frames, start_ns

    frames, start_ns = run(five_frames())
    hw = np.array([f.hw_stamp_ns for f in frames])
    np.testing.assert_array_equal(np.diff(hw), 50_000_000)  # scheduled exposure times, one period apart
    assert frames[-1].stamp_ns - start_ns >= 4 * 50_000_000  # read waited for the schedule
    assert all(f.stamp_ns >= f.hw_stamp_ns for f in frames)


def test_a_slow_reader_gets_the_newest_slot_not_a_backlog():
    camera = make_camera(lambda: np.array([0.0, 0.0, 0.025, 1.0, 0, 0, 0]), fps=50.0)

    async def late_read():
        await camera.connect()
        first = await camera.read()
        await asyncio.sleep(0.2)  # ten periods
        second = await camera.read()
        return first, second

    first, second = run(late_read())
    assert second.hw_stamp_ns - first.hw_stamp_ns >= 9 * 20_000_000
    assert second.stamp_ns - second.hw_stamp_ns < 20_000_000 + 100_000_000  # rendered at once, not a period later


def test_errors_are_driver_errors_with_clear_text():
    with pytest.raises(NotConnected, match="before connect"):
        run(make_camera(lambda: np.zeros(7)).read())

    async def read_once(camera):
        await camera.connect()
        return await camera.read()

    with pytest.raises(ProtocolError, match="non-finite"):
        run(read_once(make_camera(lambda: np.array([0, 0, 0, 1.0, 0, 0, np.nan]))))
    with pytest.raises(ProtocolError, match="shape"):
        run(read_once(make_camera(lambda: np.zeros(3))))

    def broken():
        raise RuntimeError("world not running")

    with pytest.raises(DeviceFault, match="world not running"):
        run(read_once(make_camera(broken)))
