"""``hydrosoft-stack bench tradeoff``: the sweep runs, the Pareto front is right, one JSON document and a PNG."""

from __future__ import annotations

import argparse
import json

import pytest

from hydrosoft.bench import tradeoff


def parse(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    tradeoff.add_arguments(parser)
    return parser.parse_args(list(argv))


def test_pareto_front_keeps_only_undominated_settings():
    points = [{"label": "a", "solve_ms": 1, "error_mm": 5}, {"label": "b", "solve_ms": 2, "error_mm": 2},
              {"label": "c", "solve_ms": 3, "error_mm": 3}, {"label": "d", "solve_ms": 4, "error_mm": 1},
              {"label": "e", "solve_ms": 1, "error_mm": 6}]
    assert [p["label"] for p in tradeoff.pareto(points)] == ["a", "b", "d"]


def test_quick_sweep_prints_one_json_document_and_a_png(tmp_path, capsys):
    assert tradeoff.run(parse("--quick", "--steps", "1", "--json", "--out", str(tmp_path))) == 0
    out, err = capsys.readouterr()
    document = json.loads(out)
    labels = {p["label"] for p in document["points"]}
    assert {"base", "samples=8", "grad_steps=0", "dtype=float32", "model=snh", "model=nh_pressure_normal"} <= labels
    assert len(labels) == len(document["points"])  # the base setting is run once
    assert set(document["pareto"]) <= labels and document["pareto"]
    assert all(p["solve_ms"] > 0 and p["error_mm"] > 0 for p in document["points"])
    assert (tmp_path / "tradeoff.png").read_bytes()[:4] == b"\x89PNG"
    assert "rotation" in err


def test_compile_option_compiles_every_setting():
    assert not parse().compile and tradeoff._settings("samples", 8, parse("--compile").compile).compile
    assert tradeoff._settings("dtype", "float32").compile is False


def test_settings_option_runs_only_the_named_rows_in_that_order(tmp_path, capsys):
    args = parse("--quick", "--settings", "model=nh_pressure_normal,base", "--steps", "1", "--json",
                 "--out", str(tmp_path))
    assert tradeoff.run(args) == 0
    points = json.loads(capsys.readouterr().out)["points"]
    assert [p["label"] for p in points] == ["model=nh_pressure_normal", "base"]
    assert points[0]["knob"] == "model" and points[0]["value"] == "nh_pressure_normal" and points[1]["knob"] == "base"


def test_an_unknown_setting_is_refused_with_the_known_ones(tmp_path, capsys):
    assert tradeoff.run(parse("--quick", "--settings", "base,model=pff", "--out", str(tmp_path))) == 2
    err = capsys.readouterr().err
    assert "model=pff" in err and "model=nh_pressure_normal" in err


def test_unknown_task_is_refused(tmp_path):
    assert tradeoff.run(parse("--tasks", "juggling", "--out", str(tmp_path))) == 2


@pytest.mark.slow
def test_goals_option_averages_every_setting_over_that_many_goals(tmp_path, capsys):
    args = parse("--quick", "--settings", "base,samples=8", "--goals", "2", "--steps", "1", "--json",
                 "--out", str(tmp_path))
    assert tradeoff.run(args) == 0
    document = json.loads(capsys.readouterr().out)
    assert document["goals"] == 2 and len(document["points"]) == 2
    assert all(p["episodes"] == 2 and p["error_mm_sem"] >= 0 for p in document["points"])


def test_the_solver_steps_knob_reaches_the_planner_bodies():
    from hydrosoft.tasks import make_task
    from hydrosoft.tasks.evaluation import prepare

    settings = tradeoff._settings("sdf_solver_steps", 2)
    setup = prepare(make_task("pushing"), settings)
    assert setup.planner_model.bodies[0].solver_steps == 2
    assert setup.plant.model.bodies[0].solver_steps is None  # the plant keeps the converged solve
