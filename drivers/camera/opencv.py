"""OpenCV capture drivers: ``GrabThread``, the background thread that owns a ``cv2.VideoCapture`` (shared with the
Soft Bubble's ``drivers.bubble.opencv_depth.OpenCVDepthCamera``), and ``OpenCVCamera``, a ``Camera`` on it (a
USB/V4L2 device, a stream URL, a video file or an image sequence), so ``read`` never blocks the event loop on the
device.

The grab thread owns the capture: it opens it, applies the settings, and stores each frame with its
``time.monotonic_ns`` stamp and a sequence number, then wakes the event loop. ``read`` returns a frame newer than the
one it returned last, waiting for one up to ``max_age_ms``; it never returns the same frame twice. After
``MAX_CONSECUTIVE_GRAB_FAILURES`` failed grabs in a row (device unplugged, end of a file) the thread stops and every
``read`` raises ``NotConnected`` with the reason. Files and image sequences are paced at ``fps`` so they play
back like a camera.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections.abc import Callable

import cv2
import numpy as np

from hydrosoft.drivers.base import ImageFrame
from hydrosoft.drivers.camera.config import OpenCVCameraConfig
from hydrosoft.drivers.errors import DeviceFault, NotConnected, Stale

logger = logging.getLogger(__name__)

MAX_CONSECUTIVE_GRAB_FAILURES = 10  # a USB camera drops a frame now and then; ten in a row means it is gone
GRAB_RETRY_DELAY_S = 0.01  # pause after a failed grab before the next try
CLOSE_TIMEOUT_S = 2.0  # how long ``close`` waits for the grab thread (a hung driver call can take longer)
V4L2_MANUAL_EXPOSURE = 1  # CAP_PROP_AUTO_EXPOSURE values of the V4L2 backend: 1 manual, 3 automatic


def is_file_source(source: int | str) -> bool:
    """Whether ``source`` is a file or an image-sequence pattern (played back at ``fps``) rather than a device index
    or a stream URL."""
    return isinstance(source, str) and "://" not in source


def open_capture(source: int | str) -> cv2.VideoCapture:
    """``cv2.VideoCapture(source)`` with OpenCV's default backend choice."""
    return cv2.VideoCapture(source)


