"""Analytic behaviour of PF, PFF, NH and smoothed NH on a synthetic patch against the half-space z <= 0."""

import pytest
import torch

from contact_patch import drive, grid, material, patch_step, press
from hydrosoft.contact import (
    ContactStep,
    Material,
    NonHolonomic,
    PressureField,
    PressureFieldFrictionless,
    SmoothedNonHolonomic,
    inside_fraction,
    make,
)

E, K, MU, AREA = 1e5, 3e4, 0.5, 1e-4


@pytest.mark.parametrize("model", [NonHolonomic(), PressureField(), PressureFieldFrictionless()])
def test_pressed_patch_gives_E_area_depth(model):
    depth = 0.003
    forces, _ = drive(model, press(depth=depth))
    total = forces.sum((0, 1, 2))
    expected = E * AREA * 16 * depth
    assert total[2].item() == pytest.approx(expected, rel=1e-2)
    assert torch.allclose(total[:2], torch.zeros(2, dtype=torch.float64), atol=1e-12)


def test_nh_equals_pf_for_normal_indentation_from_contact_free():
    path = press(z_start=0.0013, depth=0.0041, steps=5)
    nh, _ = drive(NonHolonomic(), path)
    pf, _ = drive(PressureField(), path)
    assert torch.allclose(nh, pf, rtol=1e-12, atol=1e-15)


def test_nh_sticks_then_slides_on_the_cone():
    depth = 0.002
    path = press(depth=depth, steps=3)
    shear = [grid(-depth, x) for x in torch.linspace(0.0, -0.004, 41, dtype=torch.float64).tolist()]
    _, history = drive(NonHolonomic(), path + shear[1:])
    f_n = E * AREA * depth
    for k, forces in enumerate(history[2:], start=1):
        displacement = 0.004 * k / 40
        f_t = forces[0, 0, :, 0]  # object moved -x relative to the body: friction on it points +x
        expected = min(K * AREA * displacement, MU * f_n)
        assert torch.allclose(f_t, torch.full_like(f_t, expected), rtol=1e-9)
        assert torch.allclose(forces[0, 0, :, 2], torch.full_like(f_t, f_n), rtol=1e-9)
    assert history[-1][0, 0, 0, 0].item() == pytest.approx(MU * f_n, rel=1e-12)


def test_nh_stick_spring_unloads_when_shear_reverses():
    depth = 0.002
    path = press(depth=depth, steps=3) + [grid(-depth, -0.0005), grid(-depth, 0.0)]
    forces, _ = drive(NonHolonomic(), path)
    assert torch.allclose(forces[0, 0, :, 0], torch.zeros(16, dtype=torch.float64), atol=1e-15)


def test_nh_resets_forces_when_points_leave_the_body():
    path = press(depth=0.002, steps=3) + [grid(-0.002, 0.001), grid(0.0005, 0.001)]
    forces, history = drive(NonHolonomic(), path)
    assert history[-2].abs().sum() > 0
    assert torch.count_nonzero(forces) == 0


def test_nh_resets_forces_when_points_slide_out_sideways():
    """A point that leaves tangentially keeps f_n without the reset of eq. 20."""
    model = NonHolonomic()
    mat = material()
    inside = patch_step(grid(0.001), grid(-0.001), AREA)
    forces = model.step(inside, torch.zeros(1, 1, 16, 3, dtype=torch.float64), mat)
    geometry = inside._replace(phi_prev=inside.phi_next, phi_next=torch.full_like(inside.phi_next, 1e-4),
                               displacement=torch.zeros_like(inside.displacement))
    assert torch.count_nonzero(model.step(geometry, forces, mat)) == 0


def test_pff_never_produces_tangential_force():
    path = press(depth=0.002, steps=3) + [grid(-0.002, x) for x in (0.001, 0.002, 0.004)]
    for forces in drive(PressureFieldFrictionless(), path)[1]:
        assert torch.count_nonzero(forces[..., :2]) == 0


def test_pf_friction_opposes_sliding_at_mu_fn():
    path = press(depth=0.002, steps=3) + [grid(-0.002, 0.001)]
    forces, _ = drive(PressureField(), path)
    f_n = E * AREA * 0.002
    assert torch.allclose(forces[0, 0, :, 0], torch.full((16,), -MU * f_n, dtype=torch.float64), rtol=1e-6)


