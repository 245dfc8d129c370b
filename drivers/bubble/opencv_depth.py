"""``OpenCVDepthCamera``: a Soft Bubble's ``DepthCamera`` on ``cv2.VideoCapture``: a device index (a camera that
streams 16-bit grey, V4L2 ``Y16``/``Z16``), a stream URL, a 16-bit video file (FFV1 ``.mkv``, ``gray16le``) or an
image sequence of 16-bit PNGs (``frame_%04d.png``).

The capture is owned by the shared grab thread of ``drivers.camera.opencv`` (``GrabThread``): frames are stamped
with ``time.monotonic_ns``, never handed out twice, ``Stale`` after ``max_age_ms``, ``NotConnected`` once the
source ends or fails ``MAX_CONSECUTIVE_GRAB_FAILURES`` grabs in a row, and files are paced at ``fps``.

Frames must arrive as depth counts, untouched: the capture is opened with ``CAP_PROP_CONVERT_RGB = 0`` (no
conversion to 8-bit BGR), a device also with ``CAP_PROP_FORMAT = -1`` (V4L2's raw buffers; FFmpeg would answer
with encoded packets, so files and URLs keep the decoded frames), and image sequences with OpenCV's own image
backend (``CAP_IMAGES``, which reads 16-bit PNGs unchanged; FFmpeg's would hand out big-endian bytes). A raw
buffer of exactly ``2 * height * width`` bytes is read as little-endian uint16 (V4L2's ``Y16``/``Z16`` layout).
Any other frame than ``(height, width)`` uint16 raises ``ProtocolError`` saying what came.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np

from hydrosoft.drivers.base import DepthFrame
from hydrosoft.drivers.camera.opencv import GrabThread
from hydrosoft.drivers.errors import ProtocolError

logger = logging.getLogger(__name__)

#: The bytes of one 16-bit depth pixel in a raw buffer.
BYTES_PER_COUNT = 2


@dataclass(frozen=True)
class OpenCVDepthConfig:
    """Settings of ``OpenCVDepthCamera``.

    source: a device index (``0`` is ``/dev/video0``), or a string: a 16-bit video file, a 16-bit PNG sequence
        pattern such as ``frames/frame_%04d.png``, or a stream URL. Files and sequences are played back at ``fps``.
    width, height: the depth image's size in pixels; every frame must have it (devices are also opened at it).
    fps: the device's frame rate (Hz), requested from devices; also the playback rate of files.
    depth_scale_m: metres per count of the camera's uint16 depth (0 = no return).
    max_age_ms: ``read`` raises ``Stale`` when no new frame arrives within this time, or the newest frame is older.
        At least two frame periods.
    open_timeout_s: how long ``connect`` waits for the source to open and deliver a first frame.
    """

    source: int | str
    width: int
    height: int
    fps: float = 30.0
    depth_scale_m: float = 0.0001
    max_age_ms: float = 500.0
    open_timeout_s: float = 5.0

    def __post_init__(self) -> None:
        if isinstance(self.source, bool) or not isinstance(self.source, (int, str)) or self.source == "":
            raise ValueError(f"OpenCVDepthConfig.source: expected a device index or a path/URL, got {self.source!r}")
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
                raise ValueError(f"OpenCVDepthConfig.{name}: expected a positive number of pixels, got {value!r}")
        for name in ("fps", "depth_scale_m", "open_timeout_s"):
            value = getattr(self, name)
            if not _is_number(value) or value <= 0:
                raise ValueError(f"OpenCVDepthConfig.{name}: expected a positive number, got {value!r}")
        if not _is_number(self.max_age_ms) or self.max_age_ms < 2 * 1000.0 / self.fps:
            raise ValueError(f"OpenCVDepthConfig.max_age_ms: {self.max_age_ms!r} must be at least two frame "
                             f"periods ({2 * 1000.0 / self.fps:.1f} ms at {self.fps} Hz)")


class OpenCVDepthCamera:
    """A Soft Bubble's depth camera read through OpenCV (see the module docstring).

    Args:
        config: source, image size, rate, depth unit, staleness limit and open timeout.
    """

    def __init__(self, config: OpenCVDepthConfig) -> None:
        self.config = config
        self._grabber = GrabThread(str(self), config.source, config.fps, config.max_age_ms, config.open_timeout_s,
                                   self._apply_settings, opener=open_depth_capture)

    def __str__(self) -> str:
        return f"OpenCVDepthCamera({self.config.source!r})"

    async def connect(self) -> None:
        """Open the source and wait for its first frame, which must be a depth image of the configured size.

        Raises:
            NotConnected: the source cannot be opened or gives no frame within ``config.open_timeout_s``.
            ProtocolError: the first frame is not ``(height, width)`` uint16 (the message says what came).
        """
        if self._grabber.running:
            return
        first = await self._grabber.start()
        try:
            self._counts(first)
        except ProtocolError:
            await self.close()
            raise
        logger.info("%s: connected, %dx%d uint16", self, self.config.width, self.config.height)

    async def read(self) -> DepthFrame:
        """The next depth frame, newer than the last one returned.

        Returns:
            ``DepthFrame``: ``depth (height, width)`` uint16 counts of ``config.depth_scale_m`` (0 = no return),
            ``stamp_ns`` when the grab returned, ``hw_stamp_ns`` from ``CAP_PROP_POS_MSEC`` (the driver's buffer
            time for V4L2, the position in the file for files) or ``None`` when the backend gives none.

        Raises:
            NotConnected: before ``connect``, after ``close``, or once the grab thread gave up (with its reason).
            Stale: no new frame within ``config.max_age_ms``, or the newest frame is older than that.
            ProtocolError: the frame is not ``(height, width)`` uint16; it is dropped, the next read goes on.
        """
        frame, stamp_ns, hw_stamp_ns = await self._grabber.next_frame()
        return DepthFrame(depth=self._counts(frame), depth_scale_m=self.config.depth_scale_m, stamp_ns=stamp_ns,
                          hw_stamp_ns=hw_stamp_ns)

    async def close(self) -> None:
        """Stop the grab thread and release the capture; safe to call repeatedly."""
        await self._grabber.stop()

    def _counts(self, frame: np.ndarray) -> np.ndarray:
        return depth_counts(frame, self.config.height, self.config.width, str(self))

    def _apply_settings(self, capture: cv2.VideoCapture) -> None:
        capture.set(cv2.CAP_PROP_CONVERT_RGB, 0)
        if isinstance(self.config.source, str):  # files, sequences and URLs: decoded frames, no device settings
            return
        if not capture.set(cv2.CAP_PROP_FORMAT, -1):
            logger.warning("%s: the backend refuses CAP_PROP_FORMAT = -1 (raw frames)", self)
        capture.set(cv2.CAP_PROP_FRAME_WIDTH, self.config.width)
        capture.set(cv2.CAP_PROP_FRAME_HEIGHT, self.config.height)
        capture.set(cv2.CAP_PROP_FPS, self.config.fps)


def depth_counts(frame: np.ndarray, height: int, width: int, label: str) -> np.ndarray:
    """``frame`` as ``(height, width)`` uint16 depth counts: as it is, or a raw buffer of exactly
    ``2 * height * width`` bytes (one row or column of uint8) read as little-endian uint16. Raises ProtocolError,
    starting with ``label``, saying what came otherwise."""
    expected = (height, width)
    raw = frame.dtype == np.uint8 and frame.ndim == 2 and min(frame.shape) == 1
    if raw and frame.size == BYTES_PER_COUNT * height * width:
        return np.ascontiguousarray(frame).reshape(-1).view("<u2").reshape(expected).astype(np.uint16, copy=False)
    if frame.dtype != np.uint16 or frame.shape != expected:
        raise ProtocolError(f"{label}: expected a single-channel uint16 depth image of {width}x{height} px, got "
                            f"shape {frame.shape} {frame.dtype}")
    return frame


def open_depth_capture(source: int | str) -> cv2.VideoCapture:
    """The capture of ``source``: OpenCV's image backend for an image-sequence pattern (``%`` in the name, 16-bit
    PNGs read unchanged), its default choice otherwise."""
    if isinstance(source, str) and "%" in source:
        return cv2.VideoCapture(source, cv2.CAP_IMAGES)
    return cv2.VideoCapture(source)


def _is_number(value: object) -> bool:
    """A finite int or float (not a bool)."""
    return not isinstance(value, bool) and isinstance(value, (int, float)) and math.isfinite(value)
