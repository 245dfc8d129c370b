"""The bubble camera service: one Soft Bubble's depth frames and its membrane deformation.

One per arm, named ``bubble_camera-ARM``. Depth frames come from the bubble's ``DepthCamera``: in sim mode
``sim.devices.BusDepthCamera`` on sim_world's rendered ``depth/ARM``; in lab mode
``drivers.bubble.opencv_depth.OpenCVDepthCamera`` on the arm's ``depth.device`` (a device index, a URL, or a
recorded 16-bit stream: FFV1 ``.mkv`` or a 16-bit PNG sequence), opened at ``depth.width`` x ``depth.height`` and
``depth.fps``. The reference is the undeformed membrane's depth image: in sim mode the nominal membrane (the scene
body ``ARM``'s ellipsoid) seen from the configured camera pose, ``drivers.bubble.render.reference_depth``; in lab
mode the captured one, read from the file ``depth.reference`` names (``hydrosoft-stack capture reference`` writes
it, ``drivers.bubble.reference``). Each frame is published as ``depth/ARM`` (``DepthFrame``, the configured
intrinsics) and ``deformation/ARM`` (``MembraneDeformation``: reference minus measured depth along the optical
axis, m, NaN = no return), both carrying the frame's ``hw_stamp_ns``.

A frame that does not fit the configured camera (size, depth unit) is counted as ``bad_frame`` (or ``protocol``
when the driver already refuses it) and dropped; a camera that sends nothing new for ``STALE_FRAME_PERIODS`` frame
periods is counted as ``stale`` and the service reports ``degraded`` until frames come again; a camera that cannot
be opened or whose stream ends is counted as ``not_connected``, closed and opened again every
``RECONNECT_DELAY_S`` (a recorded stream plays again from its start). Nothing is republished meanwhile. None of
these ends the service.

Run: ``python -m hydrosoft.services.bubble_camera CONFIG [--name bubble_camera-ARM]``.
"""

from __future__ import annotations

import argparse
import asyncio
import time
from dataclasses import dataclass

import numpy as np

from hydrosoft.drivers.base import DepthCamera, DepthFrame
from hydrosoft.drivers.bubble.deformation import membrane_deformation
from hydrosoft.drivers.bubble.reference import ReferenceFileError, load_reference
from hydrosoft.drivers.bubble.render import PinholeDepth, reference_depth
from hydrosoft.drivers.errors import DriverError, NotConnected, ProtocolError, Stale
from hydrosoft.services.bus import messages as msg
from hydrosoft.services.bus.config import ConfigError, StackConfig
from hydrosoft.services.bus import service_cli
from hydrosoft.services.bus.runtime import Service
from hydrosoft.services.sim.devices import BusDepthCamera, depth_topic
from hydrosoft.scene_spec import task_scene_parts

MODULE = "bubble_camera"
#: The camera is stale after this many frame periods (of ``depth.fps``) without a new frame.
STALE_FRAME_PERIODS = 5
#: Pause before opening the camera again after it could not be opened or its stream ended (s).
RECONNECT_DELAY_S = 0.5
#: The command that writes the reference file of lab mode.
CAPTURE_COMMAND = "hydrosoft-stack capture reference CONFIG --arm ARM"
#: A frame's depth unit may differ from the configured ``depth_scale_m`` by this fraction (float rounding).
SCALE_TOLERANCE = 1e-6


class BadFrame(ValueError):
    """A depth frame that does not fit the configured camera (its size or depth unit)."""


def membrane_radii(config: StackConfig, arm: str) -> tuple[float, float, float]:
    """The radii (m, bubble frame) of ``arm``'s nominal membrane: the ellipsoid of the scene body named ``arm``.
    Raises ConfigError when the scene has no such body or it is not an ellipsoid."""
    scene = task_scene_parts(config.scene.task)
    body = next((b for b in scene.bodies if b.name == arm), None)
    if body is None or body.sdf != "ellipsoid":
        raise ConfigError(f"arms: {arm!r} must name an ellipsoid (Soft Bubble) body of the {config.scene.task!r} "
                          f"scene; its bodies are {[(b.name, b.sdf) for b in scene.bodies]}")
    return tuple(float(r) for r in body.params["radii"])


def depth_camera(config: StackConfig, arm: str) -> PinholeDepth:
    """``arm``'s depth camera model (image size and intrinsics, px) from its ``depth`` table."""
    d = config.arm(arm).depth
    return PinholeDepth(d.width, d.height, d.fx, d.fy, d.cx, d.cy)


