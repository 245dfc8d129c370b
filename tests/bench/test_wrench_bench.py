"""The wrench benchmark without devices: the benchmark objects' scenes and trajectories, the recording format, the
frame change of the measured wrench, and ``bench wrench`` on a recording whose "measurements" are an NH model's own
predictions at the FT 300's resolution (so NH must come out at that resolution and PFF, which carries no shear,
clearly worse)."""

from __future__ import annotations

import argparse
import json
import math

import numpy as np
import pytest
import torch
from mcap.reader import make_reader

from hydrosoft.bench import wrench, wrench_replay
from hydrosoft.drivers.poses import quat_to_matrix
from hydrosoft.bench.wrench_recording import (
    METADATA_NAME,
    TOPIC,
    RecordingInfo,
    WrenchRecordingWriter,
    WrenchSample,
    read_wrench_recording,
)
from hydrosoft.bench.wrench_scenes import (
    BENCH_OBJECTS,
    BUBBLE_RADII_M,
    DEPTH_RANGE_M,
    GAP_M,
    bench_object,
    press_and_shear,
    sample_press_and_shear,
    start_pose,
    wrench_scene,
)
from hydrosoft.dynamics import signed_distances
from hydrosoft.geometry import se3
from hydrosoft.scene import compile_scene

FT300_RESOLUTION = np.array([0.01, 0.01, 0.01, 0.001, 0.001, 0.001])  # N, N m per count
SPACING_M = 0.00625  # the sim plant's spacing with deploy/sim.toml


def test_every_object_rests_on_the_table_out_of_reach_of_the_bubble_at_the_start():
    for name, obj in BENCH_OBJECTS.items():
        spacing = 0.004
        model, state, _ = compile_scene(wrench_scene(name, spacing=spacing), prune=False)
        world = se3.transform_points(state.object_pose[0], model.points)
        # surface points are cell centres: on flat faces exactly, near a ridge or round side up to a cell inside
        assert -1e-9 <= float(world[:, 2].min()) <= spacing, name
        assert obj.top_z() - spacing <= float(world[:, 2].max()) <= obj.top_z() + 1e-9, name
        local = se3.transform_points(se3.inverse(state.body_poses[0, 0]), world)
        gap = float(signed_distances(model, local.view(1, 1, -1, 3)).min())
        assert GAP_M - 1e-9 <= gap <= GAP_M + spacing, name
        assert float(state.forces.abs().max()) == 0.0, name


def test_press_and_shear_presses_then_shears_and_twists_in_equal_steps():
    obj = bench_object("cube")
    rng = np.random.default_rng(0)
    trajectory = sample_press_and_shear(rng, 12, kind="shear_twist")
    poses = press_and_shear(obj, trajectory, origin=(0.4, 0.1, 0.0))
    assert poses.shape == (13, 7)
    np.testing.assert_allclose(poses[0], start_pose(obj, (0.4, 0.1, 0.0)))
    np.testing.assert_allclose(np.linalg.norm(poses[:, 3:], axis=1), 1.0)
    bottom = poses[trajectory.press_steps, 2] - BUBBLE_RADII_M[2]
    assert obj.top_z() - bottom == pytest.approx(trajectory.depth_m)
    assert DEPTH_RANGE_M[0] <= trajectory.depth_m <= DEPTH_RANGE_M[1]
    np.testing.assert_allclose(np.diff(poses[:trajectory.press_steps + 1, 2]),
                               -(GAP_M + trajectory.depth_m) / trajectory.press_steps)
    travel = poses[-1, :2] - poses[0, :2]
    assert np.linalg.norm(travel) == pytest.approx(trajectory.shear_m)
    assert math.atan2(travel[1], travel[0]) == pytest.approx(trajectory.direction_rad)
    assert 2 * math.atan2(poses[-1, 6], poses[-1, 3]) == pytest.approx(trajectory.twist_rad)
    assert np.all(poses[trajectory.press_steps:, 2] == poses[-1, 2])
    again = sample_press_and_shear(np.random.default_rng(0), 12, kind="shear_twist")
    assert again == trajectory
    with pytest.raises(ValueError, match="2 to 40 steps"):
        sample_press_and_shear(rng, 41)


def test_sensor_to_tcp_moves_a_wrench_to_the_tcp_frame():
    rng = np.random.default_rng(1)
    w_tcp = rng.normal(size=(5, 6))
    turn = rng.normal(size=4)
    tcp_in_sensor = np.concatenate([[0.01, -0.02, 0.12], turn / np.linalg.norm(turn)])
    R, p = quat_to_matrix(tcp_in_sensor[3:]), tcp_in_sensor[:3]
    f_sensor = w_tcp[:, :3] @ R.T
    m_sensor = w_tcp[:, 3:] @ R.T + np.cross(p, f_sensor)  # the same forces, about the sensor's origin
    np.testing.assert_allclose(wrench_replay.sensor_to_tcp(np.concatenate([f_sensor, m_sensor], 1), tcp_in_sensor), w_tcp,
                               atol=1e-12)
    identity = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
    np.testing.assert_allclose(wrench_replay.sensor_to_tcp(w_tcp, identity), w_tcp)


