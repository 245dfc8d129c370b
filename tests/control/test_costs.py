"""Cost terms: known values, finite gradients at zero error, float32 and float64."""
from __future__ import annotations

import math

import pytest
import torch

from hydrosoft.control import effort_cost, hinge_cost, orientation_error, pose_cost, position_error

DTYPES = [torch.float32, torch.float64]


def pose(p, angle=0.0, axis=(0.0, 0.0, 1.0), dtype=torch.float64) -> torch.Tensor:
    """(7,) pose at position ``p`` (m) rotated by ``angle`` (rad) about the unit ``axis``."""
    s = math.sin(angle / 2)
    return torch.tensor([*p, math.cos(angle / 2), *(s * a for a in axis)], dtype=dtype)


@pytest.mark.parametrize("dtype", DTYPES)
def test_known_values(dtype):
    q = torch.stack([pose((3.0, 4.0, 0.0), 0.5, dtype=dtype), pose((0.0, 0.0, 1.0), 3 * math.pi / 2, dtype=dtype)])
    goal = pose((0.0, 0.0, 0.0), dtype=dtype)
    tol = dict(rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(position_error(q, goal), torch.tensor([5.0, 1.0], dtype=dtype), **tol)
    # 3 pi / 2 about z is a quarter turn the other way.
    torch.testing.assert_close(orientation_error(q, goal), torch.tensor([0.5, math.pi / 2], dtype=dtype), **tol)
    expected = torch.tensor([2.0 * 25 + 3.0 * 0.25, 2.0 * 1 + 3.0 * (math.pi / 2) ** 2], dtype=dtype)
    torch.testing.assert_close(pose_cost(q, goal, w_pos=2.0, w_rot=3.0), expected, **tol)
    assert pose_cost(q, goal).dtype == dtype


@pytest.mark.parametrize("dtype", DTYPES)
def test_orientation_error_ignores_quaternion_sign(dtype):
    q = pose((0.0, 0.0, 0.0), 2.0, axis=(0.6, 0.0, 0.8), dtype=dtype)
    goal = pose((0.0, 0.0, 0.0), -0.5, axis=(0.6, 0.0, 0.8), dtype=dtype)
    flipped = torch.cat([q[:3], -q[3:]])
    torch.testing.assert_close(orientation_error(q, goal), torch.tensor(2.5, dtype=dtype))
    torch.testing.assert_close(orientation_error(flipped, goal), torch.tensor(2.5, dtype=dtype))


@pytest.mark.parametrize("dtype", DTYPES)
def test_gradients_are_finite_and_zero_at_zero_error(dtype):
    goal = pose((0.1, -0.2, 0.3), 0.7, axis=(0.0, 1.0, 0.0), dtype=dtype).expand(2, 7)
    q = goal.clone().requires_grad_(True)
    for cost in (position_error(q, goal), orientation_error(q, goal), pose_cost(q, goal)):
        (grad,) = torch.autograd.grad(cost.sum(), q)
        assert torch.isfinite(grad).all()
        assert (grad.abs() < 1e-12).all()
        assert (cost.detach() < 1e-12).all()  # safe norms are off by at most sqrt(tiny)
    u = torch.zeros(2, 3, 6, dtype=dtype, requires_grad=True)
    (grad,) = torch.autograd.grad(effort_cost(u).sum() + hinge_cost(u, 0.0, 1.0, width=0.1).sum(), u)
    assert torch.isfinite(grad).all()


def test_pose_cost_gradient_matches_finite_differences():
    goal = pose((0.1, -0.2, 0.3), 0.7, axis=(0.0, 1.0, 0.0))
    q = torch.stack([pose((0.3, 0.0, 0.1), -1.0, axis=(0.8, 0.6, 0.0)), pose((0.0, 0.0, 0.0), 2.9)])
    assert torch.autograd.gradcheck(lambda x: pose_cost(x, goal, 2.0, 0.5), q.requires_grad_(True))


@pytest.mark.parametrize("dtype", DTYPES)
def test_effort_cost_weighs_components(dtype):
    u = torch.tensor([[[1.0, 0.0, 0.0, 0.0, 0.0, 2.0], [0.0, 1.0, 0.0, 1.0, 0.0, 0.0]]], dtype=dtype)
    weight = torch.tensor([10.0] * 3 + [1.0] * 3, dtype=dtype)
    torch.testing.assert_close(effort_cost(u, weight), torch.tensor([10.0 + 4.0 + 10.0 + 1.0], dtype=dtype))
    torch.testing.assert_close(effort_cost(u[:, 0, :1]), torch.tensor([1.0], dtype=dtype))


@pytest.mark.parametrize("dtype", DTYPES)
def test_hinge_cost_is_a_smooth_one_sided_square(dtype):
    limit, width = 5.0, 0.01  # e.g. a 5 N force limit smoothed over 0.01 N
    force = torch.tensor([[9.0], [5.0], [1.0]], dtype=dtype, requires_grad=True)
    cost = hinge_cost(force, limit, 2.0, width=width)
    expected = torch.tensor([2.0 * 16.0, 2.0 * (width * math.log(2)) ** 2, 0.0], dtype=dtype)
    torch.testing.assert_close(cost, expected, rtol=1e-5, atol=1e-9)
    (grad,) = torch.autograd.grad(cost.sum(), force)
    assert torch.isfinite(grad).all() and (grad >= 0).all()
    torch.testing.assert_close(grad[0, 0], torch.tensor(2.0 * 2 * 4.0, dtype=dtype))
    # Per-point limits broadcast over the trailing axes and the points are summed.
    two = hinge_cost(torch.tensor([[1.0, 3.0]], dtype=dtype), torch.tensor([0.0, 1.0], dtype=dtype), 1.0, width=1e-3)
    torch.testing.assert_close(two, torch.tensor([1.0 + 4.0], dtype=dtype))
