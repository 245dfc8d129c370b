"""The material fit's pose offset (``fit --pose-offset``): a synthetic recording whose object poses are all 0.1 mm
too low, as a tracker with a constant error reports a still object, biases E out of its 95 % interval; fitting the
offset jointly recovers it within its interval and E's interval then holds the truth. With no offset in the data
the option does not bias E, and a pure press determines the offset along the press normal only."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hydrosoft.bench import fit, material_fit
from hydrosoft.bench.fit import format_tables, run_fit
from hydrosoft.bench.synthetic_wrench import write_synthetic_recording
from hydrosoft.bench.wrench_replay import load_recordings
from hydrosoft.services.commands.cli import build_parser

from fit_recordings import TRUTH

LOW_M = -1e-4  # every recorded object pose this far below the true one (base z, the press normal)


def _holds(interval, value) -> bool:
    low, high = interval
    return low <= value <= high


def test_a_constant_pose_offset_biases_e_out_of_its_interval_unless_it_is_fitted(tmp_path):
    path = tmp_path / "wrench-cube.mcap"
    write_synthetic_recording(path, "cube", TRUTH, ["shear", "twist", "shear_twist", "shear"], steps=12, seed=1,
                              noise_scale=1.0, pose_offset_m=(0.0, 0.0, LOW_M))
    plain = run_fit([path], "nh", ["E", "K", "mu"], holdout=0.0, substeps=1)
    assert plain["pose_offset"] is None
    assert not _holds(plain["parameters"]["E"]["interval95"], TRUTH["E"])  # the problem: a confident, wrong E
    joint = run_fit([path], "nh", ["E", "K", "mu"], holdout=0.0, substeps=1, pose_offset="xyz")
    for name, true in TRUTH.items():
        assert _holds(joint["parameters"][name]["interval95"], true), name
    z = joint["pose_offset"]["offset_z"]  # the offset that moves the recorded poses back onto the true ones
    assert z["identified"] and _holds(z["interval95"], -LOW_M) and z["interval95"][0] > 0
    assert joint["fit"]["cost"] < plain["fit"]["cost"]
    assert "offset_z +0.0" in format_tables(joint) and joint["settings"]["pose_offset"]
    with pytest.raises(ValueError, match="--pose-offset"):
        run_fit([path], "nh", ["E"], holdout=0.0, uncertainty="bootstrap", pose_offset="xyz")


def test_with_no_offset_in_a_pure_press_the_option_leaves_e_unbiased_and_finds_only_the_normal_offset(tmp_path):
    path = tmp_path / "wrench-plate.mcap"
    write_synthetic_recording(path, "plate", TRUTH, ["press"] * 3, steps=8, seed=2, noise_scale=1.0)
    groups = load_recordings([path])
    batches = material_fit.replay_batches(groups, {(g.object, t.index) for g in groups for t in g.trajectories})
    result = material_fit.fit_material(batches, "nh", ["E"], substeps=1, pose_offset="xyz")
    E = result.estimates[0]
    assert E.identified and _holds(E.interval95, TRUTH["E"])
    x, y, z = result.pose_offset
    assert z.identified and _holds(z.interval95, 0.0) and z.sigma < 1e-4
    # along a flat face that is only pressed nothing moves tangentially: the prior, not the data, sets x and y
    for axis in (x, y):
        assert not axis.identified and axis.sigma > 0.25 * material_fit.POSE_OFFSET_PRIOR_M
    assert result.theta.shape == (6,) and result.offset_m == [x.value, y.value, z.value]
    normal = material_fit.fit_material(batches, "nh", ["E"], substeps=1, pose_offset="z")  # the press normal alone
    assert [e.fitted for e in normal.pose_offset] == [False, False, True] and normal.offset_m[:2] == [0.0, 0.0]
    assert normal.estimates[0].identified and _holds(normal.estimates[0].interval95, TRUTH["E"])
    assert _holds(normal.pose_offset[2].interval95, 0.0)


def test_the_fit_command_takes_pose_offset_and_refuses_it_with_the_bootstrap_with_exit_code_2(tmp_path, capsys):
    path = tmp_path / "wrench-cube.mcap"
    write_synthetic_recording(path, "cube", TRUTH, ["press"], steps=4, seed=3)
    parser = build_parser()
    assert not parser.parse_args(["fit", str(path)]).pose_offset
    assert parser.parse_args(["fit", str(path), "--pose-offset", "z"]).pose_offset == "z"
    args = parser.parse_args(["fit", str(path), "--pose-offset", "--uncertainty", "bootstrap", "--holdout", "0"])
    assert args.pose_offset == "xyz" and fit.run(args) == 2
    assert "--pose-offset works with --uncertainty hessian or profile only" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # an argparse error, exit code 2, naming the axes it takes
        parser.parse_args(["fit", "--pose-offset", str(path)])
    assert "some of xyz" in capsys.readouterr().err


def test_a_gauss_newton_step_to_a_finer_replay_that_raises_the_cost_is_replaced_by_a_refit(tmp_path):
    # on a push at one depth E and a depth offset are nearly one direction: the linear step overshoots
    path = tmp_path / "wrench-plate.mcap"
    write_synthetic_recording(path, "plate", TRUTH, ["press"] * 2, steps=6, seed=5, noise_scale=1.0)
    groups = load_recordings([path])
    batches = material_fit.replay_batches(groups, {(g.object, t.index) for g in groups for t in g.trajectories})
    theta = material_fit.to_theta(TRUTH, material_fit.START)
    mask = torch.tensor([True, False, False])

    def cost(t):
        return float(material_fit.residuals(t, batches, "nh", material_fit.START, 2).square().mean())

    moved = material_fit._move_to_finer_replay(theta, mask, np.array([2.0]), np.array([[1e-4]]), 1.0, batches, "nh",
                                               material_fit.START, 2, 30, [], None)
    assert cost(moved) <= cost(theta) and abs(float(moved[0] - theta[0])) < 0.05  # refitted, not E x e^2
    good = material_fit._move_to_finer_replay(theta, mask, np.array([0.0]), np.array([[1e-4]]), 1.0, batches, "nh",
                                              material_fit.START, 2, 30, [], None)
    assert torch.equal(good, theta)  # a step that does not raise the cost is taken as it is


def test_a_refit_on_a_cost_with_steps_stops_when_it_stalls_and_returns_the_best_point(monkeypatch):
    # the offset's cost steps where it moves the object by nanometres: L-BFGS's line search then keeps finding
    # "lower" points by a hair and runs to its evaluation cap; the stall rule stops it and keeps the best point
    def stepped(theta, batches, contact, start, substeps):
        ripple = 0.05 * torch.remainder(torch.floor(theta * 1e7), 2).detach()
        return torch.cat([theta - 0.5, 0.5 * (theta - 0.5) ** 2, 0.1 * torch.sin(3 * theta), ripple])

    monkeypatch.setattr(material_fit, "residuals", stepped)
    mask, start, scale = torch.tensor([True, True, True]), torch.zeros(3, dtype=torch.float64), 100.0
    runs = {}
    for stall in (None, material_fit.STALL_EVALUATIONS):
        evaluations = []
        theta = material_fit.minimise(start, mask, [], "nh", material_fit.START, 1, evaluations=evaluations,
                                      preconditioner=np.eye(3), cost_scale=scale, stall_evaluations=stall)
        runs[stall] = len(evaluations), float(stepped(theta, [], "", {}, 1).square().mean()), min(evaluations)
    (plain, plain_cost, _), (stalled, stalled_cost, best) = runs[None], runs[material_fit.STALL_EVALUATIONS]
    assert plain >= 1.25 * material_fit.DEFAULT_MAX_ITERATIONS  # L-BFGS alone: to its evaluation cap
    assert stalled < plain / 3 and stalled_cost == best  # stopped early, at the best point it evaluated
    assert scale * (stalled_cost - plain_cost) < material_fit.STALL_COST  # as good, within the rule's tolerance
