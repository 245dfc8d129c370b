"""The friction-cone projection at the extremes: values and gradients over a grid of normal and shear magnitudes."""

import itertools

import pytest
import torch

from hydrosoft.contact.cone import project_to_cone

MAGNITUDES = [0.0, 1e-45, 1e-38, 1e-30, 1e-20, 1e-19, 1e-10, 1.0, 250.0, 1e10, 1e30]


@pytest.mark.parametrize("compiled", [False, True], ids=["eager", "compiled"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["float32", "float64"])
def test_projection_and_gradients_are_finite_over_every_normal_and_shear(dtype, compiled):
    """Every pair of magnitudes, in one batch: the float32 pairs of a tiny shear under a large limit (1e-20 N under
    0.5 N, 1e-19 N under 125 N, ...) gave NaN gradients with a clamped ratio ``limit / |f_t|``."""
    pairs = torch.tensor(list(itertools.product(MAGNITUDES, MAGNITUDES)), dtype=torch.float64)
    f_n = pairs[:, 0].to(dtype).requires_grad_(True)
    f_t = (pairs[:, 1:] * torch.tensor([0.6, -0.8, 0.0], dtype=torch.float64)).to(dtype).requires_grad_(True)
    mu = torch.tensor(0.5, dtype=dtype)
    project = torch.compile(project_to_cone, dynamic=False) if compiled else project_to_cone
    n, t = project(f_n, f_t, mu)
    limit = (mu * f_n.detach()).double()
    norm = t.detach().double().norm(dim=-1)  # in float64: float32 squares of 1e-21 N would be subnormal
    assert torch.isfinite(n).all() and torch.isfinite(t).all()
    assert (norm <= limit * (1 + 4 * torch.finfo(dtype).eps)).all()
    # inside the cone the shear passes unchanged (above safe_norm's floor of sqrt(tiny): 1e-19 N in float32)
    sticks = (f_t.detach().double().norm(dim=-1) <= limit) & (limit > 1e-18)
    torch.testing.assert_close(t.detach()[sticks], f_t.detach()[sticks], rtol=0, atol=0)
    grads = torch.autograd.grad((n.sum() + (t * torch.tensor([1.0, 2.0, 3.0], dtype=dtype)).sum()), (f_n, f_t))
    assert all(torch.isfinite(g).all() for g in grads)
