"""Profile-likelihood intervals of the material fit (``hydrosoft-stack fit --uncertainty profile``): each fitted
parameter's 95 % interval from the cost itself, not from its linearisation at the optimum.

The fit's cost is the sum of squared whitened residuals ``S(theta)`` (``material_fit.residuals``). For parameter
``i`` its profile at a coordinate ``t`` (``material_fit.to_theta``'s log or logit coordinate) is ``S`` minimised
over the other fitted coordinates with ``theta_i = t``. The signed root ``w(t) = sign(t - theta_i) sqrt((S_profile(t)
- S(theta)) / s2)``, with ``s2`` the fit's reduced chi-square (the noise level the residuals show, as the
Gauss-Newton covariance is scaled), is ``(t - theta_i) / sigma_i`` where the residuals are linear; the interval is
where ``|w| <= Z95``. Where they are not, as near the stick/slip switches of the tangential force (slip makes it
``mu`` times the normal force, stick makes it ``K`` times the displacement, so its derivatives in mu and K jump
where a patch element switches), the profile follows the cost: the interval grows on the side where the data tell
less (more sticking, higher mu), which the Gauss-Newton interval, from the derivatives at the optimum alone, misses.

Search per side: from the Gauss-Newton end ``theta_i +- Z95 sigma_i`` by the secant on ``w`` (bisection once the
crossing is bracketed) until ``|w| - Z95`` is within ``ROOT_TOLERANCE``, at most ``MAX_POINTS`` profile points. Each
point refits the others by ``material_fit.minimise``, warm-started where the Gauss-Newton covariance puts them given
``t`` and preconditioned by their conditional covariance (a few cost evaluations). A side that does not reach
``Z95`` within ``MAX_REACH_SIGMA`` Gauss-Newton standard deviations (or mu's bound) is open: its end is the
parameter's bound (0 or inf for E and K, 0 or ``MU_MAX`` for mu). A parameter the Gauss-Newton covariance finds
undetermined (infinite variance) keeps that verdict, as under the bootstrap. ``sigma`` and ``identified`` stay
Gauss-Newton's; only ``interval95`` is the profile's.

``signed_roots``: ``w`` at given values (``bench fit``'s truth), the profile's own z-score: a value lies in the
profile interval exactly where its ``|w| <= Z95`` (the interval is that set; its ends are found to
``ROOT_TOLERANCE``), at one refit per parameter instead of the interval's 2 to 8.

With a pose offset (``fit --pose-offset``) the offset's fitted axes are among "the others": refitted at each point,
so E's profile interval carries the offset's uncertainty, as its Gauss-Newton marginal does; the offset itself keeps
its Gauss-Newton interval.

Cost: 2 to 4 profile points per side and parameter, each a refit of the others (``hydrosoft-stack fit --help``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np
import torch

from hydrosoft.bench.fit_bootstrap import theta_to_value
from hydrosoft.bench.material_fit import (MU_BOUND_LOGIT, START, Z95, MaterialFit, ParameterEstimate, ReplayBatch,
                                          minimise, residuals, stall_evaluations, to_theta)
from hydrosoft.bench.material_parameters import MU_MAX, PARAMETERS

ROOT_TOLERANCE = 0.02  # |w| within this of Z95 ends a side's search (1 % of the interval's half-width)
MAX_POINTS = 6  # profile points per side at most
MAX_REACH_SIGMA = 20.0  # a side whose profile stays under Z95 this many Gauss-Newton sigmas out is open
#: A profile refit stops once a step moves the others by less than this many of their standard deviations, or the
#: scaled cost by less (``fit_bootstrap.REFIT_TOLERANCE``'s meaning).
REFIT_TOLERANCE = 1e-5


@dataclass(frozen=True)
class Profile:
    """The profile intervals: ``estimates`` per parameter (``PARAMETERS`` order; the fit's values and Gauss-Newton
    sigma, the profile's 95 % ``interval95``), ``points`` per fitted, determined parameter: its profile points
    ``(t, w)`` (coordinate and signed root) in the order evaluated, ``open`` the names and sides (``"low"``,
    ``"high"``) that reached no ``Z95``, ``evaluations`` (cost evaluations of all refits) and ``seconds`` (wall
    time)."""

    estimates: tuple[ParameterEstimate, ...]
    points: dict[str, list[tuple[float, float]]]
    open: tuple[tuple[str, str], ...]
    evaluations: int
    seconds: float


class ProfileCost:
    """The profile ``w(t)`` of each fitted coordinate of ``fit`` (the result of ``material_fit.fit_material(batches,
    contact, params, start)``, with or without a pose offset), counting cost evaluations in ``evaluations``. Only
    the fitted coordinates with a finite Gauss-Newton variance are profiled or refitted; an undetermined one (the
    data do not change with it) stays at its fitted value. With a pose offset its fitted axes (``theta[3:6]``, mm)
    are refitted at each profile point like the other material parameters, so the offset's uncertainty widens the
    material's intervals as it widens Gauss-Newton's."""

    def __init__(self, fit: MaterialFit, batches: Sequence[ReplayBatch], contact: str, params: Sequence[str],
                 start: dict[str, float] | None = None) -> None:
        self.batches, self.contact, self.substeps = batches, contact, fit.substeps
        self.start = dict(START if start is None else start)
        self.theta = torch.as_tensor(fit.theta, dtype=torch.float64)
        fitted = [i for i, name in enumerate(PARAMETERS) if name in params]
        fitted += [len(PARAMETERS) + axis for axis, e in enumerate(fit.pose_offset) if e.fitted]  # covariance order
        keep = [j for j, _ in enumerate(fitted) if math.isfinite(fit.covariance[j, j])]
        self.fitted = [fitted[j] for j in keep]  # the determined coordinates (of theta)
        self.mask = torch.tensor([i in self.fitted for i in range(self.theta.shape[0])])
        self.covariance = fit.covariance[np.ix_(keep, keep)]
        self.s2 = fit.reduced_chi2
        self.count = fit.residual_count
        self.cost_scale = fit.residual_count / (2 * fit.reduced_chi2)  # as the bootstrap's refits (newton_scale)
        with torch.no_grad():
            self.minimum = float(residuals(self.theta, batches, contact, self.start, self.substeps).square().sum())
        self.evaluations: list[float] = []

    def sigma(self, index: int) -> float:
        """Gauss-Newton standard deviation of coordinate ``index`` (of theta)."""
        j = self.fitted.index(index)
        return math.sqrt(self.covariance[j, j])

    def signed_root(self, index: int, t: float) -> float:
        """``w(t)`` of coordinate ``index``: the rise of the cost minimised over the others, in noise variances, as
        a signed square root (module docstring); 0 where the profile lies below the fit's own cost."""
        j = self.fitted.index(index)
        others = [k for k in range(len(self.fitted)) if k != j]
        theta = self.theta.clone()
        theta[index] = t
        count = len(self.evaluations)
        if not others:
            with torch.no_grad():
                total = float(residuals(theta, self.batches, self.contact, self.start, self.substeps).square().sum())
            self.evaluations.append(total)
        else:
            shift = self.covariance[others, j] / self.covariance[j, j] * (t - float(self.theta[index]))
            for k, s in zip(others, shift):  # where the Gauss-Newton covariance puts the others given t
                theta[self.fitted[k]] += float(s)
            conditional = self.covariance[np.ix_(others, others)] - np.outer(
                self.covariance[others, j], self.covariance[j, others]) / self.covariance[j, j]
            mask = self.mask.clone()
            mask[index] = False
            mean_costs: list[float] = []
            minimise(theta, mask, self.batches, self.contact, self.start, self.substeps, evaluations=mean_costs,
                     preconditioner=np.linalg.cholesky(conditional), cost_scale=self.cost_scale,
                     tolerance_change=REFIT_TOLERANCE, stall_evaluations=stall_evaluations(theta))
            self.evaluations += [c * self.count for c in mean_costs]
        total = min(self.evaluations[count:])  # each evaluation lies on the slice theta_i = t: the least is its profile
        rise = max(total - self.minimum, 0.0) / self.s2
        return math.copysign(math.sqrt(rise), t - float(self.theta[index]))


def _reach(name: str, side: int, theta: float, sigma: float) -> float:
    """How far (coordinate units, 0 or more) a side's search may go from ``theta``: ``MAX_REACH_SIGMA`` sigmas,
    and for mu no further than its logit bound."""
    if name == "mu":
        return max(min(MAX_REACH_SIGMA * sigma, MU_BOUND_LOGIT - side * theta), 0.0)
    return MAX_REACH_SIGMA * sigma


def profile_end(cost: ProfileCost, index: int, side: int, points: list[tuple[float, float]]) -> float | None:
    """The coordinate where the profile of coordinate ``index`` crosses ``Z95`` on ``side`` (+1 above the fit, -1
    below), or None when it does not within the search's reach (an open side). Appends each point ``(t, w)``."""
    theta, sigma = float(cost.theta[index]), cost.sigma(index)
    reach = _reach(PARAMETERS[index], side, theta, sigma)
    below, above = (0.0, 0.0), None  # (distance, |w|) known to lie below and above Z95
    distance = min(Z95 * sigma, reach)
    for _ in range(MAX_POINTS):
        w = abs(cost.signed_root(index, theta + side * distance))
        points.append((theta + side * distance, side * w))
        if abs(w - Z95) <= ROOT_TOLERANCE:
            return theta + side * distance
        if w < Z95:
            below = (distance, w)
        else:
            above = (distance, w)
        if above is None:
            if distance >= reach:
                return None
            slope = below[1] / below[0] if below[0] > 0 else 0.0  # secant through w(0) = 0
            distance = min(Z95 / slope if slope > 0 else 2 * distance, 2 * distance, reach)
            continue
        (d0, w0), (d1, w1) = below, above  # bracketed: the secant inside the bracket, else bisection
        guess = d0 + (Z95 - w0) * (d1 - d0) / (w1 - w0) if w1 > w0 else 0.5 * (d0 + d1)
        distance = guess if d0 < guess < d1 else 0.5 * (d0 + d1)
    if above is None:
        return None
    (d0, w0), (d1, w1) = below, above
    return theta + side * (d0 + (Z95 - w0) * (d1 - d0) / (w1 - w0))


def profile_intervals(fit: MaterialFit, batches: Sequence[ReplayBatch], contact: str, params: Sequence[str],
                      start: dict[str, float] | None = None,
                      progress: Callable[[str, int, float], None] | None = None) -> Profile:
    """Profile-likelihood 95 % intervals (module docstring) of ``fit``, the result of
    ``material_fit.fit_material(batches, contact, params, start)``. ``progress(name, points, seconds)`` is called
    after each parameter. The pose offset's axes, where fitted, are refitted at each point, not profiled: they keep
    Gauss-Newton's intervals (``fit.pose_offset``)."""
    tic = time.perf_counter()
    cost = ProfileCost(fit, batches, contact, params, start)
    estimates, points, open_sides = [], {}, []
    for index, e in enumerate(fit.estimates):
        if not e.fitted or not math.isfinite(e.sigma):
            estimates.append(e)  # held, or undetermined by the data: no profile to follow
            continue
        points[e.name] = []
        ends = []
        for side, label in ((-1, "low"), (1, "high")):
            end = profile_end(cost, index, side, points[e.name])
            if end is None:
                open_sides.append((e.name, label))
                ends.append((0.0, MU_MAX if e.name == "mu" else math.inf)[side > 0])
            else:
                ends.append(float(theta_to_value(e.name, np.array(end), cost.start)))
        estimates.append(replace(e, interval95=(ends[0], ends[1])))
        if progress:
            progress(e.name, len(points[e.name]), time.perf_counter() - tic)
    return Profile(estimates=tuple(estimates), points=points, open=tuple(open_sides),
                   evaluations=len(cost.evaluations), seconds=time.perf_counter() - tic)


def signed_roots(fit: MaterialFit, batches: Sequence[ReplayBatch], contact: str, params: Sequence[str],
                 at: dict[str, float], start: dict[str, float] | None = None) -> tuple[dict[str, float], int]:
    """The profile's signed root ``w`` (module docstring) at the material ``at`` (E, K, mu) of each fitted,
    determined parameter of ``fit`` (as ``profile_intervals`` takes it), and the cost evaluations that took."""
    cost = ProfileCost(fit, batches, contact, params, start)
    target = to_theta(at, cost.start)
    roots = {e.name: cost.signed_root(index, float(target[index])) for index, e in enumerate(fit.estimates)
             if e.fitted and math.isfinite(e.sigma)}
    return roots, len(cost.evaluations)

