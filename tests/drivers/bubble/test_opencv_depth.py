"""OpenCVDepthCamera: the real cv2.VideoCapture on 16-bit depth streams written here from rendered membrane depth
(``drivers.bubble.render``): a 16-bit FFV1 video (``cv2.VideoWriter``, ``isColor = False``,
``VIDEOWRITER_PROP_DEPTH = CV_16U``; this OpenCV build writes and reads it bit-exactly) and a 16-bit PNG
sequence. Counts come back bit-exactly, in order, at about the playback rate; the end of the file is NotConnected;
a wrong-size, 8-bit or colour source is a ProtocolError saying what came; a missing device or file is a clear
NotConnected within the open timeout."""

from __future__ import annotations

import asyncio
import time

import cv2
import numpy as np
import pytest

from hydrosoft.drivers.base import DepthCamera
from hydrosoft.drivers.bubble.opencv_depth import OpenCVDepthCamera, OpenCVDepthConfig, depth_counts
from hydrosoft.drivers.bubble.render import PinholeDepth, reference_depth, render_depth, to_counts
from hydrosoft.drivers.errors import NotConnected, ProtocolError
from hydrosoft.geometry.sdf import Box

TEST_TIMEOUT_S = 10.0
CAMERA = PinholeDepth(160, 120, 40.0, 40.0, 79.5, 59.5)
RADII = (0.06, 0.045, 0.03)  # the tasks' bubble, m
LOOK_DOWN = (0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0)  # depth.axis "-z"
SCALE_M = 1e-4
FPS = 20.0
PRESS_M = (0.0, 0.001, 0.002, 0.003, 0.004, 0.005)  # frame i: the pushing cube this far into the membrane


def membrane_frames() -> list[np.ndarray]:
    """uint16 counts ``(120, 160)`` of the cube pressed ``PRESS_M`` into the membrane, one frame each."""
    frames = []
    for press_m in PRESS_M:
        pose = (0.0, 0.0, -(0.055 - press_m), 1.0, 0.0, 0.0, 0.0)  # the cube's top face 30 mm - press below
        frames.append(to_counts(render_depth(CAMERA, RADII, LOOK_DOWN, Box((0.025, 0.025, 0.025)), pose), SCALE_M))
    return frames


def write_ffv1(path, frames: list[np.ndarray], fps: float = FPS) -> None:
    """A 16-bit grey FFV1 video of ``frames``."""
    height, width = frames[0].shape
    writer = cv2.VideoWriter(str(path), cv2.CAP_FFMPEG, cv2.VideoWriter_fourcc(*"FFV1"), fps, (width, height),
                             [cv2.VIDEOWRITER_PROP_DEPTH, cv2.CV_16U, cv2.VIDEOWRITER_PROP_IS_COLOR, 0])
    assert writer.isOpened(), "this OpenCV build cannot write 16-bit FFV1"
    for frame in frames:
        writer.write(frame)
    writer.release()


@pytest.fixture(scope="module")
def frames() -> list[np.ndarray]:
    counts = membrane_frames()
    assert len({c.tobytes() for c in counts}) == len(counts)  # every frame differs: order is checkable
    return counts


@pytest.fixture
def video(tmp_path, frames):
    path = tmp_path / "depth.mkv"
    write_ffv1(path, frames)
    return path


@pytest.fixture
def sequence(tmp_path, frames):
    for index, frame in enumerate(frames):
        assert cv2.imwrite(str(tmp_path / f"frame_{index:04d}.png"), frame)
    return tmp_path / "frame_%04d.png"


def run(coroutine):
    return asyncio.run(asyncio.wait_for(coroutine, TEST_TIMEOUT_S))


def config(source, **changes) -> OpenCVDepthConfig:
    settings = dict(source=source if isinstance(source, int) else str(source), width=160, height=120, fps=FPS, depth_scale_m=SCALE_M, max_age_ms=1000.0,
                    open_timeout_s=3.0)
    return OpenCVDepthConfig(**(settings | changes))


async def read_all(camera):
    """Every frame until the stream ends, then the NotConnected it ended with."""
    await camera.connect()
    received = []
    try:
        while True:
            received.append(await camera.read())
    except NotConnected as error:
        return received, error
    finally:
        await camera.close()


