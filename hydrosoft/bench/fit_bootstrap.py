"""Parametric bootstrap of the material fit (``hydrosoft-stack fit --uncertainty bootstrap``): the uncertainty of
the fitted E, K and mu from refits on data simulated at the fitted material.

Each draw replays the fit's trajectories at the fitted material (the fit's own replay and sub-steps), adds fresh
noise from the FT 300's noise model (``synthetic_wrench.measured_wrenches``: the mean of ``FRAMES_PER_SAMPLE``
frames, each with Gaussian noise ``noise_scale * FT300_NOISE``, quantised) to every row, the tare row included, and
subtracts the noisy tare, as a recording is read. The noise level is the one the fit's residuals show:
``noise_scale = sqrt(reduced_chi2 * FRAMES_PER_SAMPLE)`` (about 1 under the simulated sensor's noise; model error on
lab data raises it, as it scales the Gauss-Newton covariance). The noise is drawn in the TCP frame (the sensor frame
when, as in sim, they coincide). Each draw is refitted by the fit's L-BFGS (``material_fit.minimise``), warm-started
at the fit's optimum, with the same sub-steps.

Intervals per fitted parameter, from the draws' unconstrained coordinates ``theta*`` (``material_fit.to_theta``)
against the fit's ``theta``: ``percentile`` (the 2.5 % and 97.5 % quantiles of ``theta*``) and ``basic``
(``2 theta - `` those quantiles, reversed), mapped back to values. ``sigma`` is the draws' standard deviation in value
units. A parameter the Gauss-Newton covariance finds undetermined (infinite variance: the data do not change with
it) keeps that verdict: its draws cannot move it, so their spread says nothing.

Cost: one refit per draw, 6 to 21 cost evaluations each (``hydrosoft-stack fit --help`` gives the run time).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np
import torch

from hydrosoft.bench.material_fit import (START, UNIDENTIFIED_RELATIVE_SIGMA, MaterialFit, ParameterEstimate,
                                          ReplayBatch, minimise, to_material)
from hydrosoft.bench.material_parameters import BOOTSTRAP_INTERVALS as INTERVALS
from hydrosoft.bench.material_parameters import DEFAULT_DRAWS, MU_MAX, PARAMETERS
from hydrosoft.bench.synthetic_wrench import FRAMES_PER_SAMPLE, measured_wrenches
from hydrosoft.bench.wrench_replay import predict_tcp_wrenches

BOOTSTRAP_INTERVAL = "percentile"  # the kind ``fit --uncertainty bootstrap`` reports (docs/decisions.md)
NOISE_STREAM = 0xB007  # first word of the bootstrap noise generator's seed
QUANTILES = (0.025, 0.975)  # two-sided 95 %
#: A refit stops once a step moves the values by less than this many standard deviations (along the fit's
#: covariance), or the cost by less than this many times the noise variance (0.014 standard deviations from its
#: minimum).
REFIT_TOLERANCE = 1e-4


@dataclass(frozen=True)
class Bootstrap:
    """The bootstrap's outcome: ``estimates`` per parameter (``PARAMETERS`` order; the fit's values, the draws'
    ``sigma`` and the ``interval`` kind's 95 % interval), ``intervals`` per kind (``INTERVALS``) and fitted parameter
    name ``(low, high)``, ``draws`` ``(D, p)`` the refitted unconstrained coordinates of the fitted parameters,
    ``noise_scale`` (of ``FT300_NOISE`` per frame), ``failed`` (draws whose refit was not finite, left out),
    ``evaluations`` (cost evaluations of all refits) and ``seconds`` (wall time)."""

    estimates: tuple[ParameterEstimate, ...]
    intervals: dict[str, dict[str, tuple[float, float]]]
    draws: np.ndarray
    noise_scale: float
    failed: int
    evaluations: int
    seconds: float


def noisy_batches(batches: Sequence[ReplayBatch], predicted: Sequence[np.ndarray], rng: np.random.Generator,
                  noise_scale: float) -> list[ReplayBatch]:
    """``batches`` with their measurements replaced by ``predicted`` (per batch ``(B, K + 1, 6)``, N and N m) plus
    fresh sensor noise (``measured_wrenches``) less the noisy tare row 0 (none for a ``pretared`` batch)."""
    out = []
    for batch, truth in zip(batches, predicted):
        wrenches = measured_wrenches(truth, rng, noise_scale)
        out.append(replace(batch, measured=wrenches if batch.pretared else wrenches - wrenches[:, :1]))
    return out


def theta_to_value(name: str, theta: np.ndarray, start: dict[str, float]) -> np.ndarray:
    """Parameter ``name``'s values at its unconstrained coordinates ``theta`` (any shape; ``material_fit.to_theta``'s
    inverse)."""
    theta = np.asarray(theta, dtype=np.float64)
    if name == "mu":
        return MU_MAX / (1 + np.exp(-theta))
    return start[name] * np.exp(theta)


def intervals_of(draws: np.ndarray, theta: float) -> dict[str, tuple[float, float]]:
    """The 95 % ``percentile`` and ``basic`` intervals ``(low, high)`` in unconstrained coordinates of one
    parameter from its refitted ``draws (D,)`` around the fit's ``theta``."""
    low, high = np.quantile(draws, QUANTILES)
    return {"percentile": (float(low), float(high)), "basic": (float(2 * theta - high), float(2 * theta - low))}


