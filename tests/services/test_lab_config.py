"""deploy/lab.toml: it loads, names only services that exist and real (not loopback) devices, and
``hydrosoft-stack check`` on a machine without the lab's devices reports each one as not answering, quickly, by
name, with exit status 1 and no traceback."""

from __future__ import annotations

import argparse
import importlib.util
import ipaddress
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from hydrosoft.drivers.camera.config import CameraCalibration, CameraIntrinsics, save_calibration
from hydrosoft.services import check
from hydrosoft.services.config import load_config

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


def test_check_reports_every_lab_device_as_not_answering_here():
    tic = time.monotonic()
    done = subprocess.run([sys.executable, "-m", "hydrosoft.services.cli", "check", str(LAB_TOML), "--json"],
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
    assert arm.ur_host in devices[f"ur {arm.name}"]["detail"]
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
    text = text.replace('ur_host = "192.168.1.10"', 'ur_host = "127.0.0.254"')  # nothing listens there
    path = tmp_path / "lab.toml"
    path.write_text(text)
    assert check.run(argparse.Namespace(config=str(path), json=True)) == 1
    devices = {d["device"]: d for d in json.loads(capsys.readouterr().out)["devices"]}
    assert devices["calibration"]["ok"], devices["calibration"]
    assert "640x480" in devices["calibration"]["detail"]
