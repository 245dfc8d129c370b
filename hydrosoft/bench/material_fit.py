"""The Soft Bubble's material (E, K, mu) identified from ``collect wrench`` recordings: pure functions behind
``hydrosoft-stack fit``.

Each trajectory is replayed through the contact model at its recorded poses (``wrench_replay.replay_tcp_wrenches``,
as ``bench wrench`` does), and the material that minimises the wrench error is found by L-BFGS (``torch.optim``)
over unconstrained coordinates ``theta = (log(E / E_start), log(K / K_start), logit(mu / MU_MAX))``: E and K stay
positive and mu stays in ``(0, MU_MAX)``. Parameters not asked for are held at their start values.

Residuals. Per trajectory, step ``k = 1..K`` and wrench component ``c``: ``(predicted - measured) / FT300_NOISE[c]``
(force in N, torque in N m), so forces and torques weigh by the sensor's noise. Every measured row is the recorded
wrench minus the one tare sample, so the tare's noise is shared by all rows of a trajectory: their noise covariance
per component is ``s^2 (I + 1 1^T)``. The residuals are whitened for it (``_whiten``), so the sum of their squares
is the likelihood's and the Gauss-Newton covariance below is the right one for that noise.

Uncertainty: Gauss-Newton at the optimum. ``J`` (residuals x fitted parameters) comes from forward-mode autograd
(one ``jvp`` per parameter); the covariance of theta is ``s2 (J^T J)^-1``, scaled by the reduced chi-square
``s2 = sum(r^2) / (n - p)`` (the noise level the residuals show, as ``scipy.optimize.curve_fit`` does by
default): model error on lab data then widens the intervals. A direction in which ``J^T J`` is singular (the data
do not change with it) has infinite variance. Reported per parameter: its standard deviation by the delta method
and a 95 % interval (``Z95`` standard deviations in theta, mapped back, so E and K's are multiplicative and mu's
stays inside its bounds). A parameter whose relative standard deviation exceeds ``UNIDENTIFIED_RELATIVE_SIGMA`` is
reported as unidentified: the recordings do not determine it (K from pure pressing on a flat face, for example,
where no point moves tangentially).

Pose offset (``fit_material`` with ``pose_offset="xyz"``, ``hydrosoft-stack fit --pose-offset``): a constant
position offset ``d`` (3 numbers, m, in the base frame) added to every recorded object pose, fitted jointly with the
material as a nuisance parameter; ``pose_offset="z"`` fits it along base z alone (the press normal of a horizontal
face), the other axes held at 0. A tracker that reports a still object a fraction of a millimetre too low biases E
by about 1 % per 0.07 mm (docs/fit.md); no noise term removes a constant offset, but fitting it does, and its
uncertainty then widens E's interval (E's marginal of the joint covariance). Its coordinates are ``d /
OFFSET_UNIT_M`` (mm, so the optimiser's steps are of E's scale), appended to theta, which is then ``(6,)``; a Gaussian
prior of ``POSE_OFFSET_PRIOR_M`` per axis (three more residuals, ``d / POSE_OFFSET_PRIOR_M``) keeps it within a few
mm and makes an offset the data do not determine (along a flat face that is only pressed) come out near 0 with
about the prior's spread instead of an infinite one. An axis counts as identified when its standard deviation is at
most ``UNIDENTIFIED_RELATIVE_SIGMA`` of the prior's (the data, not the prior, set it). The offset is fitted from
the material-only optimum (``_refit_with_offset``).

Replay resolution (``fit_material`` with ``substeps=None``): a replay too coarse for the recorded motion cuts
twists and slips short, a bias the covariance does not cover; the sub-steps double while a replay twice as fine
would move a fitted value by more than ``REPLAY_SHIFT_SIGMA`` standard deviations (``replay_shift``). Each doubling
takes that Gauss-Newton step, or refits by L-BFGS where the step would raise the cost (``_move_to_finer_replay``).

Not covered by the covariance: correlated model error (on lab data the residuals are not independent noise; a
bootstrap over trajectories would show it, at one fit per draw), the recorded poses' own errors, and mu's
non-Gaussian tails (the stick/slip switches make the residuals piecewise smooth in mu). Under the FT 300's noise the
95 % intervals held the truth in E 17, K 17, mu 17 of seeds 0-19 (``hydrosoft-stack bench fit``, docs/fit.md); the
parametric bootstrap (``fit_bootstrap``) agreed with them within 17 % in spread and coverage. The profile likelihood
(``fit_profile``) follows the stick/slip tails: over 110 seeds it held K and mu in 94 and 95 % (Gauss-Newton 92 and
93 %), their spread at the truth the noise's own (docs/fit.md).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from hydrosoft.bench.material_parameters import FIT_MODELS, MU_MAX, PARAMETERS
from hydrosoft.bench.wrench_replay import DEFAULT_SUBSTEPS, replay_tcp_wrenches, trajectory_errors
from hydrosoft.bench.wrench_scenes import BUBBLE_E, BUBBLE_K, BUBBLE_MU
from hydrosoft.contact import Material
from hydrosoft.drivers.robotiq_ft300.noise import SIGNAL_NOISE

START = {"E": BUBBLE_E, "K": BUBBLE_K, "mu": BUBBLE_MU}  # the scenes' Soft Bubble (hydrosoft/tasks/pushing.toml)
#: The FT 300's signal noise per frame (``noise.SIGNAL_NOISE``, the simulator's): the fit weighs each wrench
#: component by it; its absolute level cancels (see ``s2``).
FT300_NOISE = SIGNAL_NOISE
Z95 = 1.959964  # two-sided 95 % quantile of the standard normal
UNIDENTIFIED_RELATIVE_SIGMA = 0.25  # a parameter known only to +-25 % (1 sigma) or worse is not identified
SINGULAR_RCOND = 1e-10  # eigenvalues of J^T J below this fraction of the largest count as zero (no information)
DEFAULT_MAX_ITERATIONS = 60
#: A replay twice as fine moving a fitted value by more than this many of its standard deviations is too coarse:
#: its discretisation error would bias the fit (``fit_material`` with ``substeps=None``).
REPLAY_SHIFT_SIGMA = 0.1
MAX_AUTO_SUBSTEPS = 8
MU_BOUND_LOGIT = 36.0  # |logit(mu / MU_MAX)| at most this: beyond it float64's sigmoid is 0 or 1
OFFSET_AXES = ("offset_x", "offset_y", "offset_z")  # the pose offset's names, base-frame axes (m)
OFFSET_UNIT_M = 1e-3  # the offset's theta coordinates are in mm
POSE_OFFSET_PRIOR_M = 2e-3  # 1 sigma of the offset's Gaussian prior per axis: it stays within a few mm
#: With a pose offset the cost steps (by about half a noise variance on a sim collection) where the offset moves the
#: object by nanometres, so L-BFGS's line search near the optimum keeps finding "lower" points and never meets its
#: tolerance: a refit with the offset stops once this many evaluations in a row lowered the best scaled cost by less
#: than ``STALL_COST`` (``minimise``'s ``stall_evaluations``) and returns the best point it evaluated.
STALL_EVALUATIONS = 8
STALL_COST = 1e-3  # in the preconditioned refits' scaled cost: half the chi-square in noise variances


@dataclass(frozen=True)
class ReplayBatch:
    """Trajectories of one object and length, replayed together. ``object_poses``, ``bubble_poses``: ``(B, K + 1,
    7)`` (m, wxyz); ``measured``: ``(B, K + 1, 6)`` TCP-frame wrenches less the tare (N, N m); ``labels``: each
    trajectory's ``(object, trajectory index)``; ``spacing_m``: the replay's surface spacing (m); ``pretared``: its
    trajectories start in contact with wrenches tared before them (``RecordedTrajectory.pretared``), so every row,
    row 0 included, is compared as measured and no row shares a tare's noise."""

    object: str
    spacing_m: float
    object_poses: np.ndarray
    bubble_poses: np.ndarray
    measured: np.ndarray
    labels: tuple[tuple[str, int], ...]
    pretared: bool = False


