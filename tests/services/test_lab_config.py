"""deploy/lab.toml: it loads, names only services that exist and real (not loopback) devices, and
``hydrosoft-stack check`` on a machine without the lab's devices reports each one as not answering, quickly, by
name, with exit status 1 and no traceback. The bubble camera refuses lab mode without its depth device or its
reference membrane file, naming the key and the command that captures one; ``hydrosoft-stack capture reference``
captures it from a recorded 16-bit stream through the real OpenCV driver."""

from __future__ import annotations

import argparse
import importlib.util
import ipaddress
import json
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from hydrosoft.drivers.bubble.reference import load_reference
from hydrosoft.drivers.bubble.render import to_counts
from hydrosoft.drivers.camera.config import CameraCalibration, CameraIntrinsics, save_calibration
from hydrosoft.services import bubble_camera
from hydrosoft.services.commands import check
from hydrosoft.services.commands import cli
from hydrosoft.services.bus.config import load_config

LAB_TOML = Path(__file__).parents[2] / "deploy" / "lab.toml"
CHECK_TIMEOUT_S = 60.0  # the command's own probes time out after 2 s each; this only catches a hang
CHECK_QUICK_S = 20.0  # what "quickly" means for a check of a machine without the lab's devices


def test_the_lab_config_loads_and_names_only_services_that_exist():
    config = load_config(LAB_TOML)
    assert config.mode == "lab"
    names = config.service_names()
    assert "sim_world" not in names
    for name in names:
        module = name.partition("-")[0]
        assert importlib.util.find_spec(f"hydrosoft.services.{module}") is not None, name
    for name in config.services:
        assert name in names


def test_the_lab_config_names_real_devices_and_absolute_files():
    config = load_config(LAB_TOML)
    for arm in config.arms:
        assert not ipaddress.ip_address(arm.ur_host).is_loopback, arm.ur_host
        assert arm.ft_port.startswith("/dev/"), arm.ft_port
    assert config.camera.device
    assert Path(config.camera.calibration).is_absolute()
    assert Path(config.run_dir).is_absolute() and not config.run_dir.startswith("/tmp")
    lo, hi = np.array(config.limits.workspace_min), np.array(config.limits.workspace_max)
    assert np.all(lo < hi) and lo[2] > 0.0  # the TCP box stays above the table top


def loopback_lab(tmp_path: Path, text: str) -> Path:
    """``text`` (a lab config) with its UR controller moved to a loopback address where nothing listens (tests
    talk to loopback only), written to ``tmp_path``."""
    path = tmp_path / "lab.toml"
    path.write_text(text.replace('ur_host = "192.168.1.10"', 'ur_host = "127.0.0.254"'))
    return path


def test_check_reports_every_lab_device_as_not_answering_here(tmp_path):
    tic = time.monotonic()
    path = loopback_lab(tmp_path, LAB_TOML.read_text())
    done = subprocess.run([sys.executable, "-m", "hydrosoft.services.commands.cli", "check", str(path), "--json"],
                          capture_output=True, text=True, timeout=CHECK_TIMEOUT_S)
    wall_s = time.monotonic() - tic
    assert done.returncode == 1, done.stderr
    assert "Traceback" not in done.stderr
    devices = {d["device"]: d for d in json.loads(done.stdout)["devices"]}
    config = load_config(LAB_TOML)
    expected = {"tag camera", "calibration"} | {f"{kind} {arm.name}" for arm in config.arms
                                                for kind in ("ur", "ft300", "depth")}
    assert set(devices) == expected
    for name, device in devices.items():
        assert not device["ok"], name
        assert device["detail"], name
    arm = config.arms[0]
    assert "127.0.0.254" in devices[f"ur {arm.name}"]["detail"]
    assert arm.ft_port in devices[f"ft300 {arm.name}"]["detail"]
    assert config.camera.calibration in devices["calibration"]["detail"]
    assert wall_s < CHECK_QUICK_S


