"""OpenCVCamera: the real cv2.VideoCapture on files written here (video and image sequence); a missing source is a
clear NotConnected; a stalled device is Stale; a device that ignores the requested resolution is a DeviceFault."""

import asyncio
import threading

import cv2
import numpy as np
import pytest

from hydrosoft.drivers.base import Camera
from hydrosoft.drivers.camera.config import OpenCVCameraConfig
from hydrosoft.drivers.camera.opencv import OpenCVCamera
from hydrosoft.drivers.errors import DeviceFault, NotConnected, Stale

TEST_TIMEOUT_S = 10.0
FRAMES = 8
LEVELS = [20 + 25 * i for i in range(FRAMES)]  # frame i is a uniform grey of this level


def run(coroutine):
    return asyncio.run(asyncio.wait_for(coroutine, TEST_TIMEOUT_S))


@pytest.fixture
def video(tmp_path):
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (160, 120))
    assert writer.isOpened()
    for level in LEVELS:
        writer.write(np.full((120, 160, 3), level, np.uint8))
    writer.release()
    return path


@pytest.fixture
def sequence(tmp_path):
    for index, level in enumerate(LEVELS):
        cv2.imwrite(str(tmp_path / f"frame_{index:03d}.png"), np.full((120, 160, 3), level, np.uint8))
    return tmp_path / "frame_%03d.png"


async def read_all(camera):
    """Every frame until the stream ends, then the NotConnected it ended with."""
    await camera.connect()
    frames = []
    try:
        while True:
            frames.append(await camera.read())
    except NotConnected as error:
        return frames, error
    finally:
        await camera.close()


@pytest.mark.parametrize("source", ["video", "sequence"])
def test_reads_every_frame_of_a_file_in_order_then_reports_the_end(request, source):
    path = request.getfixturevalue(source)
    camera = OpenCVCamera(OpenCVCameraConfig(source=str(path), fps=50.0, max_age_ms=1000.0))
    assert isinstance(camera, Camera)
    frames, ended = run(read_all(camera))
    assert len(frames) == FRAMES
    assert [round(float(f.image.mean())) for f in frames] == pytest.approx(LEVELS, abs=2)
    assert all(f.image.shape == (120, 160, 3) and f.image.dtype == np.uint8 for f in frames)
    stamps = [f.stamp_ns for f in frames]
    assert stamps == sorted(stamps) and stamps[-1] - stamps[0] >= (FRAMES - 1) * 20_000_000 * 0.8  # paced at 50 Hz
    assert "stream ended" in str(ended) and str(path) in str(ended)


def test_missing_file_is_not_connected(tmp_path):
    camera = OpenCVCamera(OpenCVCameraConfig(source=str(tmp_path / "absent.avi"), open_timeout_s=2.0))
    with pytest.raises(NotConnected, match="cannot open"):
        run(camera.connect())
    with pytest.raises(NotConnected, match="before connect"):
        run(camera.read())


def test_missing_device_is_not_connected():
    camera = OpenCVCamera(OpenCVCameraConfig(source=63, open_timeout_s=2.0))  # /dev/video63: not on a test machine
    with pytest.raises(NotConnected, match="cannot open 63"):
        run(camera.connect())


class FakeCapture:
    """cv2.VideoCapture's surface: delivers ``frames`` frames of ``shape``, then hangs in ``read`` as a stalled
    USB camera does, until released."""

    frames = 3
    shape = (48, 64, 3)

    def __init__(self, source):
        self.delivered = 0
        self.released = threading.Event()

    def isOpened(self):
        return True

    def set(self, prop, value):
        return True

    def get(self, prop):
        return 0.0

    def read(self):
        if self.delivered < self.frames:
            self.delivered += 1
            return True, np.full(self.shape, self.delivered, np.uint8)
        self.released.wait(0.2)
        return False, None

    def release(self):
        self.released.set()


def test_stalled_device_is_stale_not_old_data(monkeypatch):
    monkeypatch.setattr(cv2, "VideoCapture", FakeCapture)
    camera = OpenCVCamera(OpenCVCameraConfig(source=0, fps=30.0, max_age_ms=100.0))

    async def scenario():
        await camera.connect()
        frames = []
        with pytest.raises(Stale, match="no new frame for 100.0 ms"):
            while True:
                frames.append(await camera.read())
        await camera.close()
        return frames

    frames = run(scenario())
    seen = [int(f.image[0, 0, 0]) for f in frames]  # the fake delivers at once: older frames may be skipped
    assert seen[-1] == 3 and seen == sorted(set(seen))  # newest last, none twice, then Stale


def test_device_ignoring_the_resolution_is_a_fault(monkeypatch):
    monkeypatch.setattr(cv2, "VideoCapture", FakeCapture)
    camera = OpenCVCamera(OpenCVCameraConfig(source=0, width=1280, height=720))
    with pytest.raises(DeviceFault, match="requested 1280x720 but the device delivers 64x48"):
        run(camera.connect())
