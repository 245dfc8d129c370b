"""``hydrosoft-stack collect wrench`` in sim mode: the real UR driver (ur_rtde) and the real FT 300 driver, against the
plant process's simulated controller and FT 300 pty, record a tiny benchmark (2 objects, 2 trajectories, 5 steps)
that ``bench wrench`` then reads; a force over the limit stops the collection; a target outside the workspace is
refused before anything starts.

The collector runs as its own process in its own session (its plant process is its child); teardown kills that
session's processes by the collector's pid. Each test uses a private run_dir and a 127.0.0.N of its own.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from hydrosoft.bench import wrench
from hydrosoft.bench.wrench_recording import TOPIC, read_wrench_recording
from hydrosoft.bench.wrench_scenes import bench_object
from hydrosoft.drivers.robotiq_ft300.noise import frame_noise, quantized
from hydrosoft.services.commands import cli
from hydrosoft.services.commands.collect import plant_origin, settle_change
from hydrosoft.services.bus.config import load_config
from loopback import free_ur_host
from stack_process import quick_planner

SIM_TOML = Path(__file__).parents[3] / "deploy" / "sim.toml"
COLLECT_TIMEOUT_S = 240.0  # two plant start-ups and 2 x 2 x 6 samples take ~25 s; a loaded machine is slower
SIM_FT_BIAS = np.asarray(load_config(SIM_TOML).sim.ft_bias)  # the simulated FT 300's zero-load offset (N, N m)


def free_loopback_host() -> str:
    """A free 127.0.0.N for this module's simulated UR controllers (``loopback.free_ur_host``)."""
    return free_ur_host(190, 60)


def private_config(tmp_path: Path, **replacements: str) -> Path:
    run_dir = tmp_path / "run"
    text = quick_planner(SIM_TOML.read_text())  # the quick planner's 12.5 mm spacing: a 6.25 mm plant
    text = text.replace('"/tmp/hydrosoft-sim/ft300-bubble"', f'"{run_dir}/ft300-bubble"')
    text = text.replace('"/tmp/hydrosoft-sim"', f'"{run_dir}"').replace('"127.0.0.2"', f'"{free_loopback_host()}"')
    for old, new in replacements.items():
        assert old in text
        text = text.replace(old, new)
    path = tmp_path / "sim.toml"
    path.write_text(text)
    return path


