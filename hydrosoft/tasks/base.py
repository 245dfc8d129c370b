"""What a manipulation task is: a scene, the actuated body DOFs and their per-step bounds, a seeded goal sampler,
the MPC costs for a goal and a success criterion (paper V-D).

Errors are measured in one unit for every task (paper Table III reports mm everywhere): the ADD, the mean
distance (m) between the object's surface points at a pose and at the goal pose, which covers position and
orientation at once. The MPC cost uses the same quantity squared (the mean squared point distance), so the
planner optimizes what the evaluation measures.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from typing import Callable, NamedTuple

import torch
from torch import Tensor

from hydrosoft.compilation import CompiledFunction
from hydrosoft.control.costs import hinge_cost, orientation_error, position_error
from hydrosoft.dynamics import Model, State
from hydrosoft.geometry import se3
from hydrosoft.geometry.se3 import safe_norm
from hydrosoft.scene import Scene

EPISODE_MARGIN = 2.0  # episode length over the fewest steps a goal needs (Task.episode_steps)

GoalSampler = Callable[[Tensor, torch.Generator], Tensor]
"""``(initial object pose (7,) float64, generator) -> goal pose (7,) float64``."""


def rotated_goal(start: Tensor, generator: torch.Generator, axis: int, degrees: tuple[float, float]) -> Tensor:
    """Goal ``(7,)``: ``start (7,)`` rotated about world axis ``axis`` (0 x, 1 y, 2 z) through its own centre by
    an angle drawn uniformly from ``degrees = (low, high)`` with a random sign."""
    magnitude, sign = torch.rand(2, generator=generator, dtype=torch.float64)
    angle = math.radians(degrees[0]) + math.radians(degrees[1] - degrees[0]) * magnitude
    delta = torch.zeros(6, dtype=torch.float64)
    delta[3 + axis] = torch.where(sign < 0.5, -angle, angle)
    return se3.retract(start, delta)


def mean_point_distance(points: Tensor, pose: Tensor, goal: Tensor) -> Tensor:
    """ADD: mean distance (m) between object-frame ``points (N, 3)`` placed at ``pose (..., 7)`` and at ``goal``.

    ``goal`` is ``(7,)`` or broadcasts against ``pose``; returns ``(...)``.
    """
    diff = se3.transform_points(pose, points) - se3.transform_points(goal, points)
    return diff.norm(dim=-1).mean(-1)


class PointTracking(NamedTuple):
    """The mean squared distance (m^2) between an object's points at a pose and at a fixed goal pose, as a few
    products with constants: the MPC's tracking term, smooth everywhere (no square root).

    Exact in closed form from the points' first and second moments ``mu = mean p``, ``S = mean p p^T``, in the goal's
    frame. With ``r = (w, v)`` the rotation from the goal's to the pose's (unit), ``d`` the position offset seen in
    the goal's frame and ``e = R_r mu - mu = w t + v x t``, ``t = 2 v x mu``, the mean of ``|R_r p - p + d|^2`` is
    ``4 v^T (tr S I - S) v + 2 d . e + |d|^2``. Every term is small where the pose is near the goal, so float32
    keeps its relative precision there (a form that subtracts ``2 <R, R_g S>`` from ``2 tr S`` lost all of it
    within tens of micrometres, and the clamp at zero then zeroed the gradient). ``r = L q / |q|``, with ``L`` the
    constant ``4 x 4`` product by the goal's inverse: a call is about 25 small operations whatever the point
    count (eager, the planner calls it once per rollout step).

    Build it with ``PointTracking.of(points (N, 3), goal (7,))``; ``tracking(pose (..., 7)) -> (...)``. Quaternions
    need not be unit, and ``q`` and ``-q`` give the same value: the term is that of the rotation they represent.
    A named tuple of tensors, so that compiled cost terms take it as an input (a new goal reuses their graphs).
    """

    inertia: Tensor  # (3, 3) m^2: tr S I - S, the quadratic form of the rotation's part
    centroid: Tensor  # (3,) m: mu, object frame
    to_goal: Tensor  # (4, 4): L^T, so that q @ to_goal = conj(q_g) q
    goal_rotation: Tensor  # (3, 3): R_g, so that (t - t_g) @ R_g is the offset in the goal's frame
    goal_position: Tensor  # (3,) m: t_g

    @classmethod
    def of(cls, points: Tensor, goal: Tensor) -> PointTracking:
        """The term for object-frame ``points (N, 3)`` (m) and ``goal (7,)``, in their dtype."""
        second = points.mT @ points / points.shape[0]
        inertia = second.diagonal().sum() * torch.eye(3, dtype=second.dtype, device=second.device) - second
        inverse = se3.quat_conjugate(se3.quat_normalize(goal[3:]))
        basis = torch.eye(4, dtype=goal.dtype, device=goal.device)
        return cls(inertia, points.mean(0), se3.quat_multiply(inverse.expand(4, 4), basis),
                   se3.quat_to_matrix(goal[3:]), goal[:3])

    def __call__(self, pose: Tensor) -> Tensor:
        q = pose[..., 3:]
        r = (q @ self.to_goal) * (q * q).sum(-1, keepdim=True).rsqrt()
        w, v = r[..., :1], r[..., 1:]
        t = 2 * torch.linalg.cross(v, self.centroid.expand_as(v))
        e = w * t + torch.linalg.cross(v, t)
        d = (pose[..., :3] - self.goal_position) @ self.goal_rotation
        return (4 * ((v @ self.inertia) * v).sum(-1) + (d * (2 * e + d)).sum(-1)).clamp_min(0.0)


def mean_squared_point_distance(points: Tensor, pose: Tensor, goal: Tensor) -> Tensor:
    """Mean squared distance (m^2) between ``points (N, 3)`` at ``pose (B, 7)`` and at ``goal (7,)``: ``(B,)``
    (``PointTracking``, built for one call)."""
    return PointTracking.of(points, goal)(pose)


@dataclass(frozen=True)
class CostWeights:
    """Weights of the MPC cost (eq. 21); lengths in m.

    The tracking terms are ``mean squared point distance / scale^2`` (so 1 = ``scale`` of ADD): ``stage`` per
    step and ``terminal`` at the horizon's end. ``effort`` weighs ``sum((u / bound)^2)`` per step (actions
    normalized by their per-step bounds). ``drift`` weighs a hinge on how far each actuated body has slipped
    over the object since the anchor state (``Task.costs``), beyond ``drift_limit`` m (it keeps the bubble on
    the object), with a smoothing width of ``drift_width`` m.
    """

    scale: float = 0.01
    stage: float = 0.1
    terminal: float = 1.0
    effort: float = 1e-3
    drift: float = 1e4
    drift_limit: float = 0.015
    drift_width: float = 0.002


def plan_anchor(state: State, actuated: tuple[int, ...]) -> tuple[Tensor, Tensor]:
    """The drift's anchor at a plan's first state (batch ``B``): the object's position ``(B, 1, 1, 3)`` and the
    ``actuated`` bodies' offsets from it ``(B, 1, M', 3)`` (m), detached (``Task.costs``)."""
    origin = state.object_pose[:, None, None, :3].detach()
    return origin, (state.body_poses[:, None, list(actuated), :3].detach() - origin)


def slip(object_poses: Tensor, body_poses: Tensor, anchor: tuple[Tensor, Tensor], actuated: tuple[int, ...],
         rolling: float) -> Tensor:
    """Slip ``(B, K, M')`` (m) of the ``actuated`` bodies at ``object_poses (B, K, 7)`` and ``body_poses (B, K, M,
    7)`` since ``anchor = (origin, offsets)`` (broadcast against ``(B, K, 1, 3)`` and ``(B, K, M', 3)``): the change
    of each body's offset from the object's centre less ``rolling`` times the object's displacement."""
    origin, offset0 = anchor
    moved = object_poses[:, :, None, :3] - origin
    offset = body_poses[:, :, list(actuated), :3] - object_poses[:, :, None, :3]
    return safe_norm(offset - offset0 - rolling * moved)


def stage_terms(object_poses: Tensor, body_poses: Tensor, u: Tensor, tracking: PointTracking,
                anchor: tuple[Tensor, Tensor], scale: Tensor, actuated: tuple[int, ...], weights: CostWeights,
                rolling: float) -> Tensor:
    """A rollout's summed stage costs ``(B,)`` (``Task.costs``): tracking, effort and drift over its ``K`` steps.

    ``object_poses (B, K, 7)``, ``body_poses (B, K, M, 7)``, ``u (B, K, M, 6)``; ``scale (M, 6)`` the per-step
    action bounds that normalise the effort; ``actuated`` the indices of the bodies that move; ``rolling`` the
    drift's share of the object's displacement (``slip``)."""
    track = tracking(object_poses).sum(1) / weights.scale**2
    effort = (u[:, :, list(actuated)] / scale[list(actuated)]).square().flatten(1).sum(-1)
    drift = hinge_cost(slip(object_poses, body_poses, anchor, actuated, rolling), weights.drift_limit, weights.drift,
                       width=weights.drift_width)
    return weights.stage * track + weights.effort * effort + drift


def terminal_terms(object_pose: Tensor, body_poses: Tensor, tracking: PointTracking, anchor: tuple[Tensor, Tensor],
                   actuated: tuple[int, ...], weights: CostWeights, rolling: float) -> Tensor:
    """The terminal cost ``(B,)`` at ``object_pose (B, 7)`` and ``body_poses (B, M, 7)``: tracking and drift
    (``stage_terms``)."""
    track = tracking(object_pose) / weights.scale**2
    drift = slip(object_pose.unsqueeze(1), body_poses.unsqueeze(1), anchor, actuated, rolling)
    return weights.terminal * track + hinge_cost(drift, weights.drift_limit, weights.drift, width=weights.drift_width)


class CostTerms(NamedTuple):
    """The functions that evaluate ``Task.costs``' arithmetic: ``EAGER_COST_TERMS``, or ``compiled_cost_terms()``."""

    stage: Callable[..., Tensor]  # stage_terms
    terminal: Callable[..., Tensor]  # terminal_terms


EAGER_COST_TERMS = CostTerms(stage_terms, terminal_terms)


def compiled_cost_terms(activation_memory_budget: float = 0.0, workers: int = 1,
                        device: torch.device | str = "cpu", **options) -> CostTerms:
    """``stage_terms`` and ``terminal_terms`` compiled (``compilation.CompiledFunction``; ``options`` go to
    ``torch.compile``; ``workers``: the solver's, ``CompiledCopies``; ``device``: where the planner's tensors are),
    for the planner to keep across goals.

    Eager, the costs were dozens of small operations per rollout, forward and backward, each paying the interpreter
    and, with two solver workers, waiting for it. Compiled, a call of both took 0.49 of the eager time forward and
    backward, and the two-worker planning cycle 0.95 (docs/decisions.md, "the task costs"). The second rollout length
    compiles once more, and with dynamo's default ``dynamic=None`` that graph is symbolic in the length and serves
    all others (open-loop plans of each episode's length)."""
    return CostTerms(CompiledFunction(stage_terms, activation_memory_budget, workers, device, **options),
                     CompiledFunction(terminal_terms, activation_memory_budget, workers, device, **options))


@dataclass(frozen=True)
class Task:
    """One manipulation task of paper V-D.

    name: task name. scene: its scene (see ``hydrosoft.tasks.scenes``). step_limits: per actuated body name,
    the largest per-step increment of each of its 6 DOFs ``(dx, dy, dz (m), rx, ry, rz (rad))``: the action
    bounds are ``-limit <= u <= limit`` (a zero limit fixes that DOF; bodies not listed are not actuated).
    goal_sampler: the seeded goal distribution (stated in each task module). steps: control steps per episode.
    success_mm: an episode succeeds when its final ADD is at most this. weights: MPC cost weights.
    travel_ratio: the most the object translates per metre of body translation (1 when it can be dragged
    along; 1/2 for rolling without slip, where the contact on top moves twice as fast as the centre).
    drift_from_scene: the drift hinge measures each actuated body's offset from the object in the table's plane
    (x, y) against the scene's resting offset (``scene_offsets``: the bubble centred on the cube) instead of the
    offset the goal started at (``Task.costs``); its height stays the goal start's. For dragging, where the offset
    a push leaves is membrane shear that the next push in the other direction must first undo.
    """

    name: str
    scene: Scene
    step_limits: dict[str, tuple[float, float, float, float, float, float]]
    goal_sampler: GoalSampler
    steps: int
    success_mm: float = 5.0
    weights: CostWeights = CostWeights()
    travel_ratio: float = 1.0
    drift_from_scene: bool = False

    def initial_pose(self) -> Tensor:
        """The object's initial pose ``(7,)`` (float64) from the scene."""
        return torch.tensor(self.scene.object.pose, dtype=torch.float64)

    def sample_goal(self, seed: int) -> Tensor:
        """The goal pose ``(7,)`` (float64) of goal number ``seed``: deterministic per seed."""
        generator = torch.Generator().manual_seed(seed)
        return self.goal_sampler(self.initial_pose(), generator)

    def bounds(self, body_names: tuple[str, ...], dtype: torch.dtype = torch.float64) -> tuple[Tensor, Tensor]:
        """Per-step action bounds ``(low, high)``, each ``(M, 6)``, for the bodies ``body_names`` in that order."""
        limits = [self.step_limits.get(name, (0.0,) * 6) for name in body_names]
        high = torch.tensor(limits, dtype=dtype)
        return -high, high

    def max_travel(self) -> tuple[float, float]:
        """Largest object motion per step the actions could cause: ``(m, rad)``.

        The object moves no faster than the bodies drag it: translation up to the largest body translation
        bound times ``travel_ratio``; rotation up to the largest body rotation bound plus that translation over
        the object's smallest half-extent (rolling). An upper bound, used to tell reachable goals from
        unreachable ones and to size episodes.
        """
        trans = self.travel_ratio * max((math.hypot(*lim[:3]) for lim in self.step_limits.values()), default=0.0)
        rot = max((math.hypot(*lim[3:]) for lim in self.step_limits.values()), default=0.0)
        return trans, rot + trans / self.object_radius()

    def object_radius(self) -> float:
        """The object's smallest half-extent (m), from its shape parameters."""
        params = self.scene.object.params
        sizes = [v / 2 for k, v in params.items() if k in ("side", "length", "width", "height")]
        sizes += [v for k, v in params.items() if k == "radius"]
        return min(sizes) if sizes else 0.01

    def min_steps(self, start: Tensor, goal: Tensor) -> int:
        """The fewest control steps in which ``goal (7,)`` could be reached from ``start (7,)`` (``max_travel``)."""
        trans, rot = self.max_travel()
        distance = float(position_error(start, goal))
        angle = float(orientation_error(start, goal))
        need = max(distance / trans if trans > 0 else math.inf * (distance > 1e-9),
                   angle / rot if rot > 0 else math.inf * (angle > 1e-9), 0.0)
        return math.ceil(need - 1e-9) if math.isfinite(need) else 2**31

    def episode_steps(self, goal: Tensor) -> int:
        """Control steps of an episode towards ``goal (7,)``: the task's ``steps``, or ``EPISODE_MARGIN`` times the
        fewest steps the goal needs when that is more, so that every sampled goal is reachable within its
        episode with room to correct."""
        return max(self.steps, math.ceil(EPISODE_MARGIN * self.min_steps(self.initial_pose(), goal)))

    def reachable(self, start: Tensor, goal: Tensor, steps: int) -> bool:
        """Whether the goal ``(7,)`` is within reach of ``start (7,)`` in ``steps`` steps (``max_travel`` bound)."""
        trans, rot = self.max_travel()
        distance = float(position_error(start, goal))
        angle = float(orientation_error(start, goal))
        return distance <= steps * trans + 1e-9 and angle <= steps * rot + 1e-9

    def scene_offsets(self, body_names: tuple[str, ...]) -> Tensor:
        """Each body's position relative to the object's ``(M, 3)`` (m, float64) in the scene as loaded (bodies
        ``body_names``, in that order): where the bodies rest on the object before any action."""
        poses = {body.name: body.pose for body in self.scene.bodies}
        centre = torch.tensor(self.scene.object.pose[:3], dtype=torch.float64)
        return torch.tensor([poses[name][:3] for name in body_names], dtype=torch.float64) - centre

    def costs(self, model: Model, goal: Tensor, anchor: tuple[Tensor, Tensor] | None = None,
              terms: CostTerms = EAGER_COST_TERMS) -> tuple[Callable, Callable]:
        """``(stage_cost(states, u) -> (B,), terminal_cost(state) -> (B,))`` for ``goal (7,)`` on ``model``, as
        ``control.CemGd`` calls them: ``stage_cost`` sums the stage costs of a rollout's ``K`` states
        ``x_0 .. x_{K-1}`` (a list of ``State``, batch ``B``) under ``u (B, K, M, 6)``, all steps in one batch of
        operations.

        The drift hinge bounds how far each actuated body slips over the object from the anchor state: the change of
        its offset from the object's centre (m), less the ``(1 / travel_ratio - 1)`` times the object's displacement
        that rolling without slip adds (zero for dragging; the object's displacement itself for rolling, where the
        contact on top moves twice as fast as the centre). ``anchor`` is ``(object_pose (7,), body_poses (M, 7))``:
        the state a goal started from, so that slip stays bounded over a whole episode of replans (each plan of a
        closed loop would otherwise allow ``drift_limit`` more, and the bubble walked off the cube). With
        ``drift_from_scene`` an anchor's offsets' x and y are the scene's resting ones (``scene_offsets``), their
        height the anchor's (the arm holds it; a TCP calibrated a few mm off would otherwise count): a push leaves
        the bubble up to 9 mm ahead of the cube (the membrane's shear), and a push back, which must shear it as far
        the other way, measured from there reached the 15 mm limit and stalled 3 mm short of its goal
        (docs/benchmarks.md, "A goal near its tolerance"). Without an anchor, the anchor is each plan's first state
        ``x_0`` with its own offsets, which ``stage_cost`` sees; it is kept per thread for the ``terminal_cost``
        call that follows (solver workers roll out their shares of the rows on threads of their own).

        ``terms`` evaluates the costs' tensor arithmetic: eager, or compiled (``compiled_cost_terms``, kept by a
        planner for all its goals: the goal and the anchor are inputs of its graphs, not constants).
        """
        goal = goal.to(model.device, model.dtype)
        tracking = PointTracking.of(model.points, goal)
        scale = self.bounds(model.body_names, model.dtype)[1].to(model.device).clamp_min(torch.finfo(model.dtype).eps)
        actuated = tuple(i for i, moves in enumerate((scale > 10 * torch.finfo(model.dtype).eps).any(-1).tolist())
                         if moves)
        constants = (actuated, self.weights, 1.0 / self.travel_ratio - 1.0)
        fixed: tuple[Tensor, Tensor] | None = None
        if anchor is not None:
            origin = anchor[0].to(model.device, model.dtype)[:3]
            offsets = anchor[1].to(model.device, model.dtype)[list(actuated), :3] - origin
            if self.drift_from_scene:  # x and y from the scene's resting offset, the height the goal started at
                resting = self.scene_offsets(tuple(model.body_names[i] for i in actuated))
                offsets = torch.cat([resting[:, :2].to(model.device, model.dtype), offsets[:, 2:]], -1)
            fixed = (origin, offsets)
        first = threading.local()

        def stage_cost(states: list[State], u: Tensor) -> Tensor:
            first.anchor = fixed if fixed is not None else plan_anchor(states[0], actuated)
            object_poses = torch.stack([state.object_pose for state in states], 1)
            body_poses = torch.stack([state.body_poses for state in states], 1)
            return terms.stage(object_poses, body_poses, u, tracking, first.anchor, scale, *constants)

        def terminal_cost(state: State) -> Tensor:
            anchor = fixed if fixed is not None else first.anchor
            return terms.terminal(state.object_pose, state.body_poses, tracking, anchor, *constants)

        return stage_cost, terminal_cost