class GrabThread:
    """The background thread that owns one ``cv2.VideoCapture`` (see the module docstring).

    Args:
        label: how messages name the driver (its ``__str__``).
        source: a device index, a file, an image-sequence pattern or a stream URL.
        fps: playback rate of files (Hz).
        max_age_ms: ``next_frame`` raises ``Stale`` past this age (ms).
        open_timeout_s: how long ``start`` waits for the first frame (s).
        opener: opens the capture (in the thread), ``open_capture`` by default.
        configure: applies the driver's settings to the opened capture (in the thread), before the first grab.
    """

    def __init__(self, label: str, source: int | str, fps: float, max_age_ms: float, open_timeout_s: float,
                 configure: Callable[[cv2.VideoCapture], None],
                 opener: Callable[[int | str], cv2.VideoCapture] = open_capture) -> None:
        self.label = label
        self.source = source
        self.fps = fps
        self.max_age_ms = max_age_ms
        self.open_timeout_s = open_timeout_s
        self._open = opener
        self._configure = configure
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._new_frame = asyncio.Event()
        self._frame: np.ndarray | None = None
        self._sequence = 0
        self._stamp_ns = 0
        self._hw_stamp_ns: int | None = None
        self._failure: str | None = None
        self._returned_sequence = 0

    @property
    def running(self) -> bool:
        """Whether the thread was started and not stopped."""
        return self._thread is not None

    async def start(self) -> np.ndarray:
        """Start the thread and wait for the first frame; returns it (``next_frame`` still hands it out).

        Raises:
            NotConnected: the source cannot be opened or gives no frame within ``open_timeout_s``.
        """
        self._loop = asyncio.get_running_loop()
        self._new_frame = asyncio.Event()
        self._stop.clear()
        self._failure = None
        self._sequence = self._returned_sequence = 0
        self._thread = threading.Thread(target=self._grab_loop, name=f"grab {self.source}", daemon=True)
        self._thread.start()
        deadline_ns = time.monotonic_ns() + int(self.open_timeout_s * 1e9)
        while True:
            self._new_frame.clear()
            with self._lock:
                failure, sequence, frame = self._failure, self._sequence, self._frame
            if failure is not None:
                await self.stop()
                raise NotConnected(f"{self.label}: {failure}")
            if sequence > 0:
                return frame
            remaining_s = (deadline_ns - time.monotonic_ns()) / 1e9
            try:
                async with asyncio.timeout(max(remaining_s, 0.0)):  # wait_for may swallow a cancellation (3.11)
                    await self._new_frame.wait()
            except TimeoutError:
                await self.stop()
                raise NotConnected(f"{self.label}: no frame within {self.open_timeout_s} s of opening") from None

    async def next_frame(self) -> tuple[np.ndarray, int, int | None]:
        """The next frame, newer than the last one returned: ``(frame, stamp_ns, hw_stamp_ns)``. ``stamp_ns`` is
        ``time.monotonic_ns`` when the grab returned, ``hw_stamp_ns`` the capture's ``CAP_PROP_POS_MSEC`` in ns
        (``None`` where the backend gives none).

        Raises:
            NotConnected: before ``start``, after ``stop``, or once the thread gave up (with its reason).
            Stale: no new frame within ``max_age_ms``, or the newest frame is older than that.
        """
        if self._thread is None:
            raise NotConnected(f"{self.label}: read before connect (or after close)")
        deadline_ns = time.monotonic_ns() + int(self.max_age_ms * 1e6)
        while True:
            self._new_frame.clear()
            with self._lock:
                failure, sequence = self._failure, self._sequence
                frame, stamp_ns, hw_stamp_ns = self._frame, self._stamp_ns, self._hw_stamp_ns
            if failure is not None:
                raise NotConnected(f"{self.label}: {failure}")
            now_ns = time.monotonic_ns()
            if sequence > self._returned_sequence:
                age_ms = (now_ns - stamp_ns) / 1e6
                if age_ms > self.max_age_ms:
                    raise Stale(f"{self.label}: newest frame is {age_ms:.0f} ms old (limit {self.max_age_ms} ms)")
                self._returned_sequence = sequence
                return frame, stamp_ns, hw_stamp_ns
            try:
                async with asyncio.timeout(max(deadline_ns - now_ns, 0) / 1e9):
                    await self._new_frame.wait()
            except TimeoutError:
                raise Stale(f"{self.label}: no new frame for {self.max_age_ms} ms") from None

    async def stop(self) -> None:
        """Stop the thread and release the capture; safe to call repeatedly."""
        thread, self._thread = self._thread, None
        if thread is None:
            return
        self._stop.set()
        await asyncio.to_thread(thread.join, CLOSE_TIMEOUT_S)
        if thread.is_alive():
            logger.warning("%s: grab thread still busy %.1f s after close", self.label, CLOSE_TIMEOUT_S)

    def _grab_loop(self) -> None:
        capture = self._open(self.source)
        try:
            if not capture.isOpened():
                self._fail(f"cannot open {self.source!r} (no such device or file, or it is busy)")
                return
            self._configure(capture)
            period_s = 1.0 / self.fps
            next_due_s = time.monotonic()
            failures = 0
            while not self._stop.is_set():
                if is_file_source(self.source):
                    if self._stop.wait(max(next_due_s - time.monotonic(), 0.0)):
                        break
                    next_due_s += period_s
                ok, frame = capture.read()
                if not ok or frame is None:
                    failures += 1
                    if failures >= MAX_CONSECUTIVE_GRAB_FAILURES:
                        self._fail(f"stream ended: {failures} failed grabs in a row after {self._sequence} frames")
                        return
                    self._stop.wait(GRAB_RETRY_DELAY_S)
                    continue
                failures = 0
                position_ms = capture.get(cv2.CAP_PROP_POS_MSEC)
                with self._lock:
                    self._frame = frame
                    self._stamp_ns = time.monotonic_ns()
                    self._hw_stamp_ns = int(position_ms * 1e6) if position_ms > 0 else None
                    self._sequence += 1
                self._wake_reader()
        finally:
            capture.release()

    def _fail(self, reason: str) -> None:
        logger.error("%s: %s", self.label, reason)
        with self._lock:
            self._failure = reason
        self._wake_reader()

    def _wake_reader(self) -> None:
        loop = self._loop
        if loop is None or loop.is_closed():
            return
        try:
            loop.call_soon_threadsafe(self._new_frame.set)
        except RuntimeError:  # the loop closed between the check and the call
            pass


