"""``bench plant`` on deploy/sim.toml's plant, eager only (the compiled mode compiles for 30-60 s; the end-to-end
stack test runs that plant)."""

from __future__ import annotations

import argparse
import json

from hydrosoft.services.benchmarks import plant


def bench(capsys, **options) -> tuple[int, dict | str]:
    """The exit status and the JSON summary (the error output when it failed)."""
    args = argparse.Namespace(**{"config": "deploy/sim.toml", "modes": "eager", "stroke_mm": 10.0, "json": True,
                                 **options})
    code = plant.run(args)
    out = capsys.readouterr()
    return code, json.loads(out.out) if code == 0 else out.err


def test_the_stroke_pushes_the_cube_and_every_tick_is_timed(capsys):
    code, summary = bench(capsys)
    assert code == 0
    (row,) = summary["rows"]
    assert row["mode"] == "eager" and row["ticks"] == 2 * 10 - plant.WARM_TICKS
    assert row["ms_per_tick"] > 0 and row["p95_ms"] >= row["ms_per_tick"]
    assert 1.0 < row["object_travel_mm"] < 10.0  # the bubble drags the cube, less far than it moves itself
    assert row["max_pose_diff"] == 0.0 and summary["speedup"] is None


def test_bad_options_exit_2_with_a_message(capsys):
    code, err = bench(capsys, modes="eager,jit")
    assert code == 2 and "unknown --modes ['jit']" in err
    code, err = bench(capsys, stroke_mm=1.0)
    assert code == 2 and "--stroke-mm must be at least" in err

