"""``hydrosoft-stack fit`` as a command: it prints the fitted values and bench wrench's tables, writes TOML a scene
takes, leaves the recordings as they were, and refuses bad options and recordings that lack what it needs, naming
them."""

from __future__ import annotations

import argparse
import datetime
import hashlib
import json
import tomllib

import pytest
import torch

from hydrosoft.bench import fit
from hydrosoft.bench.synthetic_wrench import IDENTITY, write_synthetic_recording
from hydrosoft.bench.wrench_recording import RecordingInfo, WrenchRecordingWriter, WrenchSample
from hydrosoft.scene import BodySpec
from hydrosoft.services.commands.cli import build_parser

from fit_recordings import TRUTH


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    torch.set_num_threads(1)
    path = tmp_path_factory.mktemp("fit") / "wrench-cube.mcap"
    write_synthetic_recording(path, "cube", TRUTH, ["press", "press", "press"], steps=6, seed=4)
    return path


def _args(recordings, **options):
    args = build_parser().parse_args(["fit", *map(str, recordings), "--params", "E", "--holdout", "0.34"])
    return argparse.Namespace(**{**vars(args), **options})


def _digest(path):
    return hashlib.sha256(path.read_bytes()).hexdigest(), path.stat().st_mtime_ns


def test_fit_prints_values_and_tables_writes_toml_a_scene_takes_and_leaves_the_recording_alone(recording, tmp_path,
                                                                                                capsys):
    before = _digest(recording)
    out = tmp_path / "bubble.toml"
    assert fit.run(_args([recording], out=out)) == 0
    captured = capsys.readouterr()
    assert "E   5.1" in captured.out and "(held, not fitted)" in captured.out
    assert "Trajectories  |    before     |     after" in captured.out and "held-out (1)" in captured.out
    assert "[fit] evaluation 1: cost" in captured.err and f"wrote {out}" in captured.err
    values = tomllib.loads(out.read_text())["arms"]["material"]
    assert set(values) == {"E"} and values["E"] == pytest.approx(TRUTH["E"], rel=0.01)
    BodySpec(name="bubble", sdf="ellipsoid", E=values["E"], K=1e5, mu=0.9)  # a scene's body takes it
    assert _digest(recording) == before

    assert fit.run(_args([recording.parent], json=True, params=["E", "K"])) == 0
    document = json.loads(capsys.readouterr().out)
    assert document["parameters"]["K"]["identified"] is False and document["parameters"]["K"]["sigma"] is None
    assert [(r["set"], r["when"]) for r in document["rows"]] == [("fit", "before"), ("fit", "after"),
                                                                  ("held_out", "before"), ("held_out", "after")]
    toml = fit.params_toml(document, datetime.date(2026, 11, 27))
    assert "# K: NOT identified" in toml and "2026-11-27" in toml
    assert set(tomllib.loads(toml)["arms"]["material"]) == {"E"}
    assert _digest(recording) == before


def _write(path, wrench=(0.0, 0.0, 1.0, 0.0, 0.0, 0.0), steps=3):
    info = RecordingInfo(object="cube", config="test", mode="lab", tcp_in_sensor=IDENTITY, plant_spacing_m=None,
                         seed=0, epoch_offset_ns=0)
    pose = (0.0, 0.0, 0.09, 1.0, 0.0, 0.0, 0.0)
    with WrenchRecordingWriter(path, info) as writer:
        for k in range(steps):
            writer.add(WrenchSample(object="cube", trajectory=0, step=k, phase="start" if k == 0 else "press",
                                    stamp_ns=k, bubble_pose=pose, target_pose=pose,
                                    object_pose=(0.0, 0.0, 0.025, 1.0, 0.0, 0.0, 0.0), wrench=wrench))