def test_path_dependence_nh_differs_pf_does_not():
    end = grid(-0.002, 0.002)
    straight = press(depth=0.002, steps=3, x=0.002)
    press_then_shear = press(depth=0.002, steps=3) + [grid(-0.002, 0.001), end]
    nh_a, _ = drive(NonHolonomic(), straight)
    nh_b, _ = drive(NonHolonomic(), press_then_shear)
    assert (nh_a - nh_b).abs().max() > 1e-3
    pf_a, _ = drive(PressureFieldFrictionless(), straight)
    pf_b, _ = drive(PressureFieldFrictionless(), press_then_shear)
    assert torch.allclose(pf_a, pf_b, rtol=1e-12, atol=0)
    pf_a, _ = drive(PressureField(), straight + [end])
    pf_b, _ = drive(PressureField(), press_then_shear + [end])
    assert torch.allclose(pf_a, pf_b, rtol=1e-12, atol=0)


@pytest.mark.parametrize(
    "phi_prev,phi_next,expected",
    [(0.001, 0.002, 0.0), (-0.001, -0.003, 1.0), (0.001, -0.003, 0.75), (-0.003, 0.001, 0.75),
     (0.0, 0.0, 1.0), (1e-3, 1e-3, 0.0), (-1e-3, -1e-3, 1.0), (0.0, -1e-3, 1.0), (1e-3, 0.0, 0.0)],
)
def test_inside_fraction_cases(phi_prev, phi_next, expected):
    a = inside_fraction(torch.tensor(phi_prev, dtype=torch.float64), torch.tensor(phi_next, dtype=torch.float64))
    assert a.item() == pytest.approx(expected, abs=1e-12)


def test_smoothed_nh_matches_nh_deep_inside_for_large_beta():
    path = [grid(-0.001)] + [grid(z, 0.0005 * i) for i, z in enumerate((-0.002, -0.003, -0.003))]
    mat = material()
    start = NonHolonomic().step(patch_step(grid(0.0), grid(-0.001), AREA), torch.zeros(1, 1, 16, 3, dtype=torch.float64), mat)
    nh, snh = start, start
    for a, b in zip(path[:-1], path[1:]):
        nh = NonHolonomic().step(patch_step(a, b, AREA), nh, mat)
        snh = SmoothedNonHolonomic(beta=1e6).step(patch_step(a, b, AREA), snh, mat)
    assert torch.allclose(nh, snh, rtol=1e-9)


def test_smoothed_nh_has_gradient_just_outside_pf_does_not():
    z = torch.full((1,), 2e-4, dtype=torch.float64, requires_grad=True)
    for model, expect_grad in ((SmoothedNonHolonomic(beta=1e4), True), (PressureField(), False)):
        start = torch.tensor([[0.0, 0.0, 1e-3]], dtype=torch.float64)
        end = torch.cat([torch.zeros(1, 2, dtype=torch.float64), z.view(1, 1)], -1)
        f = model.step(patch_step(start, end, AREA), torch.zeros(1, 1, 1, 3, dtype=torch.float64), material())
        (g,) = torch.autograd.grad(f[..., 2].sum(), z)
        assert (g.abs().item() > 0) == expect_grad


def test_make_rejects_unknown_model():
    with pytest.raises(ValueError, match="known models: nh, snh, pf, pff"):
        make("hydro")


@pytest.mark.parametrize("name", ["pf", "pff", "nh", "snh", "nh_pressure_normal"])
def test_every_model_steps_coordinate_major_vectors_alike(name):
    """``step(..., axis=-2)`` on ``(B, M, 3, N)`` vectors is ``step`` on their ``(B, M, N, 3)`` transposes: the same
    forces, transposed, for random depths (in, out and crossing), displacements, normals and forces, some of them
    pushed past the friction cone."""
    g = torch.Generator().manual_seed(5)
    B, M, N = 3, 2, 11
    f64 = dict(generator=g, dtype=torch.float64)
    normal = torch.nn.functional.normalize(torch.randn(B, 1, N, 3, **f64), dim=-1)
    geometry = ContactStep(phi_prev=2e-3 * torch.randn(B, M, N, **f64), phi_next=2e-3 * torch.randn(B, M, N, **f64),
                           displacement=1e-3 * torch.randn(B, M, N, 3, **f64), normal=normal,
                           area=torch.rand(N, **f64) * AREA)
    forces = torch.randn(B, M, N, 3, **f64)
    mat = Material(*(torch.tensor([v, 2 * v], dtype=torch.float64) for v in (E, K, MU)))
    transposed = geometry._replace(displacement=geometry.displacement.mT, normal=geometry.normal.mT)
    model = make(name)
    expected = model.step(geometry, forces, mat)
    assert torch.count_nonzero(expected) > 0
    torch.testing.assert_close(model.step(transposed, forces.mT, mat, axis=-2).mT, expected, rtol=1e-14, atol=0.0)