def replay_batches(groups: Sequence, chosen: set[tuple[str, int]]) -> list[ReplayBatch]:
    """The ``chosen`` trajectories (``(object, index)``) of ``groups`` (``wrench_replay.ObjectRecordings``), batched
    by object and length."""
    from hydrosoft.bench.wrench_replay import length_batches

    batches = []
    for group in groups:
        members = [i for i, t in enumerate(group.trajectories) if (group.object, t.index) in chosen]
        picked = [group.trajectories[i] for i in members]
        for rows in length_batches(picked):
            trajectories = [picked[r] for r in rows]
            batches.append(ReplayBatch(
                object=group.object, spacing_m=group.spacing_m,
                object_poses=np.stack([t.object_poses for t in trajectories]),
                bubble_poses=np.stack([t.bubble_poses for t in trajectories]),
                measured=np.stack([group.measured[members[r]] for r in rows]),
                labels=tuple((group.object, t.index) for t in trajectories), pretared=trajectories[0].pretared))
    return batches


def split_trajectories(labels: Sequence[tuple[str, int]], holdout: float, seed: int = 0
                       ) -> tuple[list[tuple[str, int]], list[tuple[str, int]]]:
    """``(fit, held_out)``: a random ``holdout`` fraction (rounded, at least one when ``holdout > 0``) of ``labels``
    held out, at least one kept for the fit; ValueError when that is impossible."""
    if not 0 <= holdout < 1:
        raise ValueError(f"holdout must be a fraction in [0, 1), got {holdout}")
    count = 0 if holdout == 0 else max(1, round(holdout * len(labels)))
    if count >= len(labels):
        raise ValueError(f"holdout {holdout} of {len(labels)} trajectories leaves none to fit: record more")
    order = np.random.default_rng(seed).permutation(len(labels))
    held = {labels[i] for i in order[:count]}
    return [x for x in labels if x not in held], [x for x in labels if x in held]


