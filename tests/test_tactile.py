"""Tactile force estimation (eq. 22-24) and the simulated sensor path plant -> deformation -> planner."""

import msgspec
import torch

from hydrosoft.dynamics import step
from hydrosoft.geometry import se3
from hydrosoft.scene import compile_scene
from hydrosoft.tactile import deformation_from_forces, forces_from_deformation, nearest_indices, resample
from hydrosoft.tasks.scenes import task_scene


def sheared_pushing_state(spacing):
    scene = task_scene("pushing")
    scene = msgspec.structs.replace(scene, object=msgspec.structs.replace(scene.object, spacing=spacing))
    model, state, _ = compile_scene(scene, prune=False)
    u = torch.zeros(1, model.n_bodies, 6, dtype=model.dtype)
    u[0, model.body_names.index("bubble"), 0] = 0.001
    for _ in range(4):
        state = step(model, state, u)
    return model, state


def normals(model, state):
    return -se3.rotate_vectors(state.object_pose, model.normals).unsqueeze(1)


def test_eq24_inverts_the_deformation_of_nh_forces():
    model, state = sheared_pushing_state(0.005)
    n = normals(model, state)
    d = deformation_from_forces(state.forces, n, model.areas, model.material)
    assert torch.allclose(forces_from_deformation(d, n, model.areas, model.material), state.forces, atol=1e-12)


def test_membrane_cannot_pull():
    model, state = sheared_pushing_state(0.005)
    n = normals(model, state)
    f = forces_from_deformation(-0.001 * n.expand_as(state.forces), n, model.areas, model.material)
    assert torch.count_nonzero(f) == 0


def test_fine_plant_observed_on_coarse_points_keeps_the_net_force():
    """Stated tolerance: the net force seen through the sensor is within 10% of the plant's (spacing 2x)."""
    plant, plant_state = sheared_pushing_state(0.0025)
    planner, planner_state = sheared_pushing_state(0.005)
    d = deformation_from_forces(plant_state.forces, normals(plant, plant_state), plant.areas, plant.material)
    index = nearest_indices(plant.points, planner.points)
    observed = forces_from_deformation(resample(d, index), normals(planner, planner_state), planner.areas,
                                       planner.material)
    net_plant = plant_state.forces.sum((0, 2))
    net_observed = observed.sum((0, 2))
    assert torch.allclose(net_observed, net_plant, rtol=0, atol=0.1 * net_plant.norm(dim=-1).max())