def test_fit_refuses_bad_options_and_recordings_that_lack_what_it_needs_naming_them(recording, tmp_path, capsys):
    cases = []
    nan = tmp_path / "wrench-nan.mcap"
    _write(nan, wrench=(0.0, 0.0, float("nan"), 0.0, 0.0, 0.0))
    cases.append(([nan], {}, "wrench-nan.mcap: not a wrench benchmark recording: Expected `float`, got `null`"))
    tare_only = tmp_path / "wrench-tare.mcap"
    _write(tare_only, steps=1)
    cases.append(([tare_only], {}, "wrench-tare.mcap: trajectory 0 has only its tare sample"))
    foreign = tmp_path / "wrench-foreign.mcap"
    foreign.write_bytes(b"not an mcap file")
    cases.append(([foreign], {}, "wrench-foreign.mcap: not a wrench benchmark recording"))
    cases.append(([tmp_path / "missing.mcap"], {}, "missing.mcap: no such recording"))
    cases.append(([recording], {"model": "pff"}, "unknown contact model 'pff'"))
    cases.append(([recording], {"params": ["E", "G"]}, "unknown parameter(s) ['G']"))
    cases.append(([recording], {"holdout": 1.5}, "holdout must be a fraction"))
    cases.append(([recording], {"out": recording}, "--out must name a .toml file"))
    cases.append(([recording], {"substeps": 0}, "--substeps must be at least 1"))
    cases.append(([recording], {"uncertainty": "bootstrap", "draws": 1}, "--draws must be at least 2, got 1"))
    before = _digest(recording)
    for recordings, options, message in cases:
        assert fit.run(_args(recordings, **options)) == 2, message
        assert message in capsys.readouterr().err
    assert _digest(recording) == before


def test_fit_fits_the_pressure_field_model_too(recording, capsys):
    assert fit.run(_args([recording], model="pf", json=True)) == 0
    document = json.loads(capsys.readouterr().out)
    rows = {(r["set"], r["when"]): r for r in document["rows"]}
    assert document["model"] == "pf" and document["parameters"]["E"]["identified"]
    assert rows["held_out", "after"]["force_n_mean"] < 0.5 * rows["held_out", "before"]["force_n_mean"]


def test_fit_reports_a_parametric_bootstrap_with_progress_when_asked(recording, tmp_path, capsys):
    out = tmp_path / "bubble.toml"
    assert fit.run(_args([recording], json=True, params=["E", "K"], uncertainty="bootstrap", draws=3, out=out)) == 0
    captured = capsys.readouterr()
    document = json.loads(captured.out)
    assert "[fit] bootstrap refit 3/3 at" in captured.err
    assert document["uncertainty_method"] == "bootstrap" and document["uncertainty"].startswith("parametric bootstrap")
    boot = document["bootstrap"]
    assert boot["draws"] == 3 and boot["interval"] == "percentile"
    E, K = document["parameters"]["E"], document["parameters"]["K"]
    assert E["interval95"] == boot["intervals95"]["percentile"]["E"] and E["identified"]
    assert K["sigma"] is None and not K["identified"]  # undetermined on a flat face: the bootstrap cannot say more
    assert "parametric bootstrap of 3 draws" in out.read_text()
    assert fit.run(_args([recording], uncertainty="bootstrap", draws=2)) == 0
    assert "(uncertainty: parametric bootstrap of 2 draws, percentile intervals" in capsys.readouterr().out


def test_fit_reports_profile_likelihood_intervals_with_progress_when_asked(recording, tmp_path, capsys):
    out = tmp_path / "bubble.toml"
    assert fit.run(_args([recording], json=True, params=["E", "K"], uncertainty="profile", out=out)) == 0
    captured = capsys.readouterr()
    document = json.loads(captured.out)
    assert "[fit] profile of E: " in captured.err and "profile of K" not in captured.err
    assert document["uncertainty_method"] == "profile" and document["uncertainty"].startswith("profile likelihood")
    profile, E, K = document["profile"], document["parameters"]["E"], document["parameters"]["K"]
    assert profile["evaluations"] > 0 and profile["open"] == [] and document["bootstrap"] is None
    low, high = E["interval95"]
    assert low < E["value"] < high and E["identified"]
    # E is linear in the model: its profile interval is Gauss-Newton's, which the document keeps beside it
    assert [low, high] == pytest.approx(profile["hessian_interval95"]["E"], rel=2e-3)
    assert K["sigma"] is None and not K["identified"]  # undetermined on a flat face: no profile to follow
    assert "profile-likelihood intervals, Gauss-Newton sigma" in out.read_text()