# --- parameters ---------------------------------------------------------------------------------------------------


def to_theta(values: dict[str, float], start: dict[str, float]) -> torch.Tensor:
    """Unconstrained coordinates ``(3,)`` of a material ``values`` (E, K in Pa/m; mu in ``[0, MU_MAX]``). A mu on a
    bound, where a fit that drives it there ends (the sigmoid saturates), maps to the largest finite coordinate
    (``MU_BOUND_LOGIT``)."""
    mu = min(max(values["mu"] / MU_MAX, 1 / (1 + math.exp(MU_BOUND_LOGIT))), 1 / (1 + math.exp(-MU_BOUND_LOGIT)))
    return torch.tensor([math.log(values["E"] / start["E"]), math.log(values["K"] / start["K"]),
                         math.log(mu / (1 - mu))], dtype=torch.float64)


def to_material(theta: torch.Tensor, start: dict[str, float]) -> Material:
    """The bubble's ``Material`` (each ``(1,)``) at unconstrained coordinates ``theta (3,)``, differentiably."""
    return Material(E=(start["E"] * torch.exp(theta[0])).view(1), K=(start["K"] * torch.exp(theta[1])).view(1),
                    mu=(MU_MAX * torch.sigmoid(theta[2])).view(1))


def to_values(theta: torch.Tensor, start: dict[str, float]) -> dict[str, float]:
    """``to_material`` as plain numbers."""
    material = to_material(theta.detach(), start)
    return {name: float(getattr(material, name)) for name in PARAMETERS}


def with_offset(theta: torch.Tensor, offset_m: Sequence[float]) -> torch.Tensor:
    """The material coordinates ``theta (3,)`` with the pose offset ``offset_m`` (3 numbers, m) appended: ``(6,)``."""
    return torch.cat([theta[:3], torch.as_tensor(offset_m, dtype=torch.float64) / OFFSET_UNIT_M])


def offset_of(theta: torch.Tensor) -> torch.Tensor | None:
    """The pose offset ``(3,)`` (m) of coordinates ``theta`` (``(6,)``), or None for material-only ``(3,)``."""
    return theta[3:6] * OFFSET_UNIT_M if theta.shape[0] == 6 else None


def _offset_poses(poses: np.ndarray, offset_m: torch.Tensor | None) -> torch.Tensor | np.ndarray:
    """Poses ``(..., 7)`` with ``offset_m (3,)`` added to each position (differentiably), or as they are."""
    if offset_m is None:
        return poses
    poses = torch.as_tensor(poses, dtype=torch.float64)
    return torch.cat([poses[..., :3] + offset_m, poses[..., 3:]], dim=-1)


# --- residuals ----------------------------------------------------------------------------------------------------


