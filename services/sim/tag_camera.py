"""The simulated tag camera of a config, without torch (the ``sim_camera`` service imports only this).

``tag_camera(config, source)``: ``drivers.camera.sim.SimCamera`` rendering the AprilTags of
``tag_tracker.config_layout`` on the object's faces over the table plane at the task frame's height, with the
calibration the tracker uses (``camera_calibration``) and sim's image noise and blur, at ``camera.fps``.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from hydrosoft.drivers.camera.config import SimCameraConfig
from hydrosoft.drivers.camera.sim import SimCamera
from hydrosoft.services.bus.config import StackConfig
from hydrosoft.services.tag_tracker import camera_calibration, config_layout

IMAGE_SEED = 0  # seed of the tag camera's pixel noise


def tag_camera(config: StackConfig, object_pose_source: Callable[[], np.ndarray]) -> SimCamera:
    """The simulated tag camera of ``config``: it renders the object at ``object_pose_source()`` (base frame) at
    ``camera.fps`` with ``sim.image_noise`` (grey levels) and ``sim.image_blur_px``, over the table top (every task
    scene's half-space z <= 0) at the task frame's height (``scene.task_frame``: level)."""
    calibration = camera_calibration(config)
    settings = SimCameraConfig(fps=config.camera.fps, noise_std=config.sim.image_noise,
                               blur_sigma_px=config.sim.image_blur_px, seed=IMAGE_SEED,
                               table_height_m=config.scene.task_frame[2])
    return SimCamera(settings, calibration.intrinsics, calibration.T_base_camera,
                     config_layout(config, calibration.T_base_camera), object_pose_source)
