"""Profile-likelihood intervals of the material fit: where the cost is quadratic they are Gauss-Newton's, where it
rises more slowly on one side (a stick/slip switch) they widen on that side only, a side that never rises far
enough is open, a parameter the data do not determine keeps its infinite verdict, and a value lies in the interval
exactly where its signed root is within Z95; with a pose offset the offset is refitted at each profile point."""

from __future__ import annotations

import math

import pytest
import torch

from hydrosoft.bench import fit_profile, material_fit
from hydrosoft.bench.material_fit import Z95
from hydrosoft.bench.synthetic_wrench import write_synthetic_recording

from fit_recordings import TRUTH, noisy_cube_fit, replay_batches


class KinkedProfile:
    """A profile with Gauss-Newton sigma ``sigma`` at ``theta`` 0 whose signed root rises with slope ``1 / sigma``
    below and ``slopes_above / sigma`` above (a kink at ``theta``, as where slip stops), capped at ``cap``."""

    def __init__(self, sigma: float, slope_above: float, cap: float = math.inf) -> None:
        self.theta = torch.zeros(3, dtype=torch.float64)
        self._sigma, self.slope_above, self.cap, self.calls = sigma, slope_above, cap, 0

    def sigma(self, index):
        return self._sigma

    def signed_root(self, index, t):
        self.calls += 1
        w = t / self._sigma * (self.slope_above if t > 0 else 1.0)
        return math.copysign(min(abs(w), self.cap), w)


def test_the_search_finds_gauss_newtons_end_where_the_cost_is_quadratic_and_widens_only_a_flatter_side():
    cost, points = KinkedProfile(sigma=0.1, slope_above=0.5), []
    low = fit_profile.profile_end(cost, 1, -1, points)
    assert low == pytest.approx(-Z95 * 0.1, abs=fit_profile.ROOT_TOLERANCE * 0.1) and len(points) == 1
    points = []
    high = fit_profile.profile_end(cost, 1, 1, points)  # half the slope: twice as far, where Gauss-Newton stops at 1
    assert high == pytest.approx(2 * Z95 * 0.1, abs=fit_profile.ROOT_TOLERANCE * 0.2)
    assert abs(abs(points[-1][1]) - Z95) <= fit_profile.ROOT_TOLERANCE and len(points) <= 3
    # a side whose cost never rises by the chi-square's quantile (the data stop telling) is open
    points = []
    assert fit_profile.profile_end(KinkedProfile(0.1, 1.0, cap=1.5), 0, 1, points) is None
    assert len(points) <= fit_profile.MAX_POINTS and points[-1][0] <= fit_profile.MAX_REACH_SIGMA * 0.1 + 1e-12
    # mu's search stops at its logit bound
    assert fit_profile._reach("mu", 1, 30.0, 1.0) == pytest.approx(material_fit.MU_BOUND_LOGIT - 30.0)
    assert fit_profile._reach("mu", -1, 30.0, 0.1) == pytest.approx(fit_profile.MAX_REACH_SIGMA * 0.1)


def test_on_a_noisy_recording_the_profile_matches_gauss_newton_for_e_and_its_ends_and_roots_agree(tmp_path):
    batches, fit = noisy_cube_fit(tmp_path)
    reported = []
    profile = fit_profile.profile_intervals(fit, batches, "nh", list(TRUTH),
                                            progress=lambda name, points, seconds: reported.append(name))
    assert reported == list(TRUTH) and not profile.open and profile.evaluations > 0
    hessian = {e.name: e for e in fit.estimates}
    for e in profile.estimates:
        assert e.value == hessian[e.name].value and e.sigma == hessian[e.name].sigma  # only the interval changes
        low, high = e.interval95
        assert low < e.value < high, e.name
        gn_low, gn_high = hessian[e.name].interval95
        if e.name == "E":  # E is linear in the model: the profile's interval is Gauss-Newton's
            assert low == pytest.approx(gn_low, rel=2e-3) and high == pytest.approx(gn_high, rel=2e-3)
        ends = [t for t, w in profile.points[e.name] if abs(abs(w) - Z95) <= fit_profile.ROOT_TOLERANCE]
        assert len(ends) >= 2, e.name  # each side ended on a point where the cost rose by Z95^2 noise variances
    # a value lies in the interval exactly where its signed root is within Z95: just past its upper end it is over
    beyond = {e.name: e.interval95[1] * 1.02 for e in profile.estimates}
    roots, evaluations = fit_profile.signed_roots(fit, batches, "nh", list(TRUTH), beyond)
    assert all(w > Z95 for w in roots.values()) and evaluations > 0


def test_a_parameter_the_data_do_not_determine_keeps_its_infinite_uncertainty_under_the_profile(tmp_path):
    path = tmp_path / "wrench-plate.mcap"  # pressing on a flat face: K changes nothing
    write_synthetic_recording(path, "plate", TRUTH, ["press"] * 2, steps=5, seed=2, noise_scale=1.0)
    batches = replay_batches(path)
    fit = material_fit.fit_material(batches, "nh", ["E", "K"], substeps=1)
    profile = fit_profile.profile_intervals(fit, batches, "nh", ["E", "K"])
    estimates = {e.name: e for e in profile.estimates}
    assert estimates["E"].identified and math.isfinite(estimates["E"].sigma)
    assert 0 < estimates["E"].interval95[0] < estimates["E"].value < estimates["E"].interval95[1] < math.inf
    assert not estimates["K"].identified and estimates["K"].interval95 == (0.0, math.inf) and "K" not in profile.points
    assert not estimates["mu"].fitted


def test_with_a_pose_offset_the_profile_refits_it_so_e_holds_the_truth_with_about_gauss_newtons_width(tmp_path):
    path = tmp_path / "wrench-plate.mcap"  # every recorded object pose 0.1 mm too low, as a tracker's constant error
    write_synthetic_recording(path, "plate", TRUTH, ["press"] * 2, steps=5, seed=2, noise_scale=1.0,
                              pose_offset_m=(0.0, 0.0, -1e-4))
    batches = replay_batches(path)
    fit = material_fit.fit_material(batches, "nh", ["E"], substeps=1, pose_offset="z")
    profile = fit_profile.profile_intervals(fit, batches, "nh", ["E"])
    E, joint = profile.estimates[0], fit.estimates[0]
    low, high = E.interval95
    assert low < TRUTH["E"] < high and not profile.open
    # the offset was refitted at each point: E's interval is about the joint Gauss-Newton one (E and a depth offset
    # are nearly linear on a press), not the far narrower one of the offset held, which misses the truth
    assert (low, high) == pytest.approx(joint.interval95, rel=0.01)
    held = material_fit.fit_material(batches, "nh", ["E"], substeps=1).estimates[0]
    assert held.interval95[0] > TRUTH["E"] and high - low > 2 * (held.interval95[1] - held.interval95[0])
    assert profile.estimates[1:] == fit.estimates[1:]  # K and mu held
    offset_z = fit.pose_offset[2]  # Gauss-Newton's, as fitted
    assert offset_z.identified and offset_z.interval95[0] < 1e-4 < offset_z.interval95[1]