def _whiten(errors: torch.Tensor) -> torch.Tensor:
    """Whitened residuals of ``errors (B, K, 6)``, noise-weighted prediction errors of rows 1..K that share the
    tare's noise: with ``L = I - b 1 1^T``, ``b = (1 - 1/sqrt(K + 1)) / K``, ``L^T L = (I + 1 1^T)^-1``."""
    steps = errors.shape[1]
    b = (1 - 1 / math.sqrt(steps + 1)) / steps
    return errors - b * errors.sum(1, keepdim=True)


def residuals(theta: torch.Tensor, batches: Sequence[ReplayBatch], contact: str, start: dict[str, float],
              substeps: int = DEFAULT_SUBSTEPS) -> torch.Tensor:
    """Whitened, noise-weighted residuals ``(n,)`` of every batch at ``theta (3,)``, or ``(6,)`` with a pose offset
    (``with_offset``; differentiable in theta): rows 1..K less the tare row's share, or, for a ``pretared`` batch,
    rows 0..K as they are; with an offset, its prior's three residuals ``d / POSE_OFFSET_PRIOR_M`` last."""
    material = to_material(theta, start)
    offset = offset_of(theta)
    weight = torch.as_tensor(1 / FT300_NOISE, dtype=torch.float64)
    out = []
    for batch in batches:
        predicted = replay_tcp_wrenches(batch.object, _offset_poses(batch.object_poses, offset), batch.bubble_poses,
                                        contact, batch.spacing_m, substeps, material)
        if batch.pretared:  # tared before the trajectory: every row on its own
            out.append(((predicted - torch.as_tensor(batch.measured)) * weight).flatten())
            continue
        error = (predicted[:, 1:] - torch.as_tensor(batch.measured[:, 1:])) * weight
        out.append(_whiten(error).flatten())
    if offset is not None:
        out.append(offset / POSE_OFFSET_PRIOR_M)
    return torch.cat(out)


def trajectory_rmses(values: dict[str, float], batches: Sequence[ReplayBatch], contact: str,
                     start: dict[str, float], substeps: int = DEFAULT_SUBSTEPS,
                     offset_m: Sequence[float] | None = None) -> list[dict]:
    """Per trajectory of ``batches`` its ``object``, ``trajectory`` and its force, torque and shear RMSEs
    (``wrench_replay.trajectory_errors``) with the material ``values`` and the object poses moved by ``offset_m``
    (3 numbers, m; None: as recorded)."""
    theta = to_theta(values, start)
    offset = None if offset_m is None else torch.as_tensor(offset_m, dtype=torch.float64)
    rows = []
    with torch.no_grad():
        for batch in batches:
            predicted = replay_tcp_wrenches(batch.object, _offset_poses(batch.object_poses, offset),
                                            batch.bubble_poses, contact, batch.spacing_m, substeps,
                                            to_material(theta, start)).numpy()
            for (name, index), p, m in zip(batch.labels, predicted, batch.measured):
                rows.append({"object": name, "trajectory": index, **trajectory_errors(p, m)})
    return rows


# --- the fit ------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ParameterEstimate:
    """One parameter's result: ``value`` and ``start`` (unit: ``material_parameters.UNITS``), ``sigma`` (1 standard
    deviation, delta method; inf when the data do not determine it), ``interval95`` ``(low, high)``, ``fitted``
    (asked for), ``identified`` (fitted and ``sigma / value <= UNIDENTIFIED_RELATIVE_SIGMA``)."""

    name: str
    start: float
    value: float
    sigma: float
    interval95: tuple[float, float]
    fitted: bool
    identified: bool


@dataclass(frozen=True)
class MaterialFit:
    """The fit's outcome: ``estimates`` per parameter (``PARAMETERS`` order), the cost (mean squared whitened
    residual) at the start and at the optimum, ``reduced_chi2`` (``s2``), ``residual_count``, ``iterations`` (L-BFGS
    cost evaluations), ``covariance`` ``(p, p)`` of the fitted theta coordinates (inf where undetermined),
    ``substeps`` (the replay's, per recorded step), ``replay_shift_sigma`` (``replay_shift`` at the optimum),
    ``theta`` ``(3,)``, the optimum's unconstrained coordinates (``to_theta``; ``(6,)`` with the pose offset's,
    ``with_offset``) and ``pose_offset``: the offset's estimates per axis (``OFFSET_AXES``, m; start 0; interval
    ``value +- Z95 sigma``), empty when it was not fitted."""

    estimates: tuple[ParameterEstimate, ...]
    cost_start: float
    cost: float
    reduced_chi2: float
    residual_count: int
    iterations: int
    covariance: np.ndarray
    substeps: int
    replay_shift_sigma: float
    theta: np.ndarray
    pose_offset: tuple[ParameterEstimate, ...] = ()  # OFFSET_AXES order; an axis not fitted is held at 0

    @property
    def values(self) -> dict[str, float]:
        return {e.name: e.value for e in self.estimates}

    @property
    def offset_m(self) -> list[float] | None:
        """The fitted pose offset (3 numbers, m), or None when it was not fitted."""
        return [e.value for e in self.pose_offset] or None