@dataclass(frozen=True)
class BubbleDepth:
    """One bubble's depth pipeline: checks each frame against the camera and turns it into the two messages.

    bubble: the bubble's (arm's) name. camera: the pinhole model. depth_scale_m: the depth unit, m per count.
    reference_m: ``(H, W)`` float32 the undeformed membrane's depth image, m. reference_stamp_ns: when it was
    taken (``time.monotonic_ns``).
    """

    bubble: str
    camera: PinholeDepth
    depth_scale_m: float
    reference_m: np.ndarray
    reference_stamp_ns: int

    @classmethod
    def nominal(cls, config: StackConfig, arm: str) -> BubbleDepth:
        """The pipeline of ``arm`` with the nominal membrane as its reference (sim mode)."""
        depth = config.arm(arm).depth
        camera = depth_camera(config, arm)
        reference = reference_depth(camera, membrane_radii(config, arm), depth.camera_in_bubble())
        return cls(arm, camera, depth.depth_scale_m, reference, time.monotonic_ns())

    @classmethod
    def captured(cls, config: StackConfig, arm: str) -> BubbleDepth:
        """The pipeline of ``arm`` with the reference read from its ``depth.reference`` file (lab mode). Raises
        ConfigError naming the key when it is empty, the file cannot be used, or its image is not the camera's
        size."""
        depth = config.arm(arm).depth
        key = f"arms.{arm}.depth.reference"
        if not depth.reference:
            raise ConfigError(f"{key}: lab mode needs the captured reference membrane file; capture one with "
                              f"`{CAPTURE_COMMAND.replace('ARM', arm)} --out PATH.npz` while nothing touches the "
                              f"bubble, and name it here")
        try:
            reference = load_reference(depth.reference)
        except ReferenceFileError as error:
            raise ConfigError(f"{key}: {error}") from error
        camera = depth_camera(config, arm)
        if reference.reference_m.shape != (camera.height, camera.width):
            raise ConfigError(f"{key}: {depth.reference} holds a {reference.reference_m.shape[1]}x"
                              f"{reference.reference_m.shape[0]} px image, the depth camera's is "
                              f"{camera.width}x{camera.height}; capture it again")
        return cls(arm, camera, depth.depth_scale_m, reference.reference_m, reference.stamp_ns())

    @classmethod
    def for_mode(cls, config: StackConfig, arm: str) -> BubbleDepth:
        """The pipeline of ``arm`` for the config's mode: ``nominal`` in sim, ``captured`` in the lab."""
        return cls.nominal(config, arm) if config.mode == "sim" else cls.captured(config, arm)

    def messages(self, frame: DepthFrame) -> tuple[msg.DepthFrame, msg.MembraneDeformation]:
        """The ``DepthFrame`` and ``MembraneDeformation`` messages of one frame. Raises BadFrame when its image is
        not ``(H, W)`` uint16 of the camera or its depth unit is not ``depth_scale_m``."""
        counts = np.asarray(frame.depth)
        expected = (self.camera.height, self.camera.width)
        if counts.dtype != np.uint16 or counts.shape != expected:
            raise BadFrame(f"bubble {self.bubble}: a depth frame must be {expected} uint16, got {counts.shape} "
                           f"{counts.dtype}")
        if not abs(frame.depth_scale_m - self.depth_scale_m) <= SCALE_TOLERANCE * self.depth_scale_m:
            raise BadFrame(f"bubble {self.bubble}: a depth frame in units of {frame.depth_scale_m} m, the camera's "
                           f"are {self.depth_scale_m} m")
        depth_m = counts.astype(np.float32) * np.float32(self.depth_scale_m)
        c = self.camera
        depth = msg.DepthFrame(bubble=self.bubble, depth=counts, depth_scale_m=self.depth_scale_m, fx_px=c.fx,
                               fy_px=c.fy, cx_px=c.cx, cy_px=c.cy, hw_stamp_ns=frame.hw_stamp_ns)
        deformation = msg.MembraneDeformation(bubble=self.bubble,
                                              deformation=membrane_deformation(depth_m, self.reference_m),
                                              reference_stamp_ns=self.reference_stamp_ns,
                                              hw_stamp_ns=frame.hw_stamp_ns)
        return depth, deformation


def error_kind(error: Exception) -> str:
    """The short name under which the service counts ``error``."""
    if isinstance(error, BadFrame):
        return "bad_frame"
    if isinstance(error, Stale):
        return "stale"
    if isinstance(error, NotConnected):
        return "not_connected"
    if isinstance(error, ProtocolError):
        return "protocol"
    return "driver"


