"""``hydrosoft-stack check``: every device a config names is probed; simulated devices answer, missing ones are
named in a FAIL line; the arm is never commanded."""

from __future__ import annotations

import argparse
import json
import os
import selectors
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hydrosoft.drivers.robotiq_ft300.simulator import SimulatedFT300
from hydrosoft.services.commands import check

SIM_TOML = Path(__file__).parents[2] / "deploy" / "sim.toml"
READY_TIMEOUT_S = 15.0
HOST = f"127.0.0.{130 + os.getpid() % 60}"


def config_for(tmp_path: Path, host: str, ft_port: Path) -> Path:
    text = SIM_TOML.read_text().replace('"127.0.0.2"', f'"{host}"')
    text = text.replace('"/tmp/hydrosoft-sim/ft300-bubble"', f'"{ft_port}"').replace('"/tmp/hydrosoft-sim"', f'"{tmp_path}"')
    path = tmp_path / "check.toml"
    path.write_text(text)
    return path


def run_check(path: Path, capsys) -> tuple[int, dict]:
    code = check.run(argparse.Namespace(config=str(path), json=True))
    return code, json.loads(capsys.readouterr().out)


@pytest.fixture
def ur_simulator():
    proc = subprocess.Popen([sys.executable, "-m", "hydrosoft.drivers.ur.simulator", "--host", HOST],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        with selectors.DefaultSelector() as selector:
            selector.register(proc.stdout, selectors.EVENT_READ)
            assert selector.select(READY_TIMEOUT_S), "UR simulator not ready"
            assert "ready" in proc.stdout.readline()
        yield proc
    finally:
        proc.terminate()
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)
        proc.stdout.close()


def test_simulated_devices_answer(tmp_path, capsys, ur_simulator):
    ft = SimulatedFT300(wrench_source=lambda: np.array([0.5, 0.0, -2.0, 0.0, 0.0, 0.01]), link=tmp_path / "ft").start()
    try:
        code, document = run_check(config_for(tmp_path, HOST, tmp_path / "ft"), capsys)
    finally:
        ft.stop()
    devices = {d["device"]: d for d in document["devices"]}
    assert code == 0, devices
    assert devices["ur bubble"]["ok"] and "RTDE streams" in devices["ur bubble"]["detail"]
    assert devices["ft300 bubble"]["ok"] and "-2.00" in devices["ft300 bubble"]["detail"]
    stats = ft.stats()
    assert stats.start_requests >= 1 and stats.stop_bursts >= 1  # the probe left the stream stopped


def test_missing_devices_are_named_and_fail(tmp_path, capsys):
    code, document = run_check(config_for(tmp_path, "127.0.0.254", tmp_path / "no-such-port"), capsys)
    devices = {d["device"]: d for d in document["devices"]}
    assert code == 1
    assert not devices["ur bubble"]["ok"] and "127.0.0.254" in devices["ur bubble"]["detail"]
    assert not devices["ft300 bubble"]["ok"] and "no-such-port" in devices["ft300 bubble"]["detail"]


def test_a_bad_config_is_refused_with_the_key(tmp_path, capsys):
    path = tmp_path / "bad.toml"
    path.write_text('arms = [{ name = "bubble" }]\n[limits]\nmax_speed_m_s = 0\n')
    assert check.run(argparse.Namespace(config=str(path), json=False)) == 2
    assert "limits.max_speed_m_s" in capsys.readouterr().err
