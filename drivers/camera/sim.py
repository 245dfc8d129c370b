"""``SimCamera``: a ``Camera`` whose frames are rendered AprilTag images of a simulated object.

``sim_world`` supplies the object's pose through a callable; each frame samples it at the frame's exposure time and
renders what the calibrated camera would see (``render.Renderer``), so the real tracker runs on real images in
simulation. Frames come on a fixed schedule at ``config.fps`` measured from ``connect``. ``read`` returns the
newest frame slot not yet delivered: it waits for the next slot, or renders at once when a slot has passed
unread (the pose is then sampled when rendering starts, up to one period after the slot's stamp); slots older than
the newest are dropped, as a real camera's frames would be, never delivered as a burst. When rendering is slower
than ``fps`` the rate is the rendering rate (about 30 ms per 1280 x 720 frame on one core).
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable

import numpy as np

from hydrosoft.drivers.base import ImageFrame
from hydrosoft.drivers.camera.config import CameraIntrinsics, SimCameraConfig
from hydrosoft.drivers.poses import check_pose, compose, inverse
from hydrosoft.drivers.camera.render import Renderer, RenderOptions
from hydrosoft.drivers.camera.tags import TagLayout
from hydrosoft.drivers.errors import DeviceFault, NotConnected, ProtocolError


class SimCamera:
    """A simulated RGB camera looking at one tagged object.

    Args:
        config: frame rate, noise, blur, seed, table height.
        intrinsics: the simulated lens (the tracker should be given the same, or a deliberately wrong one).
        T_base_camera: ``(7,)`` the camera's pose in the base frame (m, wxyz; OpenCV camera axes).
        layout: the object's tags and faces.
        object_pose_source: returns the object's current pose ``(7,)`` in the base frame; called once per frame.
    """

    def __init__(
        self,
        config: SimCameraConfig,
        intrinsics: CameraIntrinsics,
        T_base_camera: np.ndarray,
        layout: TagLayout,
        object_pose_source: Callable[[], np.ndarray],
    ) -> None:
        self.config = config
        self.intrinsics = intrinsics
        self.T_camera_base = inverse(check_pose(T_base_camera, "T_base_camera"))
        self.layout = layout
        self.object_pose_source = object_pose_source
        self._renderer = Renderer(intrinsics, RenderOptions(noise_std=config.noise_std,
                                                            blur_sigma_px=config.blur_sigma_px, grey=config.grey))
        self._rng = np.random.default_rng(config.seed)
        self._period_ns = round(1e9 / config.fps)
        self._start_ns: int | None = None
        self._next_index = 0

    def __str__(self) -> str:
        return f"SimCamera({self.intrinsics.width}x{self.intrinsics.height} @ {self.config.fps} Hz)"

    async def connect(self) -> None:
        """Start the frame clock: frame 0 is due now."""
        self._start_ns = time.monotonic_ns()
        self._next_index = 0

    async def read(self) -> ImageFrame:
        """Wait for the next scheduled frame and render it.

        Returns:
            ``ImageFrame`` with ``image (H, W, 3)`` uint8 BGR (``(H, W)`` grey with ``config.grey``), ``stamp_ns``
            when rendering finished and ``hw_stamp_ns`` the frame's scheduled exposure time (both
            ``time.monotonic_ns``).

        Raises:
            NotConnected: before ``connect`` or after ``close``.
            ProtocolError: when the pose source returns something that is not a pose (shape, NaN, quaternion norm).
            DeviceFault: when the pose source raises.
        """
        if self._start_ns is None:
            raise NotConnected(f"{self}: read before connect (or after close)")
        now_ns = time.monotonic_ns()
        index = max(self._next_index, (now_ns - self._start_ns) // self._period_ns)
        due_ns = self._start_ns + index * self._period_ns
        self._next_index = index + 1
        if due_ns > now_ns:
            await asyncio.sleep((due_ns - now_ns) / 1e9)
        try:
            pose = self.object_pose_source()
        except Exception as error:
            raise DeviceFault(f"{self}: object_pose_source raised {type(error).__name__}: {error}") from error
        try:
            T_base_object = check_pose(pose, "object pose")
        except ValueError as error:
            raise ProtocolError(f"{self}: object_pose_source returned a bad pose: {error}") from error
        image = await asyncio.to_thread(self.render, T_base_object)
        return ImageFrame(image=image, stamp_ns=time.monotonic_ns(), hw_stamp_ns=due_ns)

    def render(self, T_base_object: np.ndarray) -> np.ndarray:
        """The image ``(H, W, 3)`` uint8 BGR (``(H, W)`` grey with ``config.grey``) of the object at
        ``T_base_object (7,)``, with the table if configured."""
        T_camera_table = None
        if self.config.table_height_m is not None:
            T_base_table = np.array([0.0, 0.0, self.config.table_height_m, 1.0, 0.0, 0.0, 0.0])
            T_camera_table = compose(self.T_camera_base, T_base_table)
        return self._renderer.render(compose(self.T_camera_base, T_base_object), self.layout, self._rng,
                                     T_camera_table)

    async def close(self) -> None:
        """Stop the frame clock; ``read`` raises ``NotConnected`` afterwards."""
        self._start_ns = None
