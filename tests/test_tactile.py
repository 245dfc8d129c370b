"""The tactile observation and state estimator (eq. 22-24): geometry in, the planner's state out."""

import msgspec
import torch

from hydrosoft.contact.cone import split_normal
from hydrosoft.dynamics import step
from hydrosoft.geometry import se3
from hydrosoft.scene import compile_scene
from hydrosoft.tactile import (
    TactileObservation,
    carry_over,
    estimate_state,
    forces_from_deformation,
    observe_geometry,
    sensor_bodies,
)
from hydrosoft.tasks.scenes import task_scene


def sheared_pushing_state(spacing=0.005):
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


def test_membrane_cannot_pull():
    model, state = sheared_pushing_state()
    n = normals(model, state)
    f = forces_from_deformation(-0.001 * n.expand_as(state.forces), n, model.areas, model.material)
    assert torch.count_nonzero(f) == 0


def test_the_sensor_bodies_are_the_actuated_bubbles():
    model, _ = sheared_pushing_state()
    assert [model.body_names[int(m)] for m in sensor_bodies(model)] == ["bubble"]


def test_estimated_normal_forces_are_E_A_times_the_observed_depth():
    """Normal forces come from the measured depth alone: eq. 24's normal part, E A d, at every point."""
    model, state = sheared_pushing_state()
    sensors = sensor_bodies(model)
    depth = observe_geometry(model, state.object_pose, state.body_poses, sensors)
    estimate = estimate_state(model, TactileObservation(state.object_pose, state.body_poses, depth), sensors, state)
    f_n, _ = split_normal(estimate.forces[:, sensors], normals(model, state))
    expected = model.material.E[sensors].view(1, -1, 1) * model.areas * depth
    assert torch.allclose(f_n, expected, rtol=0, atol=1e-12)
    assert float(depth.max()) > 1e-3  # the bubble is pressed in


def test_shear_and_the_table_carry_over_from_the_prediction_within_the_cone():
    model, state = sheared_pushing_state()
    sensors = sensor_bodies(model)
    depth = observe_geometry(model, state.object_pose, state.body_poses, sensors)
    observed = TactileObservation(state.object_pose, state.body_poses, depth)
    estimate = estimate_state(model, observed, sensors, state)
    table = model.body_names.index("table")
    assert torch.equal(estimate.forces[:, table], state.forces[:, table])
    f_n, f_t = split_normal(estimate.forces[:, sensors], normals(model, state))
    assert bool((f_t.norm(dim=-1) <= model.material.mu[sensors].view(1, -1, 1) * f_n + 1e-12).all())
    _, predicted_t = split_normal(state.forces[:, sensors], normals(model, state))
    assert float(f_t.sum((0, 1, 2))[0]) > 0.5 * float(predicted_t.sum((0, 1, 2))[0]) > 0.05
    lifted = observed._replace(penetration=torch.zeros_like(depth))
    assert torch.count_nonzero(estimate_state(model, lifted, sensors, state).forces[:, sensors]) == 0


def test_without_a_prediction_the_table_holds_the_press_in_forces_and_there_is_no_shear():
    model, state = sheared_pushing_state()
    sensors = sensor_bodies(model)
    depth = observe_geometry(model, state.object_pose, state.body_poses, sensors)
    estimate = estimate_state(model, TactileObservation(state.object_pose, state.body_poses, depth), sensors)
    _, f_t = split_normal(estimate.forces[:, sensors], normals(model, state))
    assert float(f_t.norm(dim=-1).max()) == 0.0
    table = model.body_names.index("table")
    weight = model.mass * 9.81
    assert float(estimate.forces[:, table, :, 2].sum()) > weight


def test_the_carry_over_is_the_predicted_state_after_the_steps_sent():
    """``carry_over`` takes the state after ``steps`` of the plan's predicted states (the last when the plan is
    shorter), detached and without cached distances; no states (no plan) carry nothing."""
    model, state = sheared_pushing_state()
    u = torch.zeros(1, model.n_bodies, 6, dtype=model.dtype)
    u[0, model.body_names.index("bubble"), 0] = 0.001
    leaf = u.clone().requires_grad_(True)
    states = []
    for _ in range(3):
        state = step(model, state, leaf)
        states.append(state)
    carried = carry_over(states, 2)
    assert carried.phi is None and not carried.forces.requires_grad
    assert all(torch.equal(got, want) for got, want in zip(carried[:3], states[1][:3]))
    assert torch.equal(carry_over(states, 9).object_pose, states[-1].object_pose)
    assert carry_over([], 1) is None
