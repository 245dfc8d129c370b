"""``hydrosoft-stack bench control``: options, the JSON document, the Table III layout, the PNGs, progress."""

from __future__ import annotations

import argparse
import functools
import json
import math

import pytest
import torch

from hydrosoft.bench import control
from hydrosoft.dynamics import CompiledStep
from hydrosoft.tasks import evaluation
from hydrosoft.tasks.base import compiled_cost_terms

KEYS = {"task", "model", "loop", "error_mm_mean", "error_mm_std", "solve_ms", "success_rate", "goals"}


def parse(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    control.add_arguments(parser)
    return parser.parse_args(list(argv))


def test_defaults_are_the_paper_setting():
    args = parse()
    assert args.tasks == ["pushing", "rotation", "rolling", "in_hand"]
    assert args.models == ["nh", "pf", "pff"] and args.loops == ["open", "closed"]
    assert control.FULL["goals"] == 10 and control.FULL["samples"] == 64
    assert (control.FULL["horizon"], control.FULL["grad_steps"]) == (10, 2)


@pytest.mark.slow
def test_json_is_one_document_with_a_row_per_task_model_and_loop(tmp_path, capsys):
    args = parse("--tasks", "pushing,in_hand", "--models", "nh,pff", "--quick", "--steps", "1", "--goals", "2",
                 "--rate-solves", "1", "--json", "--out", str(tmp_path))
    assert control.run(args) == 0
    out, err = capsys.readouterr()
    document = json.loads(out)
    rows = document["rows"]
    assert len(rows) == 2 * 2 * 2 * 2
    assert {(r["plant"], r["task"], r["model"], r["loop"]) for r in rows} == {
        (p, t, m, loop) for p in ("finer", "same") for t in ("pushing", "in_hand") for m in ("nh", "pff")
        for loop in ("open", "closed")}
    for row in rows:
        assert KEYS <= row.keys() and row["goals"] == 2 and len(row["errors_mm"]) == 2
        assert row["error_mm_mean"] > 0 and row["error_mm_std"] >= 0 and 0 <= row["success_rate"] <= 1
        assert row["solve_ms"] > 0
    assert [rate["dtype"] for rate in document["replanning"]] == ["float64", "float32"]
    for rate in document["replanning"]:
        assert rate["samples"] == 64 and rate["horizon"] == 10 and rate["grad_steps"] == 2
        assert 150 <= rate["surface_points"] <= 250 and rate["pairs"] <= rate["points"] * 2 and rate["rate_hz"] > 0
        assert rate["solve_ms"] >= rate["rollout_ms"] + rate["backward_ms"]
        assert rate["compiled"] is False and rate["first_solve_ms"] > 0 and rate["sdf_solver_steps"] is None
        assert rate["warmup_solves_ms"] == [rate["first_solve_ms"]]  # one worker: one warm-up solve
        assert 0 < rate["median_solve_ms"] <= rate["slowest_solve_ms"]
        # a closed-loop cycle: the estimate (carrying the last prediction) and the prediction are timed with the solve
        assert rate["estimate_ms"] > 0 and rate["predict_ms"] > 0
        assert rate["solve_ms"] >= rate["rollout_ms"] + rate["backward_ms"] + rate["estimate_ms"] + rate["predict_ms"]
        assert len(rate["plan_costs"]) == rate["solves"] and all(0 <= cost < math.inf for cost in rate["plan_costs"])
    assert document["settings"]["compile"] is False
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in_hand.png", "pushing.png"]
    assert (tmp_path / "pushing.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "[32/32] same in_hand pff closed goal 1" in err


def test_the_rate_is_measured_per_bubble_solve_setting_in_one_run(tmp_path, capsys):
    args = parse("--tasks", "rotation", "--models", "nh", "--plants", "same", "--loops", "closed", "--quick",
                 "--steps", "1", "--goals", "1", "--rate-solves", "1", "--rate-dtypes", "float32",
                 "--rate-sdf-solver-steps", "converged,2", "--json", "--out", str(tmp_path))
    assert control.run(args) == 0
    rates = json.loads(capsys.readouterr().out)["replanning"]
    assert [(r["dtype"], r["sdf_solver_steps"]) for r in rates] == [("float32", None), ("float32", 2)]
    assert all(r["rate_hz"] > 0 for r in rates)
    assert control.run(parse("--rate-sdf-solver-steps", "two", "--out", str(tmp_path))) == 2
    assert "--rate-sdf-solver-steps" in capsys.readouterr().err


def test_the_rate_is_measured_per_worker_count_in_one_run_with_the_step_and_cost_calls_timed(tmp_path, capsys):
    assert control.run(parse("--tasks", "pushing", "--models", "nh", "--loops", "closed", "--plants", "same",
                             "--quick", "--steps", "1", "--goals", "1", "--rate-solves", "1", "--rate-samples", "16",
                             "--rate-dtypes", "float32", "--rate-workers", "1,2", "--rate-chunks", "4", "--json",
                             "--out", str(tmp_path))) == 0
    rates = json.loads(capsys.readouterr().out)["replanning"]
    assert [(r["workers"], r["samples"], r["chunks"]) for r in rates] == [(1, 16, 1), (2, 16, 4)]  # one: uncut
    assert [len(r["warmup_solves_ms"]) for r in rates] == [1, 2]  # two workers: a second, untimed warm-up solve
    for r in rates:
        assert 0 < r["step_forward_ms"] and 0 < r["cost_forward_ms"] and r["rate_hz"] > 0
    # one worker: the step's and the costs' forward calls lie within the rollouts (the rest is the CEM's own work)
    assert rates[0]["step_forward_ms"] + rates[0]["cost_forward_ms"] <= rates[0]["rollout_ms"]
    assert control.run(parse("--rate-workers", "0", "--out", str(tmp_path))) == 2
    assert "--rate-workers" in capsys.readouterr().err
    assert control.run(parse("--rate-chunks", "four", "--out", str(tmp_path))) == 2
    assert "--rate-chunks" in capsys.readouterr().err
    for bad in ("2", "half"):
        assert control.run(parse("--rate-activation-budgets", bad, "--out", str(tmp_path))) == 2
        assert "--rate-activation-budgets" in capsys.readouterr().err


def test_the_rate_is_measured_per_sample_count_on_the_named_device_in_one_run(tmp_path, capsys):
    """``--rate-samples`` gives one replanning row per sample count, ``--device cpu`` (the default) names the CPU in
    each, and ``--rate-only`` runs no episode (no rows, no figures); a device that is not a torch device, worker
    processes with a GPU, and fewer samples than elites are refused (exit 2) before anything runs."""
    assert control.run(parse("--rate-only", "--rate-solves", "1", "--rate-dtypes", "float32",
                             "--rate-samples", "16,32", "--device", "cpu", "--json", "--out", str(tmp_path))) == 0
    document = json.loads(capsys.readouterr().out)
    assert document["rows"] == [] and document["settings"]["pngs"] == [] and not any(tmp_path.iterdir())
    rates = document["replanning"]
    assert [(r["samples"], r["device"], r["gpu_memory_mib"]) for r in rates] == [(16, "cpu", None), (32, "cpu", None)]
    assert all(r["rate_hz"] > 0 and r["step_forward_ms"] > 0 for r in rates)
    for argv, text in ((("--device", "tpu"), "not a torch device"), (("--rate-samples", "4"), "--rate-samples"),
                       (("--device", "cuda", "--rate-worker-kinds", "processes"), "--device cuda")):
        assert control.run(parse(*argv, "--out", str(tmp_path))) == 2
        assert text in capsys.readouterr().err


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks a machine without CUDA")
def test_a_gpu_rate_on_a_machine_without_cuda_is_refused_with_the_reason(tmp_path, capsys):
    assert control.run(parse("--device", "cuda", "--out", str(tmp_path))) == 2
    assert "--device cuda: CUDA is not available on this machine" in capsys.readouterr().err


@pytest.mark.slow
def test_the_rate_is_measured_with_worker_threads_and_worker_processes_alike(tmp_path, capsys):
    """The same loop with its two shares on threads and in processes of their own: the same plans, bit for bit (the
    same arithmetic per row); the step and cost calls are not timed where they run in other processes. (B = 16 in two
    shares of 8, and the quick planner's one-step episode: the same path as B = 64's, for less CPU.)"""
    assert control.run(parse("--tasks", "pushing", "--models", "nh", "--loops", "closed", "--plants", "same",
                             "--quick", "--steps", "1", "--goals", "1", "--rate-solves", "2", "--rate-samples", "16",
                             "--rate-dtypes", "float32", "--rate-workers", "2", "--rate-worker-kinds",
                             "threads,processes", "--json", "--out", str(tmp_path))) == 0
    threads, processes = json.loads(capsys.readouterr().out)["replanning"]
    assert (threads["worker_kind"], processes["worker_kind"]) == ("threads", "processes")
    assert threads["samples"] == processes["samples"] == 16
    assert processes["plan_costs"] == threads["plan_costs"] and all(math.isfinite(c) for c in threads["plan_costs"])
    assert processes["step_forward_ms"] is None and threads["step_forward_ms"] > 0
    assert processes["rate_hz"] > 0 and processes["rollout_ms"] > 0 and processes["backward_ms"] > 0
    assert control.run(parse("--rate-worker-kinds", "fibers", "--out", str(tmp_path))) == 2
    assert "--rate-worker-kinds" in capsys.readouterr().err


def test_the_rate_is_measured_per_object_update_and_the_episodes_plan_with_the_chosen_one(tmp_path, capsys):
    assert control.run(parse("--tasks", "pushing", "--models", "nh", "--loops", "closed", "--plants", "same",
                             "--quick", "--steps", "1", "--goals", "1", "--rate-solves", "1", "--rate-dtypes",
                             "float32", "--object-update", "linearly_implicit", "--rate-object-updates",
                             "explicit,linearly_implicit", "--json", "--out", str(tmp_path))) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["settings"]["object_update"] == "linearly_implicit"
    assert report["rows"][0]["errors_mm"][0] >= 0
    rates = report["replanning"]
    assert [(r["object_update"], r["substeps"]) for r in rates] == [("explicit", 3), ("linearly_implicit", 1)]
    assert all(r["rate_hz"] > 0 for r in rates)
    assert control.run(parse("--object-update", "implicit", "--out", str(tmp_path))) == 2
    assert "--object-update" in capsys.readouterr().err
    assert control.run(parse("--object-update", "linearly_implicit", "--models", "pf", "--out", str(tmp_path))) == 2
    assert "NH or SNH" in capsys.readouterr().err


def test_table_is_laid_out_like_table_iii(tmp_path, capsys):
    args = parse("--tasks", "rotation", "--models", "nh", "--quick", "--steps", "1", "--rate-solves", "0",
                 "--out", str(tmp_path))
    assert control.run(args) == 0
    out = capsys.readouterr().out
    assert "Non-holonomic" in out and "OL Error [mm]" in out and "CL Error [mm]" in out
    line = next(line for line in out.splitlines() if line.startswith("Planar Rotation"))
    assert len(line.split("|")[1].split()) == 4  # OL mean, std, CL mean, std
    assert "replanning rate" not in out


def test_table_cells_of_four_digits_stay_apart():
    row = {"plant": "finer", "task": "rotation", "model": "pf", "solve_ms": 1.0, "rollout_ms": 1.0,
           "backward_ms": 0.0, "cem_ms": 0.0, "success_rate": 1.0, "statuses": {"reached": 1}}
    rows = [{**row, "loop": "open", "error_mm_mean": 6.21, "error_mm_std": 1.59},
            {**row, "loop": "closed", "error_mm_mean": 0.109, "error_mm_std": 0.0582}]
    line = next(line for line in control._table(rows, ["pf"]).splitlines() if line.startswith("Planar Rotation"))
    assert line.split("|")[1].split() == ["6.21", "1.59", "0.109", "0.0582"]


def test_unknown_names_are_refused(tmp_path, capsys):
    assert control.run(parse("--tasks", "juggling", "--out", str(tmp_path))) == 2
    assert control.run(parse("--models", "rigid", "--out", str(tmp_path))) == 2
    assert control.run(parse("--rate-dtypes", "float16", "--out", str(tmp_path))) == 2
    assert "juggling" in capsys.readouterr().err
    assert not tmp_path.exists() or not any(tmp_path.iterdir())


@pytest.mark.slow
def test_compile_option_runs_the_planner_and_the_rate_through_compiled_steps(tmp_path, capsys, monkeypatch):
    """Wiring only: dynamo's ``eager`` backend stands in for inductor (whose C++ compile takes minutes)."""
    monkeypatch.setattr(evaluation, "CompiledStep", functools.partial(CompiledStep, backend="eager"))
    monkeypatch.setattr(evaluation, "compiled_cost_terms", functools.partial(compiled_cost_terms, backend="eager"))
    args = parse("--tasks", "pushing", "--models", "nh", "--loops", "closed", "--quick", "--steps", "1", "--goals",
                 "1", "--rate-solves", "1", "--rate-dtypes", "float32", "--compile", "--sdf-solver-steps", "3",
                 "--rate-costs", "compiled,eager", "--out", str(tmp_path))
    try:
        assert control.run(args) == 0
    finally:
        torch._dynamo.reset()
    out = capsys.readouterr().out
    assert "float32" in out and "sub-steps, bubble SDF in 3 solver steps, 1 thread(s), " in out
    assert "replanning rate on cpu, closed-loop planar pushing" in out
    assert ("1 solver worker(s) (threads), the samples in 1 chunk(s), explicit object update, activation budget 0, "
            "compiled costs, compiled:") in out
    assert "explicit object update, activation budget 0, compiled:" in out  # --rate-costs eager
    assert "compiling the step" in out