def lab_depth_camera(config: StackConfig, arm: str) -> DepthCamera:
    """``arm``'s ``OpenCVDepthCamera`` on its ``depth.device`` at the configured size, rate and depth unit, stale
    after ``STALE_FRAME_PERIODS`` frame periods. Raises ConfigError naming the key when ``device`` is empty."""
    depth = config.arm(arm).depth
    if not depth.device:
        raise ConfigError(f"arms.{arm}.depth.device: lab mode needs the depth camera's OpenCV source (a device "
                          f"index, a /dev/v4l/by-id/... path, a URL or a recorded 16-bit stream)")
    from hydrosoft.drivers.bubble.opencv_depth import OpenCVDepthCamera, OpenCVDepthConfig

    source: int | str = int(depth.device) if depth.device.isdigit() else depth.device
    return OpenCVDepthCamera(OpenCVDepthConfig(source=source, width=depth.width, height=depth.height, fps=depth.fps,
                                               depth_scale_m=depth.depth_scale_m,
                                               max_age_ms=1000.0 * STALE_FRAME_PERIODS / depth.fps))


def open_depth_camera(service: Service, config: StackConfig, arm: str) -> DepthCamera:
    """``arm``'s depth camera: sim_world's frames over the bus in sim mode, ``lab_depth_camera`` in the lab."""
    if config.mode != "sim":
        return lab_depth_camera(config, arm)
    frames = service.subscriber(config.endpoint("sim_world"), [depth_topic(arm)])
    return BusDepthCamera(frames, arm, timeout_s=STALE_FRAME_PERIODS / config.arm(arm).depth.fps)


async def serve(service: Service, config: StackConfig, arm: str) -> None:
    """Publish ``arm``'s depth frames and deformation images until cancelled (module docstring)."""
    bubble = BubbleDepth.for_mode(config, arm)
    camera = open_depth_camera(service, config, arm)
    service.on_shutdown(camera.close)
    out = service.publisher(config.endpoint(service.name))
    depth_out, deformation_out = msg.topic_for(msg.DepthFrame, arm), msg.topic_for(msg.MembraneDeformation, arm)
    connected = await _connect(service, camera)
    await service.ready()
    if not connected:
        await service.set_state("degraded")
    while True:
        if not connected:
            await asyncio.sleep(RECONNECT_DELAY_S)
            connected = await _connect(service, camera)
            continue
        try:
            depth, deformation = bubble.messages(await camera.read())
        except (DriverError, BadFrame) as error:
            service.count_error(error_kind(error), str(error))
            if isinstance(error, (Stale, NotConnected)) and service.state != "degraded":
                await service.set_state("degraded")
            if isinstance(error, NotConnected):
                await camera.close()
                connected = False
            continue
        try:
            await out.send(depth, depth_out)
            await out.send(deformation, deformation_out)
        except msg.MessageError as error:
            service.count_error(error.kind, f"cannot publish: {error}")
            continue
        if service.state != service.effective_state("ready"):
            await service.set_state("ready")


async def _connect(service: Service, camera: DepthCamera) -> bool:
    """Open ``camera``; whether it opened. A failure is counted (its ``error_kind``), the service goes on."""
    try:
        await camera.connect()
    except DriverError as error:
        service.count_error(error_kind(error), str(error))
        if service.state == "ready":
            await service.set_state("degraded")
        return False
    return True


def _validate(config: StackConfig, arm: str) -> None:
    """Refuse a config without this arm's membrane and, in lab mode, one without its depth camera's ``device``
    or a usable ``reference`` file."""
    membrane_radii(config, arm)
    if config.mode != "sim":
        lab_depth_camera(config, arm)
        BubbleDepth.captured(config, arm)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments: CONFIG [--name MODULE-ARM] (``service_cli``)."""
    service_cli.add_arm_arguments(parser, MODULE)


def run(args: argparse.Namespace) -> int:
    """Run the service until SIGINT/SIGTERM; the exit code (2: a bad config or name, or a lab config without the
    depth camera's device or reference file)."""
    return service_cli.run_arm(args, MODULE, serve, validate=_validate)


def main(argv: list[str] | None = None) -> int:
    return service_cli.main(MODULE, __doc__, argv, add_arguments, run)


if __name__ == "__main__":
    service_cli.exit_process(main())