def collect(config: Path, out: Path, *options: str,
            timeout_s: float = COLLECT_TIMEOUT_S) -> subprocess.CompletedProcess:
    """Run the collector to its end in its own session; on a timeout, kill the session's processes by its pid."""
    proc = subprocess.Popen([sys.executable, "-m", "hydrosoft.services.commands.cli", "collect", "wrench", str(config),
                             "--out", str(out), *options], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        stdout, stderr = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        stdout, stderr = proc.communicate()
        pytest.fail(f"collect wrench did not finish within {timeout_s} s:\n{stderr[-4000:]}")
    finally:
        try:
            os.killpg(proc.pid, signal.SIGKILL)  # the plant, should the collector have left it behind
        except ProcessLookupError:
            pass
    return subprocess.CompletedProcess(proc.args, proc.returncode, stdout, stderr)


@pytest.fixture(scope="module")
def tiny_collection(tmp_path_factory):
    tmp_path = tmp_path_factory.mktemp("collect")
    out = tmp_path / "out"
    # noise off: the checks below are on the plant's wrench to the FT 300's resolution (the settle test below has it)
    config = private_config(tmp_path, **{"ft_noise = 1.0": "ft_noise = 0.0"})
    done = collect(config, out, "--objects", "cube,plate", "--trajectories", "2", "--steps", "5")
    return done, out


def test_a_tiny_sim_collection_records_every_step_through_the_real_drivers(tiny_collection):
    done, out = tiny_collection
    assert done.returncode == 0, done.stderr[-4000:]
    assert done.stdout.split() == [str(out / "wrench-cube.mcap"), str(out / "wrench-plate.mcap")]
    for name in ("cube", "plate"):
        info, trajectories = read_wrench_recording(out / f"wrench-{name}.mcap")
        assert info.object == name and info.mode == "sim" and info.plant_spacing_m == pytest.approx(0.00625)
        assert "127.0.0." in info.config_toml and len(info.trajectories) == 2
        assert [t.index for t in trajectories] == [0, 1]
        for t in trajectories:
            assert t.phases[0] == "start" and len(t.phases) == 6 and t.phases[-1] == "shear"
            np.testing.assert_allclose(t.object_poses, np.broadcast_to(bench_object(name).pose(), (6, 7)))
            np.testing.assert_allclose(t.bubble_poses[:, :3], t.target_poses[:, :3], atol=2e-4)
            # out of contact: the simulated FT 300's zero-load offset (sim.ft_bias), to its resolution
            assert np.all(np.abs(t.wrenches[0] - SIM_FT_BIAS) < 0.02), t.wrenches[0]
            pressed = t.wrenches[[i for i, phase in enumerate(t.phases) if phase != "start"]]
            assert np.all(pressed[:, 2] > 0.1)  # pressing down on the object reads +Fz for an upright TCP
    with (out / "wrench-cube.mcap").open("rb") as stream:
        schema, channel, message = next(iter(make_reader(stream).iter_messages(topics=[TOPIC])))
    assert schema.encoding == "jsonschema" and channel.message_encoding == "json"
    assert json.loads(message.data)["phase"] == "start"


def test_bench_wrench_on_the_sim_collection_finds_nh_exact_and_pff_missing_the_shear(tiny_collection):
    done, out = tiny_collection
    assert done.returncode == 0, done.stderr[-4000:]
    document = wrench.evaluate([out], ["nh", "pff"])
    per = {(t["object"], t["model"], t["trajectory"]): t for t in document["trajectories"]}
    nh = [t for t in document["trajectories"] if t["model"] == "nh"]
    pff = [per[t["object"], "pff", t["trajectory"]] for t in nh]
    # The plant is NH: what is left is the FT 300's resolution (0.01 N, 0.001 N m: ~0.006 N on an idle machine). On a
    # heavily loaded host the real-time plant can run so late that a sample (or a trajectory's tare) misses it, so the
    # bound is on the median trajectory; the shear and twist PFF cannot carry are 0.3-2 N and 0.01-0.05 N m.
    assert np.median([t["force_n"] for t in nh]) < 0.03 and np.median([t["torque_nm"] for t in nh]) < 3e-3, nh
    wins = [p["shear_n"] > n["shear_n"] + 0.1 or p["torque_nm"] > n["torque_nm"] + 0.01 for n, p in zip(nh, pff)]
    assert sum(wins) >= len(wins) - 1, (nh, pff)
    for name in ("cube", "plate"):
        rows = {r["model"]: r for r in document["rows"] if r["object"] == name}
        assert rows["nh"]["force_n_mean"] < rows["pff"]["force_n_mean"]


def test_a_wrench_at_rest_settles_through_the_ft300_noise_and_a_noise_free_one_within_two_counts():
    rng = np.random.default_rng(3)
    rest = np.array([1.2, -0.8, 2.5, 0.04, -0.03, 0.02])
    windows = quantized(rest + frame_noise(rng, (2000, 2, 5, 6))).mean(axis=2)  # two 5-frame windows, 2000 times
    settled = np.all(np.abs(windows[:, 1] - windows[:, 0]) <= settle_change(1.0), axis=1)
    assert settled.mean() > 0.99, settled.mean()
    np.testing.assert_allclose(settle_change(0.0), [0.02] * 3 + [0.002] * 3)
    creeping = windows[:, 1] + [0.5, 0, 0, 0, 0, 0]  # the membrane still loading by 0.5 N
    assert not np.all(np.abs(creeping - windows[:, 0]) <= settle_change(1.0), axis=1).any()


def test_a_force_over_the_limit_stops_the_collection(tmp_path):
    config = private_config(tmp_path, **{"max_force_n = 40.0": "max_force_n = 0.3",
                                         "release_force_n = 30.0": "release_force_n = 0.2"})
    done = collect(config, tmp_path / "out", "--objects", "cube", "--trajectories", "1", "--steps", "4")
    assert done.returncode == 1
    assert "contact force" in done.stderr and "above the limit 0.3 N" in done.stderr
    assert "the arm was stopped" in done.stderr
    info, trajectories = read_wrench_recording(tmp_path / "out" / "wrench-cube.mcap")
    assert info.object == "cube" and trajectories == []  # only complete trajectories are written


def test_a_target_outside_the_workspace_is_refused_before_anything_starts(tmp_path, capsys):
    config = private_config(tmp_path)
    command = ["collect", "wrench", str(config), "--out", str(tmp_path / "out"), "--objects", "cube",
               "--trajectories", "1", "--steps", "4"]
    assert cli.main([*command, "--object-at", "0.2,0,0"]) == 1
    err = capsys.readouterr().err
    assert "outside the workspace box" in err and "--object-at" in err
    assert not (tmp_path / "out").exists()
    assert not (tmp_path / "run").exists()  # no plant was started


def test_the_sim_plant_clamps_the_object_off_object_at_by_the_clamp_error_the_recording_does_not_see():
    args = cli.build_parser().parse_args(["collect", "wrench", str(SIM_TOML), "--out", "out", "--object-at",
                                          "0.01,0,0", "--sim-clamp-error", "0,0.0002,-0.0001"])
    assert plant_origin(args) == pytest.approx((0.01, 0.0002, -0.0001)) and args.object_at == (0.01, 0.0, 0.0)
    plain = cli.build_parser().parse_args(["collect", "wrench", str(SIM_TOML), "--out", "out"])
    assert plant_origin(plain) == plain.object_at == (0.0, 0.0, 0.0)


def test_bad_options_are_refused_with_exit_status_2(tmp_path, capsys):
    command = ["collect", "wrench", str(private_config(tmp_path)), "--out", str(tmp_path / "out")]
    for options, text in ((("--objects", "sphere"), "unknown ['sphere']"), (("--steps", "41"), "--steps"),
                          (("--trajectories", "0"), "--trajectories"), (("--hold-s", "-1"), "--hold-s")):
        assert cli.main([*command, *options]) == 2
        assert text in capsys.readouterr().err
    lab = tmp_path / "lab.toml"
    lab.write_text((Path(__file__).parents[3] / "deploy" / "lab.toml").read_text())
    assert cli.main(["collect", "wrench", str(lab), "--out", str(tmp_path / "out"), "--objects", "cube,plate"]) == 2
    assert "one object per run" in capsys.readouterr().err
    # the sim plant's clamp error exists in sim only, and within 2 mm per axis
    assert cli.main(["collect", "wrench", str(lab), "--out", str(tmp_path / "out"), "--objects", "cube",
                     "--sim-clamp-error", "0,0,-0.0001"]) == 2
    assert "--sim-clamp-error: the sim plant's clamp only" in capsys.readouterr().err
    assert cli.main([*command, "--sim-clamp-error", "0,0,0.003"]) == 2
    assert "--sim-clamp-error must be within 2 mm" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