def _nh_recording(path, name: str, kinds, steps: int) -> list:
    """A recording of ``name`` whose wrenches are NH's own predictions (4 replay steps per recorded step), rounded to
    the FT 300's resolution."""
    obj = bench_object(name)
    rng = np.random.default_rng(7)
    params = [sample_press_and_shear(rng, steps, kind) for kind in kinds]
    bubbles = np.stack([press_and_shear(obj, p) for p in params])
    objects = np.broadcast_to(obj.pose(), bubbles.shape).copy()
    truth = wrench_replay.predict_tcp_wrenches(name, objects, bubbles, "nh", SPACING_M, substeps=4)
    measured = np.round(truth / FT300_RESOLUTION) * FT300_RESOLUTION
    info = RecordingInfo(object=name, config="test", mode="sim", tcp_in_sensor=(0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0),
                         plant_spacing_m=SPACING_M, seed=7, epoch_offset_ns=1_700_000_000_000_000_000,
                         trajectories=[{"kind": p.kind} for p in params], config_toml="mode = 'sim'\n")
    with WrenchRecordingWriter(path, info) as writer:
        for i, p in enumerate(params):
            for k in range(steps + 1):
                phase = "start" if k == 0 else "press" if k <= p.press_steps else "shear"
                writer.add(WrenchSample(object=name, trajectory=i, step=k, phase=phase, stamp_ns=1000 * k,
                                        bubble_pose=tuple(bubbles[i, k].tolist()),
                                        target_pose=tuple(bubbles[i, k].tolist()),
                                        object_pose=tuple(objects[i, k].tolist()),
                                        wrench=tuple(measured[i, k].tolist())))
    return params


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    folder = tmp_path_factory.mktemp("wrench")
    torch.set_num_threads(1)
    _nh_recording(folder / "wrench-cube.mcap", "cube", ["shear", "shear_twist", "twist"], 9)
    _nh_recording(folder / "wrench-cylinder_r25.mcap", "cylinder_r25", ["shear", "shear_twist"], 9)
    return folder


def test_a_recording_reads_back_and_standard_readers_decode_it(recordings):
    info, trajectories = read_wrench_recording(recordings / "wrench-cube.mcap")
    assert info.object == "cube" and info.mode == "sim" and info.plant_spacing_m == SPACING_M
    assert [t.index for t in trajectories] == [0, 1, 2]
    assert trajectories[0].bubble_poses.shape == (10, 7) and trajectories[0].wrenches.shape == (10, 6)
    assert trajectories[0].phases[0] == "start" and trajectories[0].phases[-1] == "shear"
    with (recordings / "wrench-cube.mcap").open("rb") as stream:
        reader = make_reader(stream)
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
        assert metadata[METADATA_NAME]["object"] == "cube"
        schema, channel, message = next(iter(reader.iter_messages(topics=[TOPIC])))
    assert schema.encoding == "jsonschema" and channel.message_encoding == "json"
    assert set(json.loads(schema.data)["required"]) <= set(json.loads(message.data))
    assert message.log_time == info.epoch_offset_ns  # the first sample's stamp_ns is 0


def test_a_truncated_or_foreign_file_is_refused_by_name(tmp_path):
    bad = tmp_path / "wrench-cube.mcap"
    bad.write_bytes(b"not an mcap file")
    with pytest.raises(ValueError, match="wrench-cube.mcap"):
        read_wrench_recording(bad)


def test_nh_reproduces_its_own_recording_and_pff_misses_the_shear(recordings):
    document = wrench.evaluate([recordings], ["nh", "pf", "pff"])
    rows = {(r["object"], r["model"]): r for r in document["rows"]}
    assert set(rows) == {(o, m) for o in ("cube", "cylinder_r25") for m in ("nh", "pf", "pff")}
    quantization_n = float(np.linalg.norm(FT300_RESOLUTION[:3]))  # every component off by at most half a count
    for name in ("cube", "cylinder_r25"):
        assert rows[name, "nh"]["force_n_mean"] < quantization_n
        assert rows[name, "nh"]["torque_nm_mean"] < 2e-3
        assert rows[name, "pff"]["shear_n_mean"] > 5 * rows[name, "nh"]["shear_n_mean"] + 0.05
        assert rows[name, "pf"]["force_n_mean"] > 5 * rows[name, "nh"]["force_n_mean"]
        assert rows[name, "nh"]["paper_force_n_mean"] == wrench.PAPER_TABLE_II[name]["nh"][0]
    per_trajectory = [t for t in document["trajectories"] if t["model"] in ("nh", "pff")]
    for t in [t for t in per_trajectory if t["model"] == "pff"]:
        nh = next(n for n in per_trajectory if n["model"] == "nh" and n["object"] == t["object"]
                  and n["trajectory"] == t["trajectory"])
        assert t["shear_n"] > nh["shear_n"] or t["torque_nm"] > nh["torque_nm"]
    assert [o["ours"][0] for o in document["ordering"]] == ["nh", "nh"]


def test_bench_wrench_prints_table_ii_with_the_papers_figures(recordings, capsys):
    args = argparse.Namespace(recordings=[recordings / "wrench-cube.mcap"], models=["nh", "pff"], spacing=None,
                              substeps=1, threads=1, json=False)
    assert wrench.run(args) == 0
    text = capsys.readouterr().out
    assert "Cube" in text and "paper" in text and "0.57" in text and "0.69" in text
    assert "same order" in text and "NH wins by construction" in text
    assert wrench.run(argparse.Namespace(**{**vars(args), "json": True})) == 0
    document = json.loads(capsys.readouterr().out)
    assert {r["model"] for r in document["rows"]} == {"nh", "pff"}


def test_bench_wrench_refuses_bad_options_and_missing_files(tmp_path, capsys):
    base = dict(recordings=[tmp_path], models=["nh"], spacing=None, substeps=1, threads=1, json=False)
    assert wrench.run(argparse.Namespace(**{**base, "models": ["nope"]})) == 2
    assert wrench.run(argparse.Namespace(**{**base, "substeps": 0})) == 2
    assert wrench.run(argparse.Namespace(**base)) == 2
    assert "no wrench-*.mcap" in capsys.readouterr().err
