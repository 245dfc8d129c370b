"""The closed-loop state estimate: tactile forces (eq. 22-24) through the plant -> planner resampling, noise."""

from __future__ import annotations

import pytest
import torch
from conftest import quick_planner

from hydrosoft.tasks import make_task
from hydrosoft.tasks.evaluation import PlantSettings, estimate_state, prepare

F64 = torch.float64


def dragged(setup, steps: int = 4):
    """Drag the bubble 2 mm per step along x so the contact carries shear as well as pressure."""
    u = torch.zeros(setup.plant.model.n_bodies, 6, dtype=F64)
    u[setup.plant.model.body_names.index("bubble"), 0] = 0.002
    for _ in range(steps):
        assert setup.plant.apply(u)
    return setup


def net_forces(forces: torch.Tensor) -> torch.Tensor:
    """Net force per body ``(M, 3)`` of per-point forces ``(1, M, N, 3)``."""
    return forces[0].sum(1)


def test_observed_forces_equal_the_plants_when_they_share_spacing():
    """Same spacing, same material: eq. 24 inverted then applied gives the plant's forces back (rounding only)."""
    setup = dragged(prepare(make_task("pushing"), quick_planner(), PlantSettings(spacing_factor=1.0)))
    plant = setup.plant.state
    estimate = estimate_state(setup, setup.plant.measure())
    truth = net_forces(plant.forces)[setup.body_index]
    assert float(truth[0, 0]) > 0.1  # the bubble shears the cube along +x
    assert torch.allclose(net_forces(estimate.forces), truth, rtol=1e-9, atol=1e-12)
    assert torch.equal(estimate.object_pose, plant.object_pose)
    assert torch.equal(estimate.body_poses, plant.body_poses[:, setup.body_index])


def test_observed_forces_from_a_finer_plant_match_its_net_force_within_10_percent():
    """Half the spacing: nearest-neighbour resampling and the planner's coarser areas keep the net force within
    10 % of its magnitude."""
    setup = dragged(prepare(make_task("pushing"), quick_planner(), PlantSettings()))
    truth = net_forces(setup.plant.state.forces)[setup.body_index]
    estimate = net_forces(estimate_state(setup, setup.plant.measure()).forces)
    assert setup.plant.model.n_points > 2 * setup.planner_model.n_points
    error = (estimate - truth).norm(dim=-1) / truth.norm(dim=-1)
    assert bool((error < 0.10).all()), error


def test_noisy_sensors_are_seeded_and_leave_the_plant_alone():
    noisy = PlantSettings(pose_noise_m=0.002, pose_noise_rad=0.02, deformation_noise_m=1e-4, seed=7)
    setup = dragged(prepare(make_task("pushing"), quick_planner(), noisy), steps=2)
    truth = setup.plant.state.object_pose.clone()
    first = setup.plant.measure()
    assert not torch.equal(first.object_pose, truth)
    assert torch.equal(setup.plant.state.object_pose, truth)
    assert float((first.object_pose - truth)[0, :3].norm()) < 0.02
    setup.plant.reset()
    again = dragged(setup, steps=2).plant.measure()
    assert torch.equal(first.object_pose, again.object_pose) and torch.equal(first.deformation, again.deformation)


@pytest.mark.parametrize("name", ["pushing", "in_hand"])
def test_planner_and_plant_share_no_tensors(name):
    setup = prepare(make_task(name), quick_planner(), PlantSettings(spacing_factor=1.0, substep_factor=1))
    estimate = estimate_state(setup, setup.plant.measure())
    planner = [setup.planner_model.points, setup.planner_model.normals, setup.planner_model.areas, *estimate[:3]]
    plant = [setup.plant.model.points, setup.plant.model.normals, setup.plant.model.areas, *setup.plant.state[:3]]
    storage = {t.untyped_storage().data_ptr() for t in plant}
    assert not storage & {t.untyped_storage().data_ptr() for t in planner}