def fit_material(batches: Sequence[ReplayBatch], contact: str, params: Sequence[str],
                 start: dict[str, float] | None = None, substeps: int | None = None,
                 max_iterations: int = DEFAULT_MAX_ITERATIONS,
                 progress: Callable[[int, float, dict[str, float]], None] | None = None,
                 pose_offset: str = "") -> MaterialFit:
    """Fit ``params`` (a subset of ``PARAMETERS``) of the bubble's material to ``batches`` by L-BFGS.

    ``start``: the material to start from and to hold the other parameters at (default ``START``); ``substeps``:
    the replay's steps per recorded step, or None to choose them: from 1, doubled while a replay twice as fine would
    move a fitted value by more than ``REPLAY_SHIFT_SIGMA`` standard deviations (``replay_shift``), up to
    ``MAX_AUTO_SUBSTEPS``; each doubling moves the optimum by that Gauss-Newton step. ``progress(evaluation, cost,
    values)`` is called after each cost evaluation. ``pose_offset``: the base axes (some of ``"xyz"``) along which to
    fit a constant object position offset too (module docstring), from 0; empty: none.
    ValueError for an unknown parameter or model, or no batch.
    """
    start = dict(START if start is None else start)
    unknown = [p for p in params if p not in PARAMETERS]
    if unknown or not params:
        raise ValueError(f"unknown parameter(s) {unknown}; fit some of {', '.join(PARAMETERS)}")
    if contact not in FIT_MODELS:
        raise ValueError(f"unknown contact model {contact!r} for the fit; known: {', '.join(FIT_MODELS)}")
    if not set(pose_offset) <= set("xyz"):
        raise ValueError(f"pose offset axes must be some of x, y, z, got {pose_offset!r}")
    if not batches:
        raise ValueError("no trajectory to fit")
    mask = torch.tensor([name in params for name in PARAMETERS])
    evaluations: list[float] = []
    steps = substeps or 1
    theta = minimise(to_theta(start, start), mask, batches, contact, start, steps, max_iterations, evaluations,
                     progress)
    if pose_offset:
        theta, mask = _refit_with_offset(theta, mask, pose_offset, batches, contact, start, steps, max_iterations,
                                         evaluations, progress)
    r, J = residuals_and_jacobian(theta, mask, batches, contact, start, steps)
    while True:
        n, p = r.shape[0], int(mask.sum())
        s2 = float(np.square(r).sum()) / max(n - p, 1)
        covariance = s2 * _pseudo_inverse_with_infinity(J.T @ J)
        shift, step = replay_shift(theta, J, r, covariance, batches, contact, start, steps)
        if substeps is not None or shift <= REPLAY_SHIFT_SIGMA or steps >= MAX_AUTO_SUBSTEPS:
            break
        steps *= 2  # the optimum moves by the Gauss-Newton step to the finer replay's residuals
        theta = _move_to_finer_replay(theta, mask, step, covariance, n / (2 * s2), batches, contact, start, steps,
                                      max_iterations, evaluations, progress)
        r, J = residuals_and_jacobian(theta, mask, batches, contact, start, steps)
    estimates = _estimates(theta, start, mask, covariance)
    return MaterialFit(estimates=estimates, cost_start=evaluations[0], cost=float(np.square(r).mean()),
                       reduced_chi2=s2, residual_count=n, iterations=len(evaluations), covariance=covariance,
                       substeps=steps, replay_shift_sigma=shift, theta=theta.numpy().copy(),
                       pose_offset=_offset_estimates(theta, mask, covariance) if pose_offset else ())


