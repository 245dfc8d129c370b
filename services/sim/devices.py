"""Bus-fed twins of the camera interfaces (``drivers/base.py``) for sim-hardware mode.

sim_world renders the tag camera's images and the bubbles' depth images and publishes them; these twins subscribe
to them and implement ``Camera`` / ``DepthCamera``, so the services above them run the same code in both modes.
They are bus clients, so they live in ``services/`` (``drivers/`` may not import the bus).
"""

from __future__ import annotations

import asyncio

from hydrosoft.drivers.base import DepthFrame, ImageFrame
from hydrosoft.drivers.errors import NotConnected, ProtocolError, Stale
from hydrosoft.services.bus import sockets
from hydrosoft.services.bus import messages as msg

#: How long ``BusDepthCamera.read`` waits for a new depth frame by default, s (five periods of a 10 Hz camera).
DEPTH_TIMEOUT_S = 0.5


def depth_topic(bubble: str) -> str:
    """The topic of bubble ``bubble``'s depth frames: ``depth/<bubble>``."""
    return msg.topic_for(msg.DepthFrame, bubble)


class BusDepthCamera:
    """A ``drivers.base.DepthCamera`` whose frames are ``DepthFrame`` messages on the bus (sim_world's rendered
    ``depth/<bubble>``).

    Args:
        subscriber: a latest-value subscriber connected to the publisher and subscribed to ``depth_topic(bubble)``
            (its owner, a ``Service`` or a test's ``Bus``, closes it).
        bubble: the bubble's name (its arm's name); a frame naming another bubble is refused.
        timeout_s: ``read`` raises ``Stale`` when no new frame arrives within this long (s); also the oldest frame
            it hands out.
    """

    def __init__(self, subscriber: sockets.LatestSubscriber, bubble: str, timeout_s: float = DEPTH_TIMEOUT_S) -> None:
        if not timeout_s > 0:
            raise ValueError(f"BusDepthCamera: timeout_s must be > 0 s, got {timeout_s!r}")
        self.bubble = bubble
        self.topic = depth_topic(bubble)
        self.timeout_s = timeout_s
        self._subscriber = subscriber
        self._connected = False
        self._last_stamp_ns = 0

    def __str__(self) -> str:
        return f"BusDepthCamera({self.topic})"

    async def connect(self) -> None:
        """Start reading (the subscriber is connected already; frames published before are not waited for)."""
        self._connected = True

    async def read(self) -> DepthFrame:
        """The newest depth frame published after the one returned last, waiting up to ``timeout_s`` for it.

        Returns:
            ``DepthFrame``: ``depth`` ``(H, W)`` uint16 counts of ``depth_scale_m`` (0 = no return), a read-only
            view of the message; ``stamp_ns`` when the publisher sent it (``time.monotonic_ns``); ``hw_stamp_ns``
            the frame's own stamp (sim: the stamp of the poses it was rendered from).

        Raises:
            NotConnected: before ``connect`` or after ``close``.
            Stale: when no newer frame arrives within ``timeout_s``.
            ProtocolError: when the newest frame names another bubble (it is not handed out again).
        """
        if not self._connected:
            raise NotConnected(f"{self}: read before connect (or after close)")
        loop = asyncio.get_running_loop()
        deadline_s = loop.time() + self.timeout_s
        while True:
            frame = self._newer_frame()
            if frame is not None:
                self._last_stamp_ns = frame.stamp_ns
                if frame.bubble != self.bubble:
                    raise ProtocolError(f"{self}: a frame of bubble {frame.bubble!r} came on {self.topic}")
                return DepthFrame(depth=frame.depth, depth_scale_m=frame.depth_scale_m, stamp_ns=frame.stamp_ns,
                                  hw_stamp_ns=frame.hw_stamp_ns)
            remaining_s = deadline_s - loop.time()
            if remaining_s <= 0:
                raise Stale(f"{self}: no new depth frame within {self.timeout_s:.3g} s")
            await self._subscriber.wait(remaining_s)

    def _newer_frame(self) -> msg.DepthFrame | None:
        """The newest frame if it is younger than ``timeout_s`` and newer than the last one returned."""
        try:
            received = self._subscriber.latest(self.topic, self.timeout_s, msg.DepthFrame)
        except sockets.Stale:
            return None
        return received.value if received.stamp_ns > self._last_stamp_ns else None

    async def close(self) -> None:
        """Stop reading; ``read`` raises ``NotConnected`` afterwards."""
        self._connected = False


#: How long ``BusCamera.read`` waits for a new image by default, s (a few frame periods of a 15 Hz camera).
IMAGE_TIMEOUT_S = 0.5


def image_topic(camera: str) -> str:
    """The topic of ``camera``'s images: ``image/<camera>``."""
    return msg.topic_for(msg.CameraImage, camera)


class BusCamera:
    """A ``drivers.base.Camera`` whose images are ``CameraImage`` messages on the bus (sim_world's tag camera).

    Args:
        subscriber: a latest-value subscriber connected to the publisher and subscribed to ``image_topic(camera)``
            (its owner, a ``Service`` or a test's ``Bus``, closes it).
        camera: the camera's name.
        timeout_s: ``read`` raises ``Stale`` when no new image arrives within this long (s); also the oldest image
            it hands out.
    """

    def __init__(self, subscriber: sockets.LatestSubscriber, camera: str = "tag_camera",
                 timeout_s: float = IMAGE_TIMEOUT_S) -> None:
        if not timeout_s > 0:
            raise ValueError(f"BusCamera: timeout_s must be > 0 s, got {timeout_s!r}")
        self.camera = camera
        self.topic = image_topic(camera)
        self.timeout_s = timeout_s
        self._subscriber = subscriber
        self._connected = False
        self._last_stamp_ns = 0

    def __str__(self) -> str:
        return f"BusCamera({self.topic})"

    async def connect(self) -> None:
        """Start reading (the subscriber is connected already; images published before are not waited for)."""
        self._connected = True

    async def read(self) -> ImageFrame:
        """The newest image published after the one returned last, waiting up to ``timeout_s`` for it.

        Returns:
            ``ImageFrame``: ``image`` ``(H, W, 3)`` BGR or ``(H, W)`` grey uint8, a read-only view of the message;
            ``stamp_ns`` when the publisher sent it (``time.monotonic_ns``, the host's clock: when the image
            reached the host); ``hw_stamp_ns`` the image's exposure stamp.

        Raises:
            NotConnected: before ``connect`` or after ``close``.
            Stale: when no newer image arrives within ``timeout_s``.
        """
        if not self._connected:
            raise NotConnected(f"{self}: read before connect (or after close)")
        loop = asyncio.get_running_loop()
        deadline_s = loop.time() + self.timeout_s
        while True:
            image = self._newer_image()
            if image is not None:
                self._last_stamp_ns = image.stamp_ns
                return ImageFrame(image=image.frame, stamp_ns=image.stamp_ns, hw_stamp_ns=image.hw_stamp_ns)
            remaining_s = deadline_s - loop.time()
            if remaining_s <= 0:
                raise Stale(f"{self}: no new image within {self.timeout_s} s")
            await self._subscriber.wait(remaining_s)

    def _newer_image(self) -> msg.CameraImage | None:
        """The newest image if it is younger than ``timeout_s`` and newer than the last one returned."""
        try:
            received = self._subscriber.latest(self.topic, self.timeout_s, msg.CameraImage)
        except sockets.Stale:
            return None
        return received.value if received.stamp_ns > self._last_stamp_ns else None

    async def close(self) -> None:
        """Stop reading; ``read`` raises ``NotConnected`` afterwards."""
        self._connected = False
