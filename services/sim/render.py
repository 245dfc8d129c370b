"""What sim_world's simulated cameras see, rendered from the plant's poses.

- The tag camera: ``drivers.camera.sim.SimCamera`` (AprilTags of ``tag_tracker.object_layout`` on the object's
  faces, the table plane at the task frame's height), with the calibration the tracker uses
  (``camera_calibration``) and sim's image noise and blur, at ``camera.fps``: grey images, as a monochrome camera's.
- Each bubble's depth camera: ``drivers.bubble.render.render_depth`` of the nominal membrane (the bubble's scene
  ellipsoid) pushed in by the object (its exact signed distance, ``object_sdf``), seen from
  ``T_bubble_camera = arm.depth.camera_in_bubble()``, with Gaussian depth noise ``sim.depth_noise_m`` on every
  return, as uint16 counts of ``depth.depth_scale_m``.

Frames: poses are ``(7,)`` ``[x, y, z, qw, qx, qy, qz]`` (m) in the robot base frame; an arm's TCP frame is its
bubble's frame.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from hydrosoft.drivers.bubble.render import PinholeDepth, render_depth, to_counts
from hydrosoft.drivers.camera.config import SimCameraConfig
from hydrosoft.drivers.camera.sim import SimCamera
from hydrosoft.drivers.poses import compose, inverse
from hydrosoft.geometry.sdf import Box, Cylinder
from hydrosoft.scene import ObjectSpec
from hydrosoft.services.bus import messages as msg
from hydrosoft.services.bus.config import StackConfig
from hydrosoft.services.tag_tracker import camera_calibration, config_layout
from hydrosoft.tasks import make_task

IMAGE_SEED = 0  # seed of the tag camera's pixel noise
DEPTH_SEED = 1  # seed of the depth noise (one generator per bubble, offset by its index)


def tag_camera(config: StackConfig, object_pose_source: Callable[[], np.ndarray]) -> SimCamera:
    """The simulated tag camera of ``config``: it renders the object at ``object_pose_source()`` (base frame) at
    ``camera.fps`` with ``sim.image_noise`` (grey levels) and ``sim.image_blur_px``, over the table top (every task
    scene's half-space z <= 0) at the task frame's height (``scene.task_frame``: level). Its images are grey
    ``(H, W)``, as a monochrome camera's: the scene is grey, and the tracker reads the same grey levels from them
    as from their BGR copy, whose three times the bytes cost the renderer, the bus and the tracker about 1.3 ms of
    CPU per image more (docs/benchmarks.md)."""
    calibration = camera_calibration(config)
    settings = SimCameraConfig(fps=config.camera.fps, noise_std=config.sim.image_noise,
                               blur_sigma_px=config.sim.image_blur_px, seed=IMAGE_SEED,
                               table_height_m=config.scene.task_frame[2], grey=True)
    return SimCamera(settings, calibration.intrinsics, calibration.T_base_camera,
                     config_layout(config, calibration.T_base_camera), object_pose_source)


def object_sdf(spec: ObjectSpec) -> Box | Cylinder:
    """The exact signed distance (object frame, m) of the scene's object: a ``cube`` or ``plate`` box, or a
    ``cylinder`` along z. Raises ValueError for another shape."""
    p = spec.params
    if spec.shape == "cube":
        return Box((p.get("side", 0.05) / 2,) * 3)
    if spec.shape == "plate":
        return Box((p.get("length", 0.10) / 2, p.get("width", 0.10) / 2, p.get("thickness", 0.005) / 2))
    if spec.shape == "cylinder":
        return Cylinder(p.get("radius", 0.025), p.get("length", 0.10) / 2)
    raise ValueError(f"sim_world renders depth images of cubes, plates and cylinders, not a {spec.shape!r}")


def membrane_radii(config: StackConfig, arm: str) -> tuple[float, float, float]:
    """The radii (m) of ``arm``'s nominal membrane: its scene body's ellipsoid."""
    body = next(b for b in make_task(config.scene.task).scene.bodies if b.name == arm)
    return tuple(float(r) for r in body.params["radii"])


def depth_camera(config: StackConfig, arm: str) -> PinholeDepth:
    """``arm``'s depth camera model (image size and intrinsics, px) from its ``depth`` table."""
    d = config.arm(arm).depth
    return PinholeDepth(d.width, d.height, d.fx, d.fy, d.cx, d.cy)


@dataclass
class BubbleDepthCamera:
    """One bubble's simulated depth camera.

    camera: the pinhole model. radii: the nominal membrane's ellipsoid (m, bubble frame). T_bubble_camera: ``(7,)``
    the camera in the bubble frame. sdf: the object's signed distance (object frame). depth_scale_m: m per count.
    noise_m: std of the Gaussian noise on each returned depth (m). rng: its generator. The last noise-free image is
    kept: a bubble and object that have not moved relative to each other get fresh noise on it without a new render.
    """

    arm: str
    camera: PinholeDepth
    radii: tuple[float, float, float]
    T_bubble_camera: np.ndarray
    sdf: Box | Cylinder
    depth_scale_m: float
    noise_m: float
    rng: np.random.Generator
    _last: tuple[bytes, np.ndarray] | None = field(default=None, init=False, repr=False)  # (T_tcp_object, depth)

    @classmethod
    def from_config(cls, config: StackConfig, arm: str, index: int) -> BubbleDepthCamera:
        """The depth camera of the config's arm ``arm`` (``index``: its position in ``config.arms``)."""
        depth = config.arm(arm).depth
        return cls(arm, depth_camera(config, arm), membrane_radii(config, arm),
                   np.asarray(depth.camera_in_bubble(), dtype=np.float64),
                   object_sdf(make_task(config.scene.task).scene.object), depth.depth_scale_m,
                   config.sim.depth_noise_m, np.random.default_rng(DEPTH_SEED + index))

    def render(self, T_base_tcp: np.ndarray, T_base_object: np.ndarray) -> np.ndarray:
        """The depth image ``(H, W)`` uint16 (counts of ``depth_scale_m``; 0 = no return) with the bubble at
        ``T_base_tcp`` and the object at ``T_base_object`` (both ``(7,)``, base frame)."""
        T_tcp_object = compose(inverse(T_base_tcp), T_base_object)
        key = T_tcp_object.tobytes()
        if self._last is None or self._last[0] != key:
            self._last = (key, render_depth(self.camera, self.radii, self.T_bubble_camera, self.sdf, T_tcp_object))
        depth_m = self._last[1]
        if self.noise_m > 0:
            depth_m = depth_m + self.rng.normal(0.0, self.noise_m, depth_m.shape).astype(np.float32)
        return to_counts(depth_m, self.depth_scale_m)

    def message(self, counts: np.ndarray, hw_stamp_ns: int) -> msg.DepthFrame:
        """The ``DepthFrame`` of one rendered image (``hw_stamp_ns``: the poses' stamp)."""
        c = self.camera
        return msg.DepthFrame(bubble=self.arm, depth=counts, depth_scale_m=self.depth_scale_m, fx_px=c.fx,
                              fy_px=c.fy, cx_px=c.cx, cy_px=c.cy, hw_stamp_ns=hw_stamp_ns)
