"""What a Soft Bubble observes, and the state estimator that turns it into the planner's state (paper V-A).

A Soft Bubble's depth camera sees its membrane. Where the object presses in, the membrane is displaced to the
object's surface; with the object pose (AprilTags) and the bubble pose (the arm), that displacement is known per
object surface point as a depth: how far the point lies inside the nominal, undeformed membrane
(``TactileObservation.penetration``). The camera sees the membrane's shape, not its shear, and nothing sees the
table's contact. So the observation holds poses and per-point normal deformations only, never a force state.

``estimate_state`` builds the planner's state from such an observation and the planner's own previous
prediction (the state its model predicted for this instant):

- normal forces of each sensor body from the measured deformation, ``f_n = E A d`` along the object's inward
  normal (eq. 22-24 with ``d_n = d``: the linear membrane model);
- their tangential forces carried over from the prediction (re-split against the current normal, co-rotated with
  the body's rotation since the prediction) and projected onto the friction cone of the measured normal force, so a
  point the sensor sees out of contact carries no force;
- the forces of bodies that are not sensors (the table) carried over from the prediction, or, with no prediction
  yet, those of pressing the bodies straight into their poses (``dynamics.press_in``).

Assumptions: the sensed poses are exact; the membrane's normal deformation is the object point's depth inside
the nominal membrane; shear history is dead-reckoned by the model, never measured.

``observe_geometry`` is the observation a perfect depth camera would give at known poses (the simulated sensor of
the offline evaluation); the service stack computes the same quantity from rendered or real depth images.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from hydrosoft.contact import Material
from hydrosoft.contact.cone import project_to_cone, split_normal
from hydrosoft.dynamics import Model, State, press_in
from hydrosoft.geometry import se3


class TactileObservation(NamedTuple):
    """One observation of the sensors, batch ``B``.

    object_pose: ``(B, 7)`` the object's pose from the tags (m, wxyz), world frame.
    body_poses: ``(B, M, 7)`` every body of the model at its sensed pose (the arm's TCP poses for the bubbles, the
        fixed poses of unactuated bodies), in the model's body order.
    penetration: ``(B, S, N)`` for sensor ``s`` (model body ``sensors[s]``), how deep (m, >= 0) each of the model's
        ``N`` surface points lies inside that sensor's nominal membrane, as measured; 0 out of contact.
    """

    object_pose: Tensor
    body_poses: Tensor
    penetration: Tensor


def forces_from_deformation(deformation: Tensor, normal: Tensor, area: Tensor, material: Material) -> Tensor:
    """Eq. 22-24: forces ``(B, M, N, 3)`` (N) from deformations ``(B, M, N, 3)`` (m).

    normal: ``(B, 1 or M, N, 3)`` unit inward object normals, world frame; area ``(N,)`` m^2; material per body.
    ``f = E A d_n n + K A d_t``; the normal part is clipped at zero: a membrane cannot pull.
    """
    d_n, d_t = split_normal(deformation, normal)
    E = material.E.view(1, -1, 1)
    K = material.K.view(1, -1, 1)
    f_n = E * area * torch.relu(d_n)
    return f_n.unsqueeze(-1) * normal + (K * area).unsqueeze(-1) * d_t


def membrane_penetration(membranes, points: Tensor, object_pose: Tensor, membrane_poses: Tensor) -> Tensor:
    """What a perfect depth camera measures: the depth ``(B, S, N)`` (m, >= 0) of object-frame ``points (N, 3)``
    inside each nominal membrane (``membranes``: ``S`` signed distance functions), the object at ``object_pose
    (B, 7)`` and the membranes at ``membrane_poses (B, S, 7)``. Geometry only: no force state enters."""
    world = se3.transform_points(object_pose, points.to(object_pose.dtype)).unsqueeze(1)
    local = se3.transform_points(se3.inverse(membrane_poses), world.expand(-1, membrane_poses.shape[1], -1, -1))
    return torch.relu(-torch.stack([sdf(local[:, j]) for j, sdf in enumerate(membranes)], dim=1))


def observe_geometry(model: Model, object_pose: Tensor, body_poses: Tensor, sensors: Tensor) -> Tensor:
    """``membrane_penetration`` of the model's own surface points in its sensor bodies ``sensors (S,)``, the object
    at ``object_pose (B, 7)`` and the bodies at ``body_poses (B, M, 7)``: ``(B, S, N)`` m."""
    return membrane_penetration([model.bodies[int(m)] for m in sensors], model.points, object_pose,
                                body_poses[:, sensors])


def estimate_state(model: Model, observation: TactileObservation, sensors: Tensor,
                   previous: State | None = None) -> State:
    """The planner's state ``(B, ...)`` from ``observation`` and the planner's prediction ``previous`` (or None).

    ``sensors (S,)``: the body indices whose membranes are observed (``observation.penetration``'s order). See
    the module docstring for what comes from where. Differentiable; the result does not cache signed distances.
    """
    pose, body_poses = observation.object_pose, observation.body_poses
    if previous is None:
        previous = press_in(model, pose, body_poses)
        previous = previous._replace(forces=previous.forces.index_fill(1, sensors, 0.0))
    turn = se3.quat_to_matrix(body_poses[..., 3:]) @ se3.quat_to_matrix(previous.body_poses[..., 3:]).mT
    carried = previous.forces @ turn.mT
    normal = -se3.rotate_vectors(pose, model.normals).unsqueeze(1)
    material = Material(*(t[sensors] for t in model.material))
    f_n = material.E.view(1, -1, 1) * model.areas * observation.penetration
    _, f_t = split_normal(carried[:, sensors], normal)
    f_n, f_t = project_to_cone(f_n, f_t, material.mu.view(1, -1, 1))
    sensed = f_n.unsqueeze(-1) * normal + f_t
    forces = carried.index_copy(1, sensors, sensed)
    return State(object_pose=pose, body_poses=body_poses, forces=forces)


def carry_over(states: list[State], steps: int) -> State | None:
    """The prediction to carry into the next ``estimate_state``: the planner's predicted state after ``steps`` of its
    plan's actions, from ``states`` ``x_1 .. x_K`` along the plan (``PlanResult.states``; the last when the plan is
    shorter), detached and without its cached distances. None when there are no states (no plan was found)."""
    if not states:
        return None
    return State(*(t.detach() for t in states[min(steps, len(states)) - 1][:3]))


def sensor_bodies(model: Model) -> Tensor:
    """Indices ``(S,)`` of the model's sensor bodies: the actuated ones (the Soft Bubbles on the arms)."""
    return model.actuated.nonzero().squeeze(-1)


__all__ = ["TactileObservation", "carry_over", "estimate_state", "forces_from_deformation", "membrane_penetration",
           "observe_geometry", "sensor_bodies"]
