"""NH with the pressure field's normal force (``nh_pressure_normal``) on a synthetic patch against the half-space
z <= 0: NH's stick spring and slip on the cone, PF's normal force."""

import math

import pytest
import torch

from contact_patch import drive, grid, material, patch_step, press
from hydrosoft.contact import NonHolonomic, NonHolonomicPressureNormal, PressureFieldFrictionless, make
from hydrosoft.contact.cone import split_normal

E, K, MU, AREA = 1e5, 3e4, 0.5, 1e-4


def test_it_is_made_by_name():
    assert isinstance(make("nh_pressure_normal"), NonHolonomicPressureNormal)


def test_sticks_with_K_area_dx_then_slides_at_exactly_mu():
    depth = 0.002
    shear = [grid(-depth, x) for x in torch.linspace(0.0, -0.004, 41, dtype=torch.float64).tolist()]
    _, history = drive(NonHolonomicPressureNormal(), press(depth=depth, steps=3) + shear[1:])
    f_n = E * AREA * depth
    for k, forces in enumerate(history[2:], start=1):
        f_t = forces[0, 0, :, 0]  # object moved -x relative to the body: friction on it points +x
        expected = min(K * AREA * 0.004 * k / 40, MU * f_n)
        assert torch.allclose(f_t, torch.full_like(f_t, expected), rtol=1e-9)
        assert torch.allclose(forces[0, 0, :, 2], torch.full_like(f_t, f_n), rtol=1e-12)
    assert history[-1][0, 0, 0, 0].item() == pytest.approx(MU * f_n, rel=1e-12)


def test_normal_force_is_the_pressure_fields_along_any_path():
    """Pressed, sheared, pressed deeper, lifted, sheared back: the normal force is PFF's at every step, the tangential
    force never leaves the cone, and leaving the body resets it."""
    path = (press(depth=0.002, steps=3) + [grid(-0.002, 0.001), grid(-0.003, 0.002), grid(-0.001, 0.0015),
                                          grid(-0.001, -0.001), grid(0.0005, -0.001)])
    _, ours = drive(NonHolonomicPressureNormal(), path)
    _, pressure = drive(PressureFieldFrictionless(), path)
    normal = torch.zeros(1, 1, 16, 3, dtype=torch.float64)
    normal[..., 2] = 1.0
    for f, p in zip(ours, pressure):
        torch.testing.assert_close(f[..., 2], p[..., 2], rtol=1e-14, atol=0.0)
        f_n, f_t = split_normal(f, normal)
        assert (f_t.norm(dim=-1) <= MU * f_n * (1 + 1e-12)).all()
    assert torch.count_nonzero(ours[-1]) == 0


def test_nh_integrates_a_different_normal_force_on_a_tilted_slide():
    """The difference from NH: a face tilted against the body slid along it at constant depth. NH splits the
    sliding displacement against the tilted normal and gains normal force; the pressure normal stays."""
    tilt = 0.02
    patch = grid(-0.001)
    normal = torch.zeros(1, 1, 16, 3, dtype=torch.float64)
    normal[..., 0], normal[..., 2] = -math.sin(tilt), math.cos(tilt)
    start = patch_step(grid(0.001), patch, AREA)._replace(normal=normal)
    slide = patch_step(patch, patch, AREA)._replace(normal=normal)
    slide = slide._replace(displacement=torch.tensor([1e-3, 0.0, 0.0], dtype=torch.float64).expand(1, 1, 16, 3))
    mat = material(E, K, MU)
    change = {}
    for model in (NonHolonomic(), NonHolonomicPressureNormal()):
        forces = model.step(start, torch.zeros(1, 1, 16, 3, dtype=torch.float64), mat)
        before = (forces * normal).sum()
        for _ in range(6):
            forces = model.step(slide, forces, mat)
        change[model.name] = ((forces * normal).sum() / before - 1).item()
    assert abs(change["nh"]) > 1e-2
    assert abs(change["nh_pressure_normal"]) < 1e-12
