"""The noise benchmark's synthetic tracker noise: the recorded object poses carry the asked noise, the plant's
wrenches do not change with it (the same seed gives the same wrench noise), and ``--pose-noise`` takes MM,DEG; each
seed's ``z_linear``, the noise's share of the fit's error, and its summaries."""

from __future__ import annotations

import argparse

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from hydrosoft.bench import fit_noise
from hydrosoft.bench.synthetic_wrench import tracked_poses, write_synthetic_recording
from hydrosoft.bench.wrench_recording import read_wrench_recording

TRUTH = {"E": 3e5 * 1.7, "K": 1e5 * 0.6, "mu": 0.35}


def test_tracked_poses_carry_the_asked_position_and_rotation_noise():
    truth = np.tile(np.r_[0.1, -0.2, 0.025, Rotation.from_rotvec([0, 0, 0.7]).as_quat(scalar_first=True)], (5000, 1))
    tracked = tracked_poses(truth, np.random.default_rng(0), position_m=2e-4, rotation_rad=1e-3)
    np.testing.assert_allclose((tracked[:, :3] - truth[:, :3]).std(axis=0), 2e-4, rtol=0.05)
    turn = Rotation.from_quat(tracked[:, 3:], scalar_first=True) * Rotation.from_quat(truth[:, 3:],
                                                                                      scalar_first=True).inv()
    np.testing.assert_allclose(turn.as_rotvec().std(axis=0), 1e-3, rtol=0.05)
    assert (np.sum(tracked[:, 3:] * truth[:, 3:], axis=1) > 0).all()  # the recorded hemisphere


def test_pose_noise_changes_the_recorded_poses_only_and_the_option_takes_mm_and_deg(tmp_path):
    plain, noisy = tmp_path / "wrench-cube-a.mcap", tmp_path / "wrench-cube-b.mcap"
    write_synthetic_recording(plain, "cube", TRUTH, ["shear"], steps=3, seed=5, noise_scale=1.0)
    write_synthetic_recording(noisy, "cube", TRUTH, ["shear"], steps=3, seed=5, noise_scale=1.0,
                              pose_noise=(1e-3, 0.0))
    (_, [a]), (_, [b]) = read_wrench_recording(plain), read_wrench_recording(noisy)
    np.testing.assert_array_equal(a.wrenches, b.wrenches)
    np.testing.assert_array_equal(a.bubble_poses, b.bubble_poses)
    offsets = b.object_poses[:, :3] - a.object_poses[:, :3]
    assert 1e-4 < np.abs(offsets).mean() < 3e-3 and np.allclose(a.object_poses[:, 3:], b.object_poses[:, 3:])
    parser = argparse.ArgumentParser()
    fit_noise.add_arguments(parser)
    assert parser.parse_args(["--pose-noise", "0.2,0.05"]).pose_noise == (0.2, 0.05)
    for bad in ("0.2", "x,1", "-1,0"):
        with pytest.raises(SystemExit):
            parser.parse_args(["--pose-noise", bad])


def test_the_plant_and_replay_substeps_are_options_and_bad_ones_are_refused(capsys):
    parser = argparse.ArgumentParser()
    fit_noise.add_arguments(parser)
    args = parser.parse_args(["--plant-substeps", "1", "--substeps", "1", "--no-recovery"])
    assert (args.plant_substeps, args.substeps, args.no_recovery) == (1, 1, True)
    assert parser.parse_args([]).plant_substeps is None and parser.parse_args([]).substeps is None
    for option in ("--plant-substeps", "--substeps"):
        assert fit_noise.run(parser.parse_args([option, "0"])) == 2
        assert f"{option} must be at least 1" in capsys.readouterr().err


def test_each_seed_gives_the_error_its_noise_alone_makes_through_the_linearised_fit(monkeypatch):
    monkeypatch.setattr(fit_noise, "KINDS", ("shear", "twist", "shear_twist"))
    monkeypatch.setattr(fit_noise, "STEPS", 6)
    document = fit_noise.evaluate(1, first_seed=1, plant_substeps=1, substeps=1, recovery=False, profile=True)
    for row in document["noisy"]:  # E is linear in its interval: the fit's error is the noise's linear share
        z, z_linear = row["E"]["z"], row["E"]["z_linear"]
        assert z_linear != 0 and abs(z - z_linear) < 0.05 * max(1, abs(z))
        # and the profile's z at the truth is the same: the cost rises as the quadratic says
        assert abs(row["E"]["profile"]["z"] - z) < 0.05 * max(1, abs(z))
        assert row["profile"]["evaluations"] > 0 and row["evaluations"] > row["profile"]["evaluations"] / 10
    for name in fit_noise.TRUTH:  # the profile interval holds the truth where its z there is within Z95
        assert document["covered_by"]["profile"][name] == sum(
            abs(row[name]["profile"]["z"]) <= 1.959964 for row in document["noisy"])
        assert document["mean_square_z_profile"][name] == pytest.approx(document["noisy"][0][name]["profile"]["z"] ** 2)
    table = fit_noise.format_table(document)
    assert "Truth inside the 95 % interval (profile, seeds 1-1)" in table and "profiles at the truth" in table
    for name in fit_noise.TRUTH:
        z = [row[name]["z_linear"] for row in document["noisy"]]
        assert document["mean_square_z_linear"][name] == pytest.approx(z[0] ** 2)
        assert document["covered_linear"][name] == sum(abs(x) <= 1.959964 for x in z)
