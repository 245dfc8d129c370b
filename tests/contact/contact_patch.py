"""A synthetic contact patch: N object points on a face with inward normal +z against the half-space z <= 0."""

import torch

from hydrosoft.contact import ContactStep, Material


def material(E=1e5, K=3e4, mu=0.5, dtype=torch.float64):
    return Material(*(torch.tensor([v], dtype=dtype) for v in (E, K, mu)))


def patch_step(p_prev, p_next, area, dtype=torch.float64):
    """ContactStep for points ``(N, 3)`` moving from p_prev to p_next; the body is the half-space phi = z."""
    p_prev = torch.as_tensor(p_prev, dtype=dtype).reshape(1, 1, -1, 3)
    p_next = torch.as_tensor(p_next, dtype=dtype).reshape(1, 1, -1, 3)
    n = p_prev.shape[2]
    normal = torch.zeros(1, 1, n, 3, dtype=dtype)
    normal[..., 2] = 1.0
    return ContactStep(
        phi_prev=p_prev[..., 2],
        phi_next=p_next[..., 2],
        displacement=p_prev - p_next,
        normal=normal,
        area=torch.full((n,), area, dtype=dtype),
    )


def drive(model, path, area=1e-4, mat=None, dtype=torch.float64):
    """Forces ``(1, 1, N, 3)`` after moving points along ``path``: a list of ``(N, 3)`` positions."""
    mat = mat or material(dtype=dtype)
    forces = torch.zeros(1, 1, torch.as_tensor(path[0]).reshape(-1, 3).shape[0], 3, dtype=dtype)
    history = []
    for a, b in zip(path[:-1], path[1:]):
        forces = model.step(patch_step(a, b, area, dtype), forces, mat)
        history.append(forces)
    return forces, history


def grid(z, x=0.0, n=4):
    """n*n points of a 1 cm patch at height z, shifted by x."""
    xs = torch.linspace(-0.005, 0.005, n, dtype=torch.float64)
    gx, gy = torch.meshgrid(xs + x, xs, indexing="ij")
    return torch.stack([gx.flatten(), gy.flatten(), torch.full((n * n,), z, dtype=torch.float64)], -1)


def press(z_start=0.002, depth=0.003, steps=7, x=0.0):
    """The patch pressed from ``z_start`` to ``-depth`` (m) in ``steps`` positions, shifted by x."""
    return [grid(z, x) for z in torch.linspace(z_start, -depth, steps, dtype=torch.float64).tolist()]
