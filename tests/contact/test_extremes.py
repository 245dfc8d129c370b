"""Property tests: no NaN/Inf in forces or gradients and forces inside the friction cone, at the extremes."""

import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from hydrosoft.contact import ContactStep, Material, MODELS, make
from hydrosoft.contact.cone import split_normal

N = 6
log_uniform = lambda lo, hi: st.floats(lo, hi).map(lambda e: 10.0**e)  # noqa: E731
phis = st.sampled_from([0.0, 1e-300, -1e-300, 1e-12, -1e-12, 1e-6, -1e-6, 1e-3, -1e-3, 0.05, -0.05])
lengths = st.sampled_from([0.0, 1e-300, 1e-20, 1e-12, 1e-9, 1e-6, 1e-3, 0.02])


@st.composite
def scenarios(draw):
    dtype = draw(st.sampled_from([torch.float32, torch.float64]))
    E = draw(log_uniform(2, 8))
    K = draw(log_uniform(2, 8))
    mu = draw(st.sampled_from([0.0, 1e-6, 0.3, 1.0, 5.0]))
    name = draw(st.sampled_from(sorted(MODELS)))
    params = {"beta": draw(log_uniform(0, 6))} if name == "snh" else {}
    phi_prev = torch.tensor(draw(st.lists(phis, min_size=N, max_size=N)), dtype=torch.float64)
    grazing = draw(st.booleans())
    phi_next = phi_prev.clone() if grazing else torch.tensor(draw(st.lists(phis, min_size=N, max_size=N)), dtype=torch.float64)
    scale = torch.tensor(draw(st.lists(lengths, min_size=N, max_size=N)), dtype=torch.float64)
    direction = torch.nn.functional.normalize(torch.randn(N, 3, generator=torch.Generator().manual_seed(draw(st.integers(0, 99)))), dim=-1)
    tangential_force = draw(st.sampled_from([0.0, 1e-30, 1e-12, 1e-3, 10.0]))
    return dtype, name, params, Material(*(torch.tensor([v], dtype=dtype) for v in (E, K, mu))), phi_prev, phi_next, scale, direction, tangential_force


@settings(max_examples=300, deadline=None)
@given(scenarios())
def test_forces_and_gradients_finite_and_inside_cone(scenario):
    dtype, name, params, material, phi_prev, phi_next, scale, direction, f_t0 = scenario
    model = make(name, **params)
    normal = torch.zeros(1, 1, N, 3, dtype=dtype)
    normal[..., 2] = 1.0
    displacement = (scale.unsqueeze(-1) * direction).to(dtype).view(1, 1, N, 3).requires_grad_(True)
    phi_prev = phi_prev.to(dtype).view(1, 1, N).requires_grad_(True)
    phi_next = phi_next.to(dtype).view(1, 1, N).requires_grad_(True)
    forces = torch.zeros(1, 1, N, 3, dtype=dtype)
    forces[..., 0] = f_t0
    forces[..., 2] = (material.E * 1e-4 * torch.relu(-phi_prev.detach())).view(1, 1, N)
    forces.requires_grad_(True)
    geometry = ContactStep(phi_prev, phi_next, displacement, normal, torch.full((N,), 1e-4, dtype=dtype))
    out = model.step(geometry, forces, material)
    assert torch.isfinite(out).all()
    f_n, f_t = split_normal(out.detach().double(), normal.double())
    assert (f_n >= 0).all()
    limit = material.mu.double() * f_n
    assert (f_t.norm(dim=-1) <= limit * (1 + 1e-5) + 1e-30).all()
    grads = torch.autograd.grad(out.sum(), (displacement, phi_prev, phi_next, forces), allow_unused=True)
    for g in grads:
        assert g is None or torch.isfinite(g).all()


def test_a_tiny_shear_under_a_large_limit_has_finite_gradients_in_float32():
    """Found by the property test above: a point pressed 5 cm deep (50 N) moved by 1e-20 m carries a ~1e-18 N shear
    under a 250 N friction limit. The cone's clamped ratio ``limit / |f_t|`` had the gradient ``0 * limit / |f_t|^2``,
    and ``limit / |f_t|^2`` overflows float32: NaN gradients for every input of the point."""
    dtype = torch.float32
    material = Material(*(torch.tensor([v], dtype=dtype) for v in (1e7, 1e6, 5.0)))
    normal = torch.tensor([0.0, 0.0, 1.0], dtype=dtype).expand(1, 1, 1, 3)
    displacement = (1e-20 * torch.tensor([-0.4742, 0.5238, 0.7077])).view(1, 1, 1, 3).requires_grad_(True)
    phi_prev = torch.full((1, 1, 1), -0.05, dtype=dtype, requires_grad=True)
    phi_next = torch.zeros(1, 1, 1, dtype=dtype, requires_grad=True)
    forces = torch.tensor([0.0, 0.0, 50.0], dtype=dtype).view(1, 1, 1, 3).requires_grad_(True)
    for name in sorted(MODELS):
        geometry = ContactStep(phi_prev, phi_next, displacement, normal, torch.full((1,), 1e-4, dtype=dtype))
        out = make(name).step(geometry, forces, material)
        f_n, f_t = split_normal(out.detach(), normal)
        assert torch.isfinite(out).all() and (f_t.norm(dim=-1) <= 5.0 * f_n).all()
        grads = torch.autograd.grad(out.sum(), (displacement, phi_prev, phi_next, forces), allow_unused=True)
        assert all(g is None or torch.isfinite(g).all() for g in grads), name