def test_check_accepts_a_calibration_file_with_extrinsics(tmp_path, capsys):
    calibration = tmp_path / "tag_camera.toml"
    save_calibration(calibration, CameraCalibration(
        CameraIntrinsics(width=640, height=480, fx=610.0, fy=612.0, cx=320.0, cy=240.0, distortion=(0.0,) * 5),
        np.array([0.5, -0.2, 0.35, 0.376141, -0.778837, -0.451977, 0.218283])))
    text = LAB_TOML.read_text().replace('"/etc/hydrosoft/calibration/tag_camera.toml"', f'"{calibration}"')
    text = text.replace('ft_port = "/dev/robotiq_ft300"', f'ft_port = "{tmp_path / "no-ft300"}"')
    path = loopback_lab(tmp_path, text)
    assert check.run(argparse.Namespace(config=str(path), json=True)) == 1
    devices = {d["device"]: d for d in json.loads(capsys.readouterr().out)["devices"]}
    assert devices["calibration"]["ok"], devices["calibration"]
    assert "640x480" in devices["calibration"]["detail"]


LAB_DEPTH_DEVICE = 'device = "2"'
LAB_REFERENCE = 'reference = "/etc/hydrosoft/calibration/bubble_reference.npz"'


@pytest.mark.parametrize("change, text", [
    ((LAB_REFERENCE, 'reference = ""'), "arms.bubble.depth.reference: lab mode needs the captured reference"),
    ((LAB_REFERENCE, LAB_REFERENCE), "arms.bubble.depth.reference: /etc/hydrosoft/calibration/bubble_reference.npz: "
                                     "no such reference file"),
    ((LAB_DEPTH_DEVICE, 'device = ""'), "arms.bubble.depth.device: lab mode needs the depth camera's OpenCV source"),
])
def test_the_bubble_camera_refuses_lab_mode_without_its_device_or_reference(tmp_path, capsys, change, text):
    assert LAB_DEPTH_DEVICE in LAB_TOML.read_text() and LAB_REFERENCE in LAB_TOML.read_text()
    path = tmp_path / "lab.toml"
    path.write_text(LAB_TOML.read_text().replace(*change))
    assert bubble_camera.main([str(path)]) == 2
    err = capsys.readouterr().err
    assert text in err
    if "lab mode needs the captured reference" in text:
        assert "hydrosoft-stack capture reference CONFIG --arm bubble" in err


def test_capture_reference_writes_the_file_the_bubble_camera_then_uses(tmp_path, capsys):
    config = load_config(LAB_TOML)
    nominal = bubble_camera.BubbleDepth.nominal(config, "bubble").reference_m
    rng = np.random.default_rng(0)
    frames = [to_counts(nominal + rng.normal(0.0, 2e-4, nominal.shape), 1e-4) for _ in range(5)]
    video = tmp_path / "bubble.mkv"
    writer = cv2.VideoWriter(str(video), cv2.CAP_FFMPEG, cv2.VideoWriter_fourcc(*"FFV1"), 30.0, (160, 120),
                             [cv2.VIDEOWRITER_PROP_DEPTH, cv2.CV_16U, cv2.VIDEOWRITER_PROP_IS_COLOR, 0])
    for frame in frames:
        writer.write(frame)
    writer.release()
    reference = tmp_path / "bubble_reference.npz"
    path = tmp_path / "lab.toml"
    path.write_text(LAB_TOML.read_text().replace(LAB_DEPTH_DEVICE, f'device = "{video}"')
                    .replace(LAB_REFERENCE, f'reference = "{reference}"'))
    assert cli.main(["capture", "reference", str(path), "--arm", "bubble", "--frames", "5"]) == 0
    assert f"wrote {reference}: 160x120 px from 5 frames" in capsys.readouterr().out
    captured = load_reference(reference)
    assert captured.frames == 5 and captured.depth_scale_m == 1e-4
    assert np.abs(captured.reference_m - nominal).max() < 6e-4  # the median of 5 noisy frames
    pipeline = bubble_camera.BubbleDepth.for_mode(load_config(path), "bubble")
    np.testing.assert_array_equal(pipeline.reference_m, captured.reference_m)
    assert cli.main(["capture", "reference", str(path), "--arm", "bubble", "--frames", "6"]) == 1  # 5 in the file
    err = capsys.readouterr().err  # Stale first: a file's end takes 10 failed grabs, paced at fps
    assert err.startswith("capture reference: OpenCVDepthCamera(") and ("no new frame" in err or "ended" in err)
    # check reads one frame of the depth camera and loads its reference
    assert check.run(argparse.Namespace(config=str(loopback_lab(tmp_path, path.read_text())), json=True)) == 1
    depth = {d["device"]: d for d in json.loads(capsys.readouterr().out)["devices"]}["depth bubble"]
    assert depth["ok"] and "160x120 uint16" in depth["detail"] and str(reference) in depth["detail"], depth
    assert "Traceback" not in err