@pytest.mark.parametrize("source", ["video", "sequence"])
def test_reads_the_counts_bit_exactly_in_order_at_fps_then_reports_the_end(request, frames, source):
    path = request.getfixturevalue(source)
    camera = OpenCVDepthCamera(config(path))
    assert isinstance(camera, DepthCamera)
    received, ended = run(read_all(camera))
    assert len(received) == len(frames)
    for sent, got in zip(frames, received):
        assert got.depth.dtype == np.uint16 and got.depth.shape == (120, 160)
        np.testing.assert_array_equal(got.depth, sent)
        assert got.depth_scale_m == SCALE_M
    stamps_s = np.array([f.stamp_ns for f in received]) / 1e9
    periods_s = np.diff(stamps_s)
    assert periods_s.min() > 0  # in order, never the same frame twice
    # paced at fps (the median: a slow first decode is caught up by the next frames, on schedule)
    assert np.median(periods_s) == pytest.approx(1.0 / FPS, rel=0.25)
    assert stamps_s[-1] - stamps_s[0] < 3 * (len(frames) - 1) / FPS
    assert "stream ended" in str(ended) and str(path) in str(ended)
    with pytest.raises(NotConnected, match="before connect"):
        run(camera.read())


def test_a_wrong_size_source_is_a_protocol_error_saying_what_came(video):
    camera = OpenCVDepthCamera(config(video, width=80, height=60))
    with pytest.raises(ProtocolError, match=r"uint16 depth image of 80x60 px, got shape \(120, 160\) uint16"):
        run(camera.connect())
    with pytest.raises(NotConnected):  # closed after the refusal
        run(camera.read())


def test_an_8_bit_colour_video_is_a_protocol_error(tmp_path):
    path = tmp_path / "colour.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), FPS, (160, 120))
    for level in (10, 20, 30):
        writer.write(np.full((120, 160, 3), level, np.uint8))
    writer.release()
    with pytest.raises(ProtocolError, match="uint8"):
        run(OpenCVDepthCamera(config(path)).connect())


def test_a_bad_frame_in_the_stream_is_refused_and_the_next_one_read(tmp_path, frames):
    cv2.imwrite(str(tmp_path / "frame_0000.png"), frames[0])
    cv2.imwrite(str(tmp_path / "frame_0001.png"), frames[1][:60, :80])  # a frame of another size
    cv2.imwrite(str(tmp_path / "frame_0002.png"), frames[2])
    camera = OpenCVDepthCamera(config(tmp_path / "frame_%04d.png"))

    async def scenario():
        await camera.connect()
        try:
            first = await camera.read()
            with pytest.raises(ProtocolError, match=r"got shape \(60, 80\)"):
                await camera.read()
            third = await camera.read()
        finally:
            await camera.close()
        return first, third

    first, third = run(scenario())
    np.testing.assert_array_equal(first.depth, frames[0])
    np.testing.assert_array_equal(third.depth, frames[2])


@pytest.mark.parametrize("source, text", [(63, "cannot open 63"), ("absent.mkv", "cannot open")])
def test_a_missing_device_or_file_is_not_connected_within_its_timeout(tmp_path, source, text):
    if isinstance(source, str):
        source = str(tmp_path / source)
    camera = OpenCVDepthCamera(config(source, open_timeout_s=2.0))  # /dev/video63: not on a test machine
    tic_s = time.monotonic()
    with pytest.raises(NotConnected, match=text):
        run(camera.connect())
    assert time.monotonic() - tic_s < 2.0 + 1.0


def test_a_raw_little_endian_buffer_is_read_as_counts_and_other_shapes_are_refused(frames):
    raw = frames[3].astype("<u2").view(np.uint8).reshape(1, -1)  # what V4L2 hands out for Y16 in raw mode
    np.testing.assert_array_equal(depth_counts(raw, 120, 160, "cam"), frames[3])
    with pytest.raises(ProtocolError, match=r"cam: .* got shape \(1, 100\) uint8"):
        depth_counts(raw[:, :100], 120, 160, "cam")
    with pytest.raises(ProtocolError, match=r"got shape \(120, 160, 3\) uint16"):
        depth_counts(np.zeros((120, 160, 3), np.uint16), 120, 160, "cam")


def test_the_rendered_nominal_membrane_fits_the_uint16_range():
    counts = to_counts(reference_depth(CAMERA, RADII, LOOK_DOWN), SCALE_M)
    assert counts.min() > 0  # every pixel sees the membrane: no 0 (no return) in the test streams' background


@pytest.mark.parametrize("changes, text", [
    (dict(source=""), "source"),
    (dict(width=0), "width"),
    (dict(depth_scale_m=0.0), "depth_scale_m"),
    (dict(max_age_ms=50.0), "two frame periods"),
])
def test_bad_settings_are_refused_by_name(changes, text):
    with pytest.raises(ValueError, match=text):
        config(changes.pop("source", "x.mkv"), **changes)