def newton_scale(fit: MaterialFit) -> tuple[np.ndarray, float] | None:
    """The refits' preconditioner ``C (p, p)`` and cost scale (``material_fit.minimise``): ``C`` the Cholesky factor
    of the fit's covariance and the scale ``n / (2 s2)``, so that the scaled cost's Gauss-Newton Hessian in ``u`` is
    the identity and ``u`` counts standard deviations. None when a direction is undetermined (infinite covariance)."""
    if not np.isfinite(fit.covariance).all():
        return None
    return np.linalg.cholesky(fit.covariance), fit.residual_count / (2 * fit.reduced_chi2)


def bootstrap(fit: MaterialFit, batches: Sequence[ReplayBatch], contact: str, params: Sequence[str],
              draws: int = DEFAULT_DRAWS, seed: int = 0, start: dict[str, float] | None = None,
              interval: str = BOOTSTRAP_INTERVAL,
              progress: Callable[[int, int, float], None] | None = None) -> Bootstrap:
    """Parametric bootstrap (module docstring) of ``fit``, the result of ``material_fit.fit_material(batches,
    contact, params, start)``: ``draws`` refits, noise seeded by ``seed``; ``interval``: the kind its estimates
    report (``INTERVALS``). ``progress(draw, draws, seconds)`` is called after each refit. ValueError for fewer
    than 2 draws or an unknown interval kind."""
    if draws < 2:
        raise ValueError(f"the bootstrap needs at least 2 draws, got {draws}")
    if interval not in INTERVALS:
        raise ValueError(f"unknown bootstrap interval {interval!r}; known: {', '.join(INTERVALS)}")
    start = dict(START if start is None else start)
    tic = time.perf_counter()
    mask = torch.tensor([name in params for name in PARAMETERS])
    theta = torch.as_tensor(fit.theta, dtype=torch.float64)
    material = to_material(theta, start)
    predicted = [predict_tcp_wrenches(b.object, b.object_poses, b.bubble_poses, contact, b.spacing_m, fit.substeps,
                                      material) for b in batches]
    noise_scale = math.sqrt(fit.reduced_chi2 * FRAMES_PER_SAMPLE)
    rng = np.random.default_rng((NOISE_STREAM, seed))  # apart from other generators seeded by the same number
    scaled = newton_scale(fit)
    preconditioner, cost_scale = scaled if scaled is not None else (None, 1.0)
    evaluations: list[float] = []
    refits = []
    for draw in range(draws):
        simulated = noisy_batches(batches, predicted, rng, noise_scale)
        refits.append(minimise(theta.clone(), mask, simulated, contact, start, fit.substeps,
                               evaluations=evaluations, preconditioner=preconditioner, cost_scale=cost_scale,
                               tolerance_change=REFIT_TOLERANCE)[mask].numpy())
        if progress:
            progress(draw + 1, draws, time.perf_counter() - tic)
    samples = np.stack(refits)
    finite = np.isfinite(samples).all(axis=1)
    samples = samples[finite]
    if len(samples) < 2:
        raise ValueError(f"only {len(samples)} of {draws} bootstrap refits were finite")
    fitted = [name for name in PARAMETERS if name in params]
    kinds: dict[str, dict[str, tuple[float, float]]] = {kind: {} for kind in INTERVALS}
    estimates = []
    for e in fit.estimates:
        if not e.fitted or not math.isfinite(e.sigma):
            estimates.append(e)  # held, or undetermined by the data: its draws cannot move it
            continue
        column = fitted.index(e.name)
        t = float(fit.theta[PARAMETERS.index(e.name)])
        for kind, bounds in intervals_of(samples[:, column], t).items():
            low, high = theta_to_value(e.name, np.array(bounds), start)
            kinds[kind][e.name] = (float(low), float(high))
        sigma = float(np.std(theta_to_value(e.name, samples[:, column], start), ddof=1))
        identified = math.isfinite(sigma) and sigma <= UNIDENTIFIED_RELATIVE_SIGMA * e.value
        estimates.append(replace(e, sigma=sigma, interval95=kinds[interval][e.name], identified=identified))
    return Bootstrap(estimates=tuple(estimates), intervals=kinds, draws=samples, noise_scale=noise_scale,
                     failed=int((~finite).sum()), evaluations=len(evaluations),
                     seconds=time.perf_counter() - tic)
