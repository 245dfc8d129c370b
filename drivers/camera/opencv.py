"""``OpenCVCamera``: a ``Camera`` on ``cv2.VideoCapture`` (a USB/V4L2 device, a stream URL, a video file or an image
sequence), grabbing in a background thread so ``read`` never blocks the event loop on the device.

The grab thread owns the capture: it opens it, applies the settings, and stores each frame with its
``time.monotonic_ns`` stamp and a sequence number, then wakes the event loop. ``read`` returns a frame newer than the
one it returned last, waiting for one up to ``config.max_age_ms``; it never returns the same frame twice. After
``MAX_CONSECUTIVE_GRAB_FAILURES`` failed grabs in a row (device unplugged, end of a file) the thread stops and every
``read`` raises ``NotConnected`` with the reason. Files and image sequences are paced at ``config.fps`` so they play
back like a camera.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time

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


class OpenCVCamera:
    """A camera read through OpenCV (see the module docstring).

    Args:
        config: source, resolution, rate, exposure, staleness limit and open timeout.
    """

    def __init__(self, config: OpenCVCameraConfig) -> None:
        self.config = config
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

    def __str__(self) -> str:
        return f"OpenCVCamera({self.config.source!r})"

    @property
    def is_file(self) -> bool:
        """Whether the source is a file or an image sequence (paced at ``fps``) rather than a device or stream."""
        return isinstance(self.config.source, str) and "://" not in self.config.source

    async def connect(self) -> None:
        """Open the source and wait for its first frame.

        Raises:
            NotConnected: the source cannot be opened or gives no frame within ``config.open_timeout_s``.
            DeviceFault: the device delivers another resolution than the one requested.
        """
        if self._thread is not None:
            return
        self._loop = asyncio.get_running_loop()
        self._new_frame = asyncio.Event()
        self._stop.clear()
        self._failure = None
        self._sequence = self._returned_sequence = 0
        self._thread = threading.Thread(target=self._grab_loop, name=f"grab {self.config.source}", daemon=True)
        self._thread.start()
        deadline_ns = time.monotonic_ns() + int(self.config.open_timeout_s * 1e9)
        while True:
            self._new_frame.clear()
            with self._lock:
                failure, sequence, frame = self._failure, self._sequence, self._frame
            if failure is not None:
                await self.close()
                raise NotConnected(f"{self}: {failure}")
            if sequence > 0:
                break
            remaining_s = (deadline_ns - time.monotonic_ns()) / 1e9
            try:
                await asyncio.wait_for(self._new_frame.wait(), max(remaining_s, 0.0))
            except TimeoutError:
                await self.close()
                raise NotConnected(f"{self}: no frame within {self.config.open_timeout_s} s of opening") from None
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
        if self._thread is None:
            raise NotConnected(f"{self}: read before connect (or after close)")
        max_age_ns = int(self.config.max_age_ms * 1e6)
        deadline_ns = time.monotonic_ns() + max_age_ns
        while True:
            self._new_frame.clear()
            with self._lock:
                failure, sequence = self._failure, self._sequence
                frame, stamp_ns, hw_stamp_ns = self._frame, self._stamp_ns, self._hw_stamp_ns
            if failure is not None:
                raise NotConnected(f"{self}: {failure}")
            now_ns = time.monotonic_ns()
            if sequence > self._returned_sequence:
                age_ms = (now_ns - stamp_ns) / 1e6
                if age_ms > self.config.max_age_ms:
                    raise Stale(f"{self}: newest frame is {age_ms:.0f} ms old (limit {self.config.max_age_ms} ms)")
                self._returned_sequence = sequence
                return ImageFrame(image=frame, stamp_ns=stamp_ns, hw_stamp_ns=hw_stamp_ns)
            try:
                await asyncio.wait_for(self._new_frame.wait(), max(deadline_ns - now_ns, 0) / 1e9)
            except TimeoutError:
                raise Stale(f"{self}: no new frame for {self.config.max_age_ms} ms") from None

    async def close(self) -> None:
        """Stop the grab thread and release the capture; safe to call repeatedly."""
        thread, self._thread = self._thread, None
        if thread is None:
            return
        self._stop.set()
        await asyncio.to_thread(thread.join, CLOSE_TIMEOUT_S)
        if thread.is_alive():
            logger.warning("%s: grab thread still busy %.1f s after close", self, CLOSE_TIMEOUT_S)

    # The grab thread.

    def _grab_loop(self) -> None:
        capture = cv2.VideoCapture(self.config.source)
        try:
            if not capture.isOpened():
                self._fail(f"cannot open {self.config.source!r} (no such device or file, or it is busy)")
                return
            self._apply_settings(capture)
            period_s = 1.0 / self.config.fps
            next_due_s = time.monotonic()
            failures = 0
            while not self._stop.is_set():
                if self.is_file:
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

    def _fail(self, reason: str) -> None:
        logger.error("%s: %s", self, reason)
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