def _move_to_finer_replay(theta: torch.Tensor, mask: torch.Tensor, step: np.ndarray, covariance: np.ndarray,
                          cost_scale: float, batches, contact, start, substeps: int, max_iterations: int,
                          evaluations: list[float], progress) -> torch.Tensor:
    """The optimum at the finer replay (``substeps``) from ``theta``, the coarser one's: ``theta`` moved by the
    Gauss-Newton ``step (p,)``, or, when that raises the finer replay's cost (a direction the data barely determine,
    such as E against a depth offset on a push at one depth, where the linear step overshoots), L-BFGS from
    ``theta`` at the finer replay, preconditioned by ``covariance`` where it is finite."""
    moved = theta.masked_scatter(mask, theta[mask] + torch.as_tensor(step))
    with torch.no_grad():
        costs = [float(residuals(t, batches, contact, start, substeps).square().mean()) for t in (theta, moved)]
    if costs[1] <= costs[0]:
        return moved
    try:
        preconditioner = np.linalg.cholesky(covariance) if np.isfinite(covariance).all() else None
    except np.linalg.LinAlgError:  # not positive definite: plain L-BFGS
        preconditioner = None
    return minimise(theta, mask, batches, contact, start, substeps, max_iterations, evaluations, progress,
                    preconditioner=preconditioner, cost_scale=1.0 if preconditioner is None else cost_scale,
                    stall_evaluations=stall_evaluations(theta))


def _refit_with_offset(theta: torch.Tensor, mask: torch.Tensor, axes: str, batches, contact, start, substeps: int,
                       max_iterations: int, evaluations: list[float], progress) -> tuple[torch.Tensor, torch.Tensor]:
    """The joint optimum ``(6,)`` of the material and the pose offset along ``axes`` (some of ``"xyz"``), and its
    mask ``(6,)``, from the material's optimum
    ``theta (3,)`` at offset 0: L-BFGS preconditioned by the Gauss-Newton covariance there (as the bootstrap's
    refits), so the offset (mm) and the material's log and logit coordinates, of very different curvature, take
    Newton-sized steps. From a cold start L-BFGS stalled short of the material-only fit's cost. It stops once it
    stalls (``STALL_EVALUATIONS``)."""
    theta = with_offset(theta, (0.0, 0.0, 0.0))
    mask = torch.cat([mask, torch.tensor([axis in axes for axis in "xyz"])])
    r, J = residuals_and_jacobian(theta, mask, batches, contact, start, substeps)
    n, p = r.shape[0], int(mask.sum())
    s2 = max(float(np.square(r).sum()) / max(n - p, 1), 1e-12)
    information = J.T @ J
    information += SINGULAR_RCOND * max(float(np.trace(information)), 1e-12) * np.eye(p)  # stays invertible
    preconditioner = np.linalg.cholesky(s2 * np.linalg.inv(information))
    theta = minimise(theta, mask, batches, contact, start, substeps, max_iterations, evaluations, progress,
                     preconditioner=preconditioner, cost_scale=n / (2 * s2), stall_evaluations=STALL_EVALUATIONS)
    return theta, mask


def stall_evaluations(theta: torch.Tensor) -> int | None:
    """``minimise``'s ``stall_evaluations`` for a refit from ``theta``: ``STALL_EVALUATIONS`` with a pose offset
    (its cost has steps), else None."""
    return None if offset_of(theta) is None else STALL_EVALUATIONS


