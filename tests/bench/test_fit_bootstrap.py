"""The parametric bootstrap of the material fit: on a synthetic recording with the FT 300's noise its spread matches
the Gauss-Newton covariance where the model is nearly linear (E and K), its refits are warm-started fits of the same
optimiser, and its intervals are what their names say."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hydrosoft.bench import fit_bootstrap, material_fit
from hydrosoft.bench.synthetic_wrench import write_synthetic_recording

from fit_recordings import TRUTH, noisy_cube_fit, replay_batches


def test_the_bootstrap_spread_matches_gauss_newton_where_the_model_is_nearly_linear(tmp_path):
    batches, fit = noisy_cube_fit(tmp_path)
    draws = []
    boot = fit_bootstrap.bootstrap(fit, batches, "nh", list(TRUTH), draws=16, seed=0,
                                   progress=lambda draw, total, seconds: draws.append((draw, total)))
    assert draws[-1] == (16, 16) and boot.draws.shape == (16, 3) and boot.failed == 0
    # the simulated sensor averages 5 frames of the datasheet noise: the residuals show that level
    assert 0.8 < boot.noise_scale < 1.25
    assert boot.evaluations < 16 * 25  # warm-started and preconditioned: a few evaluations per refit
    hessian = {e.name: e for e in fit.estimates}
    for e in boot.estimates:
        assert e.value == hessian[e.name].value  # the fit's values; only their uncertainty is the bootstrap's
        low, high = e.interval95
        assert low < e.value < high and e.interval95 == boot.intervals["percentile"][e.name], e.name
        if e.name in ("E", "K"):  # nearly linear in the model: the spread is Gauss-Newton's within sampling error
            assert 0.6 < e.sigma / hessian[e.name].sigma < 1.6, e.name
    # basic interval: the percentile one reflected about the fit's value, in the log/logit coordinates
    theta = dict(zip(material_fit.PARAMETERS, fit.theta))
    for name in TRUTH:
        (p_low, p_high), (b_low, b_high) = boot.intervals["percentile"][name], boot.intervals["basic"][name]
        t_p = [float(material_fit.to_theta({**TRUTH, name: v}, material_fit.START)[list(TRUTH).index(name)])
               for v in (p_low, p_high, b_low, b_high)]
        assert t_p[2] == pytest.approx(2 * theta[name] - t_p[1], abs=1e-9)
        assert t_p[3] == pytest.approx(2 * theta[name] - t_p[0], abs=1e-9)


def test_a_parameter_the_data_do_not_determine_keeps_its_infinite_uncertainty_under_the_bootstrap(tmp_path):
    path = tmp_path / "wrench-plate.mcap"  # pressing on a flat face: K changes nothing
    write_synthetic_recording(path, "plate", TRUTH, ["press"] * 2, steps=5, seed=2, noise_scale=1.0)
    batches = replay_batches(path)
    fit = material_fit.fit_material(batches, "nh", ["E", "K"], substeps=1)
    boot = fit_bootstrap.bootstrap(fit, batches, "nh", ["E", "K"], draws=4, seed=0)
    estimates = {e.name: e for e in boot.estimates}
    assert estimates["E"].identified and math.isfinite(estimates["E"].sigma)
    assert not estimates["K"].identified and estimates["K"].sigma == math.inf
    assert estimates["K"].interval95 == (0.0, math.inf) and "K" not in boot.intervals["percentile"]
    assert not estimates["mu"].fitted


def test_the_bootstrap_refuses_too_few_draws_and_unknown_intervals():
    with pytest.raises(ValueError, match="at least 2 draws"):
        fit_bootstrap.bootstrap(None, [], "nh", ["E"], draws=1)
    with pytest.raises(ValueError, match="unknown bootstrap interval 'bca'"):
        fit_bootstrap.bootstrap(None, [], "nh", ["E"], draws=5, interval="bca")
    assert np.allclose(fit_bootstrap.theta_to_value("mu", np.array([0.0]), material_fit.START), 1.5)
