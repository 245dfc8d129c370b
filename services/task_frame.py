"""The task frame: where the task scene lies in the robot's base frame.

The model library plans in its task scene's own world frame (``hydrosoft/tasks/*.toml``: the table top at z = 0,
the object near the origin). On the bus every pose, point and vector is in the robot's base frame (ur_rtde reports
and takes TCP poses in it, the tag tracker reports the object in it). ``scene.task_frame`` in the config is
``T_base_task``, the task frame's pose in the base frame; the planner converts its inputs into the task frame and
its targets and predictions back, and sim_world places its plant there, so nothing else needs to know it.

In sim the default (identity) puts the scene at the base origin; in the lab it is measured once
(``hydrosoft-stack calibrate task-frame``) for where the table and the object's start are.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from hydrosoft.geometry import se3


@dataclass(frozen=True)
class TaskFrame:
    """``T_base_task`` ``(7,)`` float64 [x, y, z (m), qw, qx, qy, qz] and the conversions between the frames.

    Every method takes tensors of any leading shape and returns float64 ones (new tensors; exact for the identity).
    """

    pose: Tensor

    @classmethod
    def from_pose(cls, values) -> TaskFrame:
        """The task frame at ``values`` (7 numbers, checked by the config: ``SceneConfig``)."""
        return cls(torch.as_tensor(np.asarray(values, dtype=np.float64)).clone())

    def to_task(self, pose_base: Tensor) -> Tensor:
        """Poses ``(..., 7)`` in the base frame -> the same poses in the task frame."""
        return se3.compose(se3.inverse(self.pose), pose_base.double())

    def to_base(self, pose_task: Tensor) -> Tensor:
        """Poses ``(..., 7)`` in the task frame -> the same poses in the base frame."""
        return se3.compose(self.pose, pose_task.double())

    def points_to_base(self, points: Tensor) -> Tensor:
        """Points ``(..., 3)`` (m) in the task frame -> the base frame."""
        return se3.transform_points(self.pose, points.double().reshape(-1, 3)).reshape(points.shape)

    def vectors_to_base(self, vectors: Tensor) -> Tensor:
        """Free vectors ``(..., 3)`` (forces, displacements) in the task frame -> the base frame."""
        return se3.rotate_vectors(self.pose, vectors.double().reshape(-1, 3)).reshape(vectors.shape)

