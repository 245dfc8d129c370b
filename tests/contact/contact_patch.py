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
