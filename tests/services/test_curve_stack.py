"""CURVE forced on loopback through the real launcher (fake services): the services' tcp sockets are CURVE
servers, ``status`` reads them with the config's keys, and a peer with an unauthorised key or none receives
nothing while each refusal is counted in the refusing service's status."""

from __future__ import annotations

import asyncio
import json
import signal
import socket
import subprocess
import sys

import pytest
from fakes.stack_run import LauncherRun, remove_tree, short_run_root, wait_until, write_config

from hydrosoft.services.bus import sockets as b
from hydrosoft.services.commands import keys
from hydrosoft.services.bus.config import load_config

#: Longest a status call may take here, s (its window plus a Python start on a busy machine).
STATUS_TIMEOUT_S = 30.0
#: How long the outsiders listen to show that nothing reaches them, s (the fake publishes at 20 Hz).
LISTEN_S = 1.5


@pytest.fixture
def root():
    path = short_run_root()
    yield path
    remove_tree(path)


def free_tcp_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def run_status(config) -> dict:
    result = subprocess.run([sys.executable, "-m", "hydrosoft.services.commands.status", str(config), "--json", "--wait", "3"],
                            capture_output=True, text=True, timeout=STATUS_TIMEOUT_S)
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout)["services"]


async def listen(endpoints: list[str], curve: b.CurveKeys | None) -> int:
    """Messages a subscriber with ``curve`` (None: no keys) receives from ``endpoints`` in ``LISTEN_S``."""
    with b.Bus(curve=curve) as bus:
        subscriber = b.LatestSubscriber(bus, endpoints)
        await asyncio.sleep(LISTEN_S)
        subscriber.drain()
        return sum(subscriber.received.values())


def test_forced_curve_serves_authorised_keys_only_and_counts_the_refused(root):
    authorized = root / "authorized"
    host_public, host_secret = keys.generate_key_pair(root / "host", "robot")
    _, intruder_secret = keys.generate_key_pair(root / "intruder", "intruder")
    authorized.mkdir()
    (authorized / host_public.name).write_bytes(host_public.read_bytes())
    ports = {kind: free_tcp_port() for kind in ("data", "status")}
    config_path = write_config(root, ["a"], (
        f'[curve]\nsecret_key_file = "{host_secret}"\nauthorized_keys_dir = "{authorized}"\nloopback = true\n\n'
        f'[endpoints]\n"sim_world.data" = "tcp://127.0.0.1:{ports["data"]}"\n'
        f'"sim_world.status" = "tcp://127.0.0.1:{ports["status"]}"\n'))
    config = load_config(config_path)
    endpoints = [config.endpoint("sim_world", kind) for kind in ("data", "status")]
    run = LauncherRun(config_path, "--only", "sim_world")
    try:
        run.wait_for("[launcher] stack ready")
        services = run_status(config_path)  # status reads the tcp endpoint as an authorised CURVE client
        assert services["sim_world"]["state"] == "ready", services
        assert services["sim_world"]["published_hz"]["heartbeat/sim_world-data"] > 5.0, services

        host = b.CurveKeys(host_secret, authorized, loopback=True)
        intruder = b.CurveKeys(intruder_secret, authorized, {e: host_public for e in endpoints}, loopback=True)
        assert asyncio.run(listen(endpoints, host)) > 0  # the authorised key receives
        assert asyncio.run(listen(endpoints, intruder)) == 0  # a key the host does not know: nothing
        assert asyncio.run(listen(endpoints, None)) == 0  # no keys: nothing

        def refused() -> int:
            return run_status(config_path)["sim_world"]["errors"].get("curve_refused", 0)

        assert wait_until(lambda: refused() >= 1, 10.0, period_s=0.5)
    finally:
        if run.process.poll() is None:
            run.process.send_signal(signal.SIGINT)
            run.wait_exit()
        run.cleanup()