def minimise(theta: torch.Tensor, mask: torch.Tensor, batches: Sequence[ReplayBatch], contact: str,
             start: dict[str, float], substeps: int, max_iterations: int = DEFAULT_MAX_ITERATIONS,
             evaluations: list[float] | None = None, progress=None, preconditioner: np.ndarray | None = None,
             cost_scale: float = 1.0, tolerance_change: float = 1e-12,
             stall_evaluations: int | None = None) -> torch.Tensor:
    """L-BFGS over the fitted coordinates (``mask``, theta's shape) of ``theta`` (``(3,)``, or ``(6,)`` with a pose
    offset) from there, the others held; the optimum, theta's shape. Appends each cost evaluation (the mean squared
    residual) to ``evaluations``; ``progress`` as ``fit_material``'s.

    ``preconditioner``: a ``(p, p)`` matrix ``C``; L-BFGS then runs over ``u`` with the fitted coordinates
    ``theta_0 + C u`` from ``u = 0``, on the cost times ``cost_scale``. With ``C^T H C`` about the identity for
    that cost's Hessian ``H`` its first steps are about Newton's, so a warm start near the optimum takes few
    evaluations (``fit_bootstrap``'s refits). ``tolerance_change``: L-BFGS stops once a step moves ``u`` (or theta)
    or the scaled cost by less.

    ``stall_evaluations``: stop once that many evaluations in a row lowered the best scaled cost by less than
    ``STALL_COST``, and return the best point evaluated (``STALL_EVALUATIONS``: for a cost with steps); None:
    L-BFGS's own stopping rules alone."""
    evaluations = [] if evaluations is None else evaluations
    origin = theta[mask].clone()
    C = None if preconditioner is None else torch.as_tensor(preconditioner, dtype=torch.float64)
    free = torch.zeros_like(origin) if C is not None else origin.clone()
    free.requires_grad_(True)
    best = {"cost": math.inf, "free": free.detach().clone(), "stalled": 0}

    def full(free_part: torch.Tensor) -> torch.Tensor:
        return theta.masked_scatter(mask, free_part if C is None else origin + C @ free_part)

    optimizer = torch.optim.LBFGS([free], lr=1.0, max_iter=max_iterations, tolerance_grad=1e-9,
                                  tolerance_change=tolerance_change, history_size=10, line_search_fn="strong_wolfe")

    def closure() -> torch.Tensor:
        optimizer.zero_grad()
        cost = residuals(full(free), batches, contact, start, substeps).square().mean()
        (cost_scale * cost).backward()
        evaluations.append(float(cost.detach()))
        if progress:
            progress(len(evaluations), evaluations[-1], _shown_values(full(free.detach()), start))
        scaled = cost_scale * evaluations[-1]
        best["stalled"] = 0 if scaled < best["cost"] - STALL_COST else best["stalled"] + 1
        if scaled < best["cost"]:
            best["cost"], best["free"] = scaled, free.detach().clone()
        if stall_evaluations is not None and best["stalled"] >= stall_evaluations:
            raise _Stalled
        return cost_scale * cost.detach()

    try:
        optimizer.step(closure)
    except _Stalled:
        return full(best["free"])
    return full(free.detach())


class _Stalled(Exception):
    """``minimise``'s refit made no progress over ``stall_evaluations`` evaluations."""


def _shown_values(theta: torch.Tensor, start: dict[str, float]) -> dict[str, float]:
    """The material at ``theta`` (``to_values``) and, with a pose offset, its axes (``OFFSET_AXES``, m): what
    ``progress`` reports."""
    offset = offset_of(theta)
    offsets = {} if offset is None else dict(zip(OFFSET_AXES, offset.tolist()))
    return {**to_values(theta, start), **offsets}


def replay_shift(theta: torch.Tensor, J: np.ndarray, r: np.ndarray, covariance: np.ndarray, batches, contact,
                 start, substeps: int) -> tuple[float, np.ndarray]:
    """How far a replay twice as fine would move the fitted values from ``theta (3,)``, an optimum at ``substeps``
    with residuals ``r (n,)``, Jacobian ``J (n, p)`` and ``covariance (p, p)``. Returns the largest move in units of
    each fitted parameter's standard deviation (0 where that is infinite: the data do not determine it) and the move
    ``(p,)`` itself: the Gauss-Newton step ``-(J^T J)^-1 J^T r'`` to the residuals ``r'`` at ``2 substeps``."""
    with torch.no_grad():
        finer = residuals(theta, batches, contact, start, 2 * substeps).numpy()
    step = -np.linalg.lstsq(J, finer, rcond=None)[0]
    sigma = np.sqrt(np.diag(covariance))
    ratio = np.where(np.isfinite(sigma) & (sigma > 0), np.abs(step) / np.where(np.isfinite(sigma), sigma, 1.0), 0.0)
    return float(ratio.max()), step