class OpenCVCamera:
    """A camera read through OpenCV (see the module docstring).

    Args:
        config: source, resolution, rate, exposure, staleness limit and open timeout.
    """

    def __init__(self, config: OpenCVCameraConfig) -> None:
        self.config = config
        self._grabber = GrabThread(str(self), config.source, config.fps, config.max_age_ms, config.open_timeout_s,
                                   self._apply_settings)

    def __str__(self) -> str:
        return f"OpenCVCamera({self.config.source!r})"

    @property
    def is_file(self) -> bool:
        """Whether the source is a file or an image sequence (paced at ``fps``) rather than a device or stream."""
        return is_file_source(self.config.source)

    async def connect(self) -> None:
        """Open the source and wait for its first frame.

        Raises:
            NotConnected: the source cannot be opened or gives no frame within ``config.open_timeout_s``.
            DeviceFault: the device delivers another resolution than the one requested.
        """
        if self._grabber.running:
            return
        frame = await self._grabber.start()
        height, width = frame.shape[:2]
        wanted = (self.config.width or width, self.config.height or height)
        if (width, height) != wanted:
            await self.close()
            raise DeviceFault(f"{self}: requested {wanted[0]}x{wanted[1]} but the device delivers {width}x{height}")
        logger.info("%s: connected, %dx%d", self, width, height)

    async def read(self) -> ImageFrame:
        """The next frame, newer than the last one returned.

        Returns:
            ``ImageFrame``: ``image`` as the capture gives it (``(H, W, 3)`` uint8 BGR for most sources),
            ``stamp_ns`` when the grab returned, ``hw_stamp_ns`` from ``CAP_PROP_POS_MSEC`` (the driver's buffer
            time for V4L2, the position in the file for files) or ``None`` when the backend gives none.

        Raises:
            NotConnected: before ``connect``, after ``close``, or once the grab thread gave up (with its reason).
            Stale: no new frame within ``config.max_age_ms``, or the newest frame is older than that.
        """
        image, stamp_ns, hw_stamp_ns = await self._grabber.next_frame()
        return ImageFrame(image=image, stamp_ns=stamp_ns, hw_stamp_ns=hw_stamp_ns)

    async def close(self) -> None:
        """Stop the grab thread and release the capture; safe to call repeatedly."""
        await self._grabber.stop()

    def _apply_settings(self, capture: cv2.VideoCapture) -> None:
        if self.is_file:
            return
        if self.config.width is not None:
            capture.set(cv2.CAP_PROP_FRAME_WIDTH, self.config.width)
        if self.config.height is not None:
            capture.set(cv2.CAP_PROP_FRAME_HEIGHT, self.config.height)
        capture.set(cv2.CAP_PROP_FPS, self.config.fps)
        if self.config.exposure is not None:
            capture.set(cv2.CAP_PROP_AUTO_EXPOSURE, V4L2_MANUAL_EXPOSURE)
            capture.set(cv2.CAP_PROP_EXPOSURE, self.config.exposure)
