"""``hydrosoft-stack bench tracker --quick --json`` runs and prints one JSON document of rows with sane figures."""

import argparse
import json

import cv2
import numpy as np
import pytest

from hydrosoft.services.benchmarks.tracker import add_arguments, run


def parse(argv):
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    return parser.parse_args(argv)


def test_quick_json_rows(capsys):
    threads = cv2.getNumThreads()
    try:
        assert run(parse(["--quick", "--json", "--threads", "1"])) == 0
    finally:
        cv2.setNumThreads(threads)
    document = json.loads(capsys.readouterr().out)
    assert document["config"]["opencv_threads"] == 1
    rows = document["rows"]
    assert [(row["distance_m"], row["view_angle_deg"]) for row in rows] == [(0.3, 0.0), (0.3, 60.0), (1.0, 0.0),
                                                                            (1.0, 60.0)]
    for row in rows:
        assert row["images"] == 3 and 0.0 <= row["detection_rate"] <= 1.0
        for key in ("pos_err_mm_median", "pos_err_mm_p95", "pos_err_mm_max", "rot_err_deg_median",
                    "rot_err_deg_p95", "rot_err_deg_max", "tags_per_pose", "rejections", "render_ms", "track_ms",
                    "track_cpu_ms_mean", "track_cpu_ms_p95", "pos_err_mm_mean_base", "pos_err_mm_mean_camera"):
            assert key in row
        assert 0.0 < row["track_cpu_ms_mean"] and 0.0 < row["track_cpu_ms_p95"]
    near_oblique = rows[1]  # 0.3 m, 60 deg: two or three faces in view
    assert near_oblique["detection_rate"] == 1.0 and near_oblique["tags_per_pose"] >= 2
    assert near_oblique["pos_err_mm_max"] < 1.0 and near_oblique["rot_err_deg_max"] < 0.5
    signed = np.array(near_oblique["pos_err_mm_mean_camera"])  # mm, camera frame: within the largest error
    assert signed.shape == (3,) and np.all(np.abs(signed) <= near_oblique["pos_err_mm_max"])
    far_head_on = rows[2]  # 1 m straight down: one small tag seen head-on is ambiguous, so it is rejected
    assert far_head_on["detection_rate"] < 1.0 and "ambiguous" in far_head_on["rejections"]
    assert document["config"]["tag_size_m"] == 0.032
    cpu = document["track_cpu_ms"]
    assert cpu["images"] == 12 and 0.0 < cpu["mean"] and cpu["p95"] >= min(row["track_cpu_ms_p95"] for row in rows)
    assert document["config"]["sequence"]["images"] == 12 and document["config"]["sequence"]["full_frame_every"] == 10
    sequences = document["sequences"]
    assert [row["distance_m"] for row in sequences] == [0.3, 1.0]
    for row in sequences:  # 12 images: whole at the first and the eleventh, and at any fallback
        assert row["images"] == 12 and row["poses"] >= 10 and row["pose_mismatches"] == 0
        assert row["full_frame_searches"] >= 2 and row["region_searches"] >= 8
        assert row["max_pose_diff_mm"] == 0.0 and row["max_pose_diff_deg"] == 0.0  # the same corners, bit for bit
        assert 0.0 < row["roi_cpu_ms_mean"] and 0.0 < row["full_frame_cpu_ms_mean"]
    sequence_cpu = document["sequence_cpu_ms"]
    assert sequence_cpu["images"] == 24 and 0.0 < sequence_cpu["roi"]["mean"] <= sequence_cpu["roi"]["p95"]
    assert sequence_cpu["roi_to_full_frame"] == pytest.approx(sequence_cpu["roi"]["mean"] /
                                                              sequence_cpu["full_frame"]["mean"])
    assert document["config"]["pieces"] == {"config": "deploy/sim.toml", "images": 12}
    pieces = document["pieces"]
    assert set(pieces) == {"receive", "grey", "detect", "corners", "pose", "track"}
    for piece in pieces.values():
        assert 0.0 <= piece["mean"] <= piece["p95"]
    assert pieces["track"]["mean"] > max(pieces[name]["mean"] for name in ("grey", "detect", "corners", "pose"))


def test_bad_options_exit_with_status_2(capsys):
    assert run(parse(["--quick", "--distances", "0.3,x"])) == 2
    assert "--distances" in capsys.readouterr().err
    assert run(parse(["--quick", "--threads", "0"])) == 2
    assert "--threads" in capsys.readouterr().err
    assert run(parse(["--quick", "--angles", "95"])) == 2
