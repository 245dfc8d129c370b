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

import numpy as np
import torch
from torch import Tensor

from hydrosoft.geometry import se3


def _quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton products ``a ⊗ b`` of quaternions ``(..., 4)`` wxyz, broadcast."""
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], axis=-1)


class TaskFrame:
    """``T_base_task`` ``pose (7,)`` float64 [x, y, z (m), qw, qx, qy, qz] and the conversions between the frames.

    The tensor methods take tensors of any leading shape and return new float64 ones (exact for the identity);
    the ``*_np`` ones do the same on numpy poses ``(..., 7)`` in a few microseconds, for a loop that converts every
    tick (sim_world's physics).
    """

    def __init__(self, pose: Tensor) -> None:
        self.pose = pose.double()
        self._inverse = se3.inverse(self.pose)
        self._identity = bool(torch.equal(self.pose, se3.identity()))
        self._t = self.pose[:3].numpy().copy()
        self._q = self.pose[3:].numpy().copy()
        self._q_inverse = self._q * np.array([1.0, -1.0, -1.0, -1.0])
        self._R = se3.quat_to_matrix(self.pose[3:]).numpy()

    @classmethod
    def from_pose(cls, values) -> TaskFrame:
        """The task frame at ``values`` (7 numbers, checked by the config: ``SceneConfig``)."""
        return cls(torch.as_tensor(np.asarray(values, dtype=np.float64)).clone())

    def to_task(self, pose_base: Tensor) -> Tensor:
        """Poses ``(..., 7)`` in the base frame -> the same poses in the task frame."""
        return pose_base.double().clone() if self._identity else se3.compose(self._inverse, pose_base.double())

    def to_base(self, pose_task: Tensor) -> Tensor:
        """Poses ``(..., 7)`` in the task frame -> the same poses in the base frame."""
        return pose_task.double().clone() if self._identity else se3.compose(self.pose, pose_task.double())

    def points_to_base(self, points: Tensor) -> Tensor:
        """Points ``(..., 3)`` (m) in the task frame -> the base frame."""
        return se3.transform_points(self.pose, points.double().reshape(-1, 3)).reshape(points.shape)

    def vectors_to_base(self, vectors: Tensor) -> Tensor:
        """Free vectors ``(..., 3)`` (forces, displacements) in the task frame -> the base frame."""
        if self._identity:
            return vectors.double().clone()
        return se3.rotate_vectors(self.pose, vectors.double().reshape(-1, 3)).reshape(vectors.shape)

    def to_task_np(self, pose_base: np.ndarray) -> np.ndarray:
        """``to_task`` of numpy poses ``(..., 7)``."""
        pose_base = np.asarray(pose_base, dtype=np.float64)
        if self._identity:
            return pose_base.copy()
        return np.concatenate([(pose_base[..., :3] - self._t) @ self._R,
                               _quat_multiply(self._q_inverse, pose_base[..., 3:])], axis=-1)

    def to_base_np(self, pose_task: np.ndarray) -> np.ndarray:
        """``to_base`` of numpy poses ``(..., 7)``."""
        pose_task = np.asarray(pose_task, dtype=np.float64)
        if self._identity:
            return pose_task.copy()
        return np.concatenate([pose_task[..., :3] @ self._R.T + self._t, _quat_multiply(self._q, pose_task[..., 3:])],
                              axis=-1)