def residuals_and_jacobian(theta: torch.Tensor, mask: torch.Tensor, batches, contact, start, substeps
                            ) -> tuple[np.ndarray, np.ndarray]:
    """Residuals ``(n,)`` and their Jacobian ``(n, p)`` in the fitted coordinates, by forward-mode autograd."""
    import torch.autograd.forward_ad as forward_ad

    columns = []
    with torch.no_grad():
        r = residuals(theta, batches, contact, start, substeps).numpy()
    for i in mask.nonzero().flatten().tolist():
        with forward_ad.dual_level():
            direction = torch.zeros_like(theta)
            direction[i] = 1.0
            dual = residuals(forward_ad.make_dual(theta, direction), batches, contact, start, substeps)
            columns.append(forward_ad.unpack_dual(dual).tangent.detach().numpy())
    return r, np.stack(columns, axis=-1)


def _pseudo_inverse_with_infinity(information: np.ndarray) -> np.ndarray:
    """``information^-1`` for a symmetric positive semi-definite ``(p, p)`` matrix; along its null directions
    (eigenvalues under ``SINGULAR_RCOND`` of the largest) the variance is infinite: every entry that involves
    such a direction is inf (the diagonal) or nan (off it)."""
    eigenvalues, vectors = np.linalg.eigh(information)
    largest = max(float(eigenvalues.max()), 0.0)
    null = eigenvalues <= SINGULAR_RCOND * largest if largest > 0 else np.ones_like(eigenvalues, dtype=bool)
    inverse = np.where(null, 0.0, 1 / np.where(null, 1.0, eigenvalues))
    covariance = (vectors * inverse) @ vectors.T
    touched = (np.abs(vectors[:, null]) > 1e-6).any(axis=1)
    covariance[np.ix_(touched, touched)] = np.nan
    covariance[touched, touched] = np.inf
    return covariance


def _offset_estimates(theta: torch.Tensor, mask: torch.Tensor, covariance: np.ndarray
                      ) -> tuple[ParameterEstimate, ...]:
    """The pose offset's estimates (m) per axis from coordinates 3..5 of ``theta (6,)``, ``mask (6,)`` and the
    fitted coordinates' ``covariance``; an axis not fitted is 0, held."""
    fitted_index = {i: j for j, i in enumerate(mask.nonzero().flatten().tolist())}
    out = []
    for axis, name in enumerate(OFFSET_AXES):
        if 3 + axis not in fitted_index:
            out.append(ParameterEstimate(name, 0.0, 0.0, 0.0, (0.0, 0.0), False, False))
            continue
        value = float(theta[3 + axis]) * OFFSET_UNIT_M
        variance = covariance[fitted_index[3 + axis], fitted_index[3 + axis]]
        sigma = math.sqrt(variance) * OFFSET_UNIT_M if math.isfinite(variance) else math.inf
        out.append(ParameterEstimate(name, 0.0, value, sigma, (value - Z95 * sigma, value + Z95 * sigma), True,
                                     sigma <= UNIDENTIFIED_RELATIVE_SIGMA * POSE_OFFSET_PRIOR_M))
    return tuple(out)


def _estimates(theta: torch.Tensor, start: dict[str, float], mask: torch.Tensor, covariance: np.ndarray
               ) -> tuple[ParameterEstimate, ...]:
    values = to_values(theta, start)
    fitted_index = {i: j for j, i in enumerate(mask.nonzero().flatten().tolist())}
    out = []
    for i, name in enumerate(PARAMETERS):
        if i not in fitted_index:
            value = start[name]
            out.append(ParameterEstimate(name, value, value, 0.0, (value, value), False, False))
            continue
        value = values[name]
        sigma_theta = math.sqrt(covariance[fitted_index[i], fitted_index[i]])
        t = float(theta[i])
        if name == "mu":
            slope = value * (1 - value / MU_MAX)  # d mu / d theta of MU_MAX * sigmoid(theta)
            sigma = slope * sigma_theta if math.isfinite(sigma_theta) else math.inf
            interval = tuple(MU_MAX / (1 + math.exp(-(t + s * Z95 * sigma_theta))) if math.isfinite(sigma_theta)
                             else (0.0, MU_MAX)[s > 0] for s in (-1, 1))
        else:
            sigma = value * sigma_theta
            interval = tuple(value * math.exp(s * Z95 * sigma_theta) if math.isfinite(sigma_theta)
                             else (0.0, math.inf)[s > 0] for s in (-1, 1))
        identified = math.isfinite(sigma) and sigma <= UNIDENTIFIED_RELATIVE_SIGMA * value
        out.append(ParameterEstimate(name, start[name], value, sigma, interval, True, identified))
    return tuple(out)
