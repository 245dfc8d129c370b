"""The closed-loop state estimate: what the simulated sensors observe, the estimator, noise, no shared state."""

from __future__ import annotations

import pytest
import torch
from conftest import quick_planner

from hydrosoft.tasks import make_task
from hydrosoft.tasks.evaluation import PlantSettings, observed_state, prepare

F64 = torch.float64


def dragged(setup, steps: int = 4):
    """Drag the bubble 2 mm per step along x so the contact carries shear as well as pressure."""
    u = torch.zeros(setup.plant.model.n_bodies, 6, dtype=F64)
    u[setup.plant.model.body_names.index("bubble"), 0] = 0.002
    for _ in range(steps):
        assert setup.plant.apply(u)
    return setup


def observe(setup):
    return setup.plant.observe(setup.planner_model.points, setup.body_index, setup.sensors)


def test_the_estimate_does_not_read_the_plants_force_state():
    """Changing the plant's table forces or its shear history changes nothing the sensors report."""
    setup = dragged(prepare(make_task("pushing"), quick_planner(), PlantSettings()))
    before, estimate = observe(setup), observed_state(setup)
    assert float(before.penetration.max()) > 1e-3
    plant = setup.plant.state
    setup.plant.state = plant._replace(forces=torch.randn_like(plant.forces))
    after, again = observe(setup), observed_state(setup)
    for a, b in zip(before, after):
        assert torch.equal(a, b)
    for a, b in zip(estimate[:3], again[:3]):
        assert torch.equal(a, b)


def test_the_observation_follows_the_true_poses():
    setup = dragged(prepare(make_task("pushing"), quick_planner(), PlantSettings()))
    seen = observe(setup)
    assert torch.equal(seen.object_pose, setup.plant.state.object_pose)
    assert torch.equal(seen.body_poses, setup.plant.state.body_poses[:, setup.body_index])
    assert seen.penetration.shape == (1, 1, setup.planner_model.n_points)


def test_noisy_sensors_are_seeded_and_leave_the_plant_alone():
    noisy = PlantSettings(pose_noise_m=0.002, pose_noise_rad=0.02, deformation_noise_m=1e-4, seed=7)
    setup = dragged(prepare(make_task("pushing"), quick_planner(), noisy), steps=2)
    truth = setup.plant.state.object_pose.clone()
    first = observe(setup)
    assert not torch.equal(first.object_pose, truth)
    assert torch.equal(setup.plant.state.object_pose, truth)
    assert float((first.object_pose - truth)[0, :3].norm()) < 0.02
    assert float(first.penetration.min()) >= 0.0
    setup.plant.reset()
    again = observe(dragged(setup, steps=2))
    assert torch.equal(first.object_pose, again.object_pose) and torch.equal(first.penetration, again.penetration)


@pytest.mark.parametrize("name", ["pushing", "in_hand"])
def test_planner_and_plant_share_no_tensors(name):
    setup = prepare(make_task(name), quick_planner(), PlantSettings.same_as_planner())
    estimate = observed_state(setup)
    planner = [setup.planner_model.points, setup.planner_model.normals, setup.planner_model.areas, *estimate[:3]]
    plant = [setup.plant.model.points, setup.plant.model.normals, setup.plant.model.areas, *setup.plant.state[:3]]
    storage = {t.untyped_storage().data_ptr() for t in plant}
    assert not storage & {t.untyped_storage().data_ptr() for t in planner}
