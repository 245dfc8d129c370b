"""The task frame: base <-> task conversions of poses, points and vectors, exact for the identity."""

from __future__ import annotations

import math

import numpy as np
import torch

from hydrosoft.geometry import se3
from hydrosoft.services.arm.task_frame import TaskFrame

YAW = math.radians(120.0)
FRAME = TaskFrame.from_pose([0.45, -0.12, -0.03, math.cos(YAW / 2), 0.0, 0.0, math.sin(YAW / 2)])


def random_poses(n: int, seed: int) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    poses = torch.randn(n, 7, generator=generator, dtype=torch.float64)
    poses[:, 3:] = torch.nn.functional.normalize(poses[:, 3:], dim=-1)
    return poses


def test_poses_go_to_the_task_frame_and_back():
    poses = random_poses(5, 0)
    task = FRAME.to_task(poses)
    torch.testing.assert_close(FRAME.to_base(task), poses, atol=1e-12, rtol=0)
    torch.testing.assert_close(FRAME.to_base(se3.identity()), FRAME.pose)  # the task origin lies at the frame
    moved = FRAME.to_task(FRAME.pose + torch.tensor([0.0, 0.0, 0.1, 0, 0, 0, 0], dtype=torch.float64))
    torch.testing.assert_close(moved[:3], torch.tensor([0.0, 0.0, 0.1], dtype=torch.float64), atol=1e-12, rtol=0)


def test_a_task_frame_x_step_is_turned_by_the_frames_yaw_in_the_base_frame():
    step = torch.tensor([[0.01, 0.0, 0.0]], dtype=torch.float64)
    expected = torch.tensor([[0.01 * math.cos(YAW), 0.01 * math.sin(YAW), 0.0]], dtype=torch.float64)
    torch.testing.assert_close(FRAME.vectors_to_base(step), expected, atol=1e-15, rtol=0)
    points = torch.zeros(2, 3, 3, dtype=torch.float64)
    torch.testing.assert_close(FRAME.points_to_base(points), FRAME.pose[:3].expand(2, 3, 3))


def test_points_and_poses_agree():
    pose = random_poses(1, 1)[0]
    point = torch.tensor([0.02, -0.01, 0.03], dtype=torch.float64)
    in_base = FRAME.points_to_base(se3.transform_points(pose, point.unsqueeze(0)))
    torch.testing.assert_close(in_base, se3.transform_points(FRAME.to_base(pose), point.unsqueeze(0)))


def test_the_identity_changes_nothing_bit_for_bit():
    identity = TaskFrame.from_pose(se3.identity())
    poses = random_poses(4, 2)
    assert torch.equal(identity.to_task(poses), poses) and torch.equal(identity.to_base(poses), poses)
    vectors = torch.randn(4, 3, dtype=torch.float64)
    assert torch.equal(identity.vectors_to_base(vectors), vectors)


def test_the_numpy_forms_agree_with_the_tensor_forms():
    poses = random_poses(6, 3)
    np.testing.assert_allclose(FRAME.to_base_np(poses.numpy()), FRAME.to_base(poses).numpy(), atol=1e-15, rtol=0)
    np.testing.assert_allclose(FRAME.to_task_np(poses.numpy()), FRAME.to_task(poses).numpy(), atol=1e-15, rtol=0)
    np.testing.assert_allclose(FRAME.to_task_np(FRAME.to_base_np(poses[0].numpy())), poses[0].numpy(), atol=1e-15)
    identity = TaskFrame.from_pose(se3.identity())
    assert np.array_equal(identity.to_base_np(poses.numpy()), poses.numpy())
