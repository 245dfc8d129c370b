"""A stack split across two hosts, simulated on loopback with the real launcher over fake services: one config,
``launch --host robot`` on one address and ``launch --host compute`` on another, CURVE forced on loopback, each
host with its own key pair and run_dir. Each launcher runs its host's services only; ``status`` from either host
shows every service of both; a peer with an unauthorised key that connects to every inter-host endpoint receives
nothing, and every service counts its refusals."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import msgspec
import pytest
from fakes.stack_run import LauncherRun, remove_tree, short_run_root, wait_until, write_config
from loopback import free_loopback_address

from hydrosoft.services.bus import sockets as b
from hydrosoft.services.commands import keys
from hydrosoft.services.bus.config import ENDPOINT_KINDS, HOST_ENV, load_config

DEPLOY = Path(__file__).parents[2] / "deploy"

#: The hosts' tcp ports start here (three per service, see services/bus/config.py).
FIRST_PORT = 5600
#: Longest a status call may take here, s (its window plus a Python start on a busy machine).
STATUS_TIMEOUT_S = 30.0
#: How long the intruder listens to show that nothing reaches it, s (the fakes publish at 20 Hz).
LISTEN_S = 1.5
ROBOT_SERVICES = ["sim_world", "arm_commander-a", "ft_reader-a", "bubble_camera-a", "tag_tracker"]


@pytest.fixture
def root():
    path = short_run_root()
    yield path
    remove_tree(path)


def two_host_config(root) -> tuple:
    """The split config in ``root`` (hosts on two free 127.0.0.N), and the intruder's secret key file."""
    ports = range(FIRST_PORT, FIRST_PORT + len(ENDPOINT_KINDS) * (len(ROBOT_SERVICES) + 1))
    robot = free_loopback_address(21, 39, ports)
    compute = free_loopback_address(21, 39, ports, taken=(robot,))
    authorized = root / "authorized"
    authorized.mkdir()
    tables = ""
    for name, address, services in (("robot", robot, ROBOT_SERVICES), ("compute", compute, ["planner"])):
        public, secret = keys.generate_key_pair(root / name, name)
        (authorized / public.name).write_bytes(public.read_bytes())
        tables += (f'[hosts.{name}]\naddress = "{address}"\nservices = {json.dumps(services)}\n'
                   f'first_port = {FIRST_PORT}\npublic_key_file = "{public}"\nsecret_key_file = "{secret}"\n'
                   f'run_dir = "{root}/{name}-run"\n\n')
    _, intruder = keys.generate_key_pair(root / "intruder", "intruder")
    curve = f'[curve]\nsecret_key_file = "{root}/robot/robot.key_secret"\nauthorized_keys_dir = "{authorized}"\n' \
            'loopback = true\n\n'
    return write_config(root, ["a"], curve + tables), intruder


def run_status(config, host: str) -> dict:
    result = subprocess.run([sys.executable, "-m", "hydrosoft.services.commands.status", str(config), "--json", "--wait", "4"],
                            capture_output=True, text=True, timeout=STATUS_TIMEOUT_S,
                            env={**os.environ, HOST_ENV: host})
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout)["services"]


async def intrude(endpoints: list[str], curve: b.CurveKeys) -> int:
    """Messages an unauthorised CURVE client receives from ``endpoints`` in ``LISTEN_S``."""
    with b.Bus(curve=curve) as bus:
        subscriber = b.LatestSubscriber(bus, endpoints)
        await asyncio.sleep(LISTEN_S)
        subscriber.drain()
        return sum(subscriber.received.values())


def test_two_launchers_of_one_config_split_the_stack_and_refuse_an_unauthorised_peer(root):
    config_path, intruder_secret = two_host_config(root)
    robot = LauncherRun(config_path, "--host", "robot")
    compute = LauncherRun(config_path, "--host", "compute")
    try:
        robot.wait_for("[launcher] stack ready")
        compute.wait_for("[launcher] stack ready")
        assert not robot.find(lambda line: "[planner]" in line)
        assert not compute.find(lambda line: any(f"[{name}]" in line for name in ROBOT_SERVICES))

        for host in ("robot", "compute"):
            services = run_status(config_path, host)
            assert set(services) == {*ROBOT_SERVICES, "planner"}
            assert all(report is not None and report["state"] == "ready" for report in services.values()), services

        config = load_config(config_path)  # no host: every endpoint is the tcp one
        endpoints = [config.endpoint(name, kind) for name in config.service_names() for kind in ("data", "status")]
        assert all(endpoint.startswith("tcp://127.0.0.") for endpoint in endpoints)
        server_keys = config.curve_keys().server_key_files
        intruder = b.CurveKeys(intruder_secret, root / "authorized", server_keys, loopback=True)
        assert asyncio.run(intrude(endpoints, intruder)) == 0

        def refusals() -> dict[str, int]:
            return {name: report["errors"].get("curve_refused", 0)
                    for name, report in run_status(config_path, "compute").items()}

        assert wait_until(lambda: all(n >= 1 for n in refusals().values()), 15.0, period_s=1.0), refusals()
        for run in (robot, compute):
            assert run.process.poll() is None, run.text()[-3000:]
    finally:
        for run in (compute, robot):
            if run.process.poll() is None:
                run.process.send_signal(signal.SIGINT)
                run.wait_exit()
            run.cleanup()


def test_the_lab_two_hosts_config_is_the_lab_config_split_with_curve_between_the_hosts():
    split, lab = load_config(DEPLOY / "lab-two-hosts.toml"), load_config(DEPLOY / "lab.toml")
    assert msgspec.structs.replace(split, curve=None, hosts={}) == lab
    assert split.local_services() == lab.service_names()
    assert split.on_host("compute").local_services() == ["planner"]
    robot = split.on_host("robot")
    assert robot.curve.secret_key_file.endswith("robot.key_secret")
    planner_cmd = robot.endpoint("planner", "cmd")
    assert planner_cmd.startswith("tcp://192.168.2.2:") and not b.is_local_endpoint(planner_cmd)
    assert isinstance(robot.curve_keys().for_endpoint(planner_cmd, bind=False), b.CurveClient)
    assert robot.endpoint("tag_tracker").startswith("ipc://")
