"""The model benchmark runs (quick grid) and emits the documented schema with finite, positive figures.

No timing assertions: timings depend on the machine and its load.
"""

import argparse
import json
import math

import pytest

from hydrosoft.bench import model as bench_model

ROW_FIELDS = {"model", "dtype", "batch", "points", "substeps", "check_ms", "step_ms", "step_backward_ms",
              "substep_ms", "substep_backward_ms", "point_updates_per_s", "peak_mem_mb", "speedup_vs_eager_f64"}
ACCURACY_FIELDS = {"setting", "force_rel_error", "step_ms"}
PRUNING_FIELDS = {"task", "step_ms_full", "step_ms_pruned", "points_full", "points_pruned"}


@pytest.fixture(scope="module")
def quick_args():
    parser = argparse.ArgumentParser()
    bench_model.add_arguments(parser)
    args = parser.parse_args(["--quick", "--json", "--batches", "1,4", "--points", "100", "--threads", "1"])
    return args


def _run(args, capsys):
    assert bench_model.run(args) == 0
    out = capsys.readouterr().out
    return json.loads(out)


@pytest.mark.slow
def test_quick_bench_json_schema_and_values(quick_args, capsys):
    doc = _run(quick_args, capsys)
    assert set(doc) == {"config", "rows", "accuracy", "wrench", "object_update", "pruning", "point_sets",
                        "loop_tails", "drift"}
    assert doc["drift"] == []  # only when named
    assert doc["config"]["threads"] == 1 and doc["config"]["memory_method"]

    rows = doc["rows"]
    assert {(r["model"], r["dtype"], r["batch"]) for r in rows} == {
        (m, d, b) for m in ("nh", "snh", "pf", "pff") for d in ("float32", "float64") for b in (1, 4)}
    for r in rows:
        assert ROW_FIELDS <= set(r)
        assert r["mode"] == "eager" and r["bodies"] == 2
        for key in ("check_ms", "step_ms", "step_backward_ms", "substep_ms", "substep_backward_ms",
                    "point_updates_per_s", "peak_mem_mb", "speedup_vs_eager_f64"):
            assert math.isfinite(r[key]) and r[key] > 0, (key, r)
        # a step takes the sub-steps its contacts need; the update rate counts one contact update per sub-step
        assert isinstance(r["substeps"], int) and r["substeps"] >= 1
        assert math.isclose(r["point_updates_per_s"] * r["substep_ms"] / 1e3, r["batch"] * r["bodies"] * r["points"])
        if r["dtype"] == "float64":
            assert r["speedup_vs_eager_f64"] == 1.0

    accuracy = doc["accuracy"]
    assert accuracy[0]["setting"].startswith("reference") and accuracy[0]["force_rel_error"] == 0.0
    assert any(r["model"] == "snh" for r in accuracy) and any(r["dtype"] == "float32" for r in accuracy)
    for r in accuracy:
        assert ACCURACY_FIELDS <= set(r)
        assert math.isfinite(r["force_rel_error"]) and r["force_rel_error"] >= 0
        assert math.isfinite(r["step_ms"]) and r["step_ms"] > 0
        assert r["peak_force_n"] > 0
    # the float32 replay agrees with the float64 reference to far better than 1% (the stated float32 tolerance)
    assert next(r for r in accuracy if r["setting"] == "float32")["force_rel_error"] < 1e-2

    wrench = doc["wrench"]
    assert {(r["object"], r["dtype"], r["mode"]) for r in wrench} == {
        (o, d, "eager") for o in ("cube", "cylinder_r25") for d in ("float32", "float64")}
    for r in wrench:
        assert r["batch"] == 1 and r["points"] > 200 and math.isfinite(r["query_ms"]) and r["query_ms"] > 0
        # the bubble pressed 6 mm into the object pushes up on it; float32 gives the same force
        same = next(o for o in wrench if o["object"] == r["object"] and o["dtype"] == "float64")
        assert 0.5 < r["force_z_n"] < 10 and math.isclose(r["force_z_n"], same["force_z_n"], rel_tol=1e-5), r
    assert doc["config"]["drake_query_ms"] == [0.06, 0.2]

    pruning = doc["pruning"]
    assert {r["task"] for r in pruning} == {"pushing", "rotation", "rolling", "in_hand"}
    for r in pruning:
        assert PRUNING_FIELDS <= set(r)
        assert r["step_ms_full"] > 0 and r["step_ms_pruned"] > 0
        assert 0 < r["points_pruned"] <= r["points_full"]


def test_the_object_update_section_measures_both_updates_against_the_reference(quick_args, capsys):
    doc = _run(argparse.Namespace(**{**vars(quick_args), "sections": "object-update"}), capsys)
    rows = {(r["task"], r["epsilon_factor"], r["update"]): r for r in doc["object_update"]}
    assert {key[:2] for key in rows} == {("pushing", 1.0), ("pushing", 0.2)}
    for damping in (1.0, 0.2):
        explicit, implicit, finer = (rows[("pushing", damping, update)]
                                     for update in ("explicit", "linearly_implicit", "linearly_implicit x4"))
        assert implicit["substeps"] == 1 and finer["substeps"] == 4
        assert 0 < implicit["position_error_mm"] < 0.1 * implicit["motion_mm"]
        assert finer["position_error_mm"] < implicit["position_error_mm"]
        assert all(math.isfinite(r["step_ms"]) and r["step_ms"] > 0 for r in (explicit, implicit, finer))
    assert rows[("pushing", 0.2, "explicit")]["substeps"] > 3 * rows[("pushing", 1.0, "explicit")]["substeps"]


def test_the_point_sets_section_times_slices_against_gathers_of_the_same_forces(quick_args, capsys):
    doc = _run(argparse.Namespace(**{**vars(quick_args), "sections": "point-sets"}), capsys)
    (row,) = doc["point_sets"]
    assert row["batch"] == 8 and row["mode"] == "eager" and row["pairs"] == row["points"] == 132
    for key in ("forward_ms_slices", "forward_ms_gathers", "forward_backward_ms_slices", "forward_backward_ms_gathers"):
        assert math.isfinite(row[key]) and row[key] > 0
    assert math.isclose(row["forward_ratio"], row["forward_ms_slices"] / row["forward_ms_gathers"], rel_tol=1e-9)
    assert row["max_force_diff_n"] <= 1e-6  # float32: the same arithmetic, read two ways


def test_the_loop_tails_section_needs_compile_and_says_so(quick_args, capsys):
    assert bench_model.run(argparse.Namespace(**{**vars(quick_args), "sections": "loop-tails"})) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out)["loop_tails"] == []
    assert "loop-tails: skipped" in captured.err and "--compile" in captured.err


def test_the_drift_section_rolls_both_models_in_both_dtypes_and_float32_stays_on_float64(quick_args, capsys):
    """A short rollout (the long one is ``--drift-steps 1000``): the cylinder moves millimetres, and float32 ends
    within 1 um and 1e-5 rad of float64 for NH and nh_pressure_normal."""
    doc = _run(argparse.Namespace(**{**vars(quick_args), "sections": "drift", "drift_steps": 8}), capsys)
    assert {(r["model"], r["dtype"]) for r in doc["drift"]} == {
        (m, d) for m in ("nh", "nh_pressure_normal") for d in ("float32", "float64")}
    for r in doc["drift"]:
        assert r["steps"] == 8 and 2 < r["drift_mm"] < 8 and 0 < r["drift_rad"] < 0.4
        assert 0 <= r["f32_gap_um"] < 1 and 0 <= r["f32_gap_rad"] < 1e-5
        single = next(o for o in doc["drift"] if o["model"] == r["model"] and o["dtype"] == "float32")
        assert math.isclose(r["drift_mm"], single["drift_mm"], abs_tol=1e-3)


def test_drift_steps_below_one_are_refused(capsys):
    parser = argparse.ArgumentParser()
    bench_model.add_arguments(parser)
    assert bench_model.run(parser.parse_args(["--sections", "drift", "--drift-steps", "0"])) == 2
    assert "--drift-steps must be at least 1" in capsys.readouterr().err


def test_tables_without_json(capsys):
    parser = argparse.ArgumentParser()
    bench_model.add_arguments(parser)
    args = parser.parse_args(
        ["--quick", "--models", "nh", "--batches", "1", "--points", "100", "--sections", "rows,pruning,point-sets"])
    assert bench_model.run(args) == 0
    out = capsys.readouterr().out
    assert "step speed and memory" in out and "pruning" in out and "point sets" in out and "pose-to-wrench" not in out
    assert not out.lstrip().startswith("{")


def test_an_unknown_section_is_refused(capsys):
    parser = argparse.ArgumentParser()
    bench_model.add_arguments(parser)
    assert bench_model.run(parser.parse_args(["--quick", "--sections", "rows,wrenches"])) == 2
    assert "unknown section wrenches" in capsys.readouterr().err
