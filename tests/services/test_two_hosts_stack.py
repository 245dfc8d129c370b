"""The sim stack split across two simulated hosts, end to end: one config, ``launch --host robot`` (sim_world, the
arm's services, the tag tracker) and ``launch --host compute`` (the planner) on two free 127.0.0.N, CURVE forced on
loopback, each host with its own key pair and run_dir. A client on the robot host pushes the cube to its goal
(sim_world's true error within 5 mm) while a process with an unauthorised key connects to every inter-host
endpoint: it receives nothing, its request is never answered, and the refusals are counted. Then the compute host
dies mid-goal (SIGKILL of its launcher and planner): the arm stops within the planner heartbeat timeout plus a servo
period (as the robot host sees it: the commander's published state), and nothing moves it again by itself.

One two-host launch for the whole module (a launch takes minutes on a loaded 2-core machine). Every process is
stopped by its pid (each launcher's process group, then a check that none is left)."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import subprocess
import sys
import time

import pytest
from loopback import free_loopback_address
from stack_process import Stack, children_left, stack_config

from hydrosoft.services.bus import sockets as b
from hydrosoft.services.commands import keys
from hydrosoft.services.bus import messages as m
from hydrosoft.services.client import StackClient, true_error_mm
from hydrosoft.services.bus.config import ENDPOINT_KINDS, load_config

pytestmark = pytest.mark.slow

GOAL_TIMEOUT_S = 240.0
#: The planner's heartbeat timeout (deploy/sim.toml: 0.5 s) plus one servo period (8 ms), plus the time for the
#: commander's next published state to show it (one servo period) and scheduling slack on a busy machine (as
#: test_stack.py's bound for a killed planner).
HOST_LOSS_STOP_BOUND_S = 0.5 + 0.008 + 0.008 + 0.2
#: How long the arm is watched after the compute host died, to show that nothing moves it again, s.
WATCH_AFTER_S = 3.0
FIRST_PORT = 5600
ROBOT_SERVICES = ["sim_world", "arm_commander-bubble", "ft_reader-bubble", "bubble_camera-bubble", "tag_tracker"]


class HostStack(Stack):
    """One host's launcher (``launch CONFIG --host HOST``) as a subprocess in its own session."""

    def __init__(self, config, log, host: str) -> None:
        self.config, self.log = config, log
        self._out = log.open("wb")
        self.process = subprocess.Popen([sys.executable, "-m", "hydrosoft.services.commands.cli", "launch", str(config),
                                         "--host", host], stdout=self._out, stderr=subprocess.STDOUT,
                                        start_new_session=True)


def split_config(tmp_path):
    """deploy/sim.toml made private to this test, split over two free loopback hosts with CURVE forced; and the
    intruder's secret key file."""
    path = stack_config(tmp_path, compiled_plant=True)
    ports = range(FIRST_PORT, FIRST_PORT + len(ENDPOINT_KINDS) * (len(ROBOT_SERVICES) + 1))
    robot = free_loopback_address(21, 39, ports)
    compute = free_loopback_address(21, 39, ports, taken=(robot,))
    authorized = tmp_path / "authorized"
    authorized.mkdir()
    run_dirs = {"robot": tmp_path / "run", "compute": tmp_path / "compute-run"}  # robot: the FT 300 link's run_dir
    text = f'\n[curve]\nsecret_key_file = "{tmp_path}/robot/robot.key_secret"\n' \
           f'authorized_keys_dir = "{authorized}"\nloopback = true\n'
    for name, address, services in (("robot", robot, ROBOT_SERVICES), ("compute", compute, ["planner"])):
        public, secret = keys.generate_key_pair(tmp_path / name, name)
        (authorized / public.name).write_bytes(public.read_bytes())
        text += (f'\n[hosts.{name}]\naddress = "{address}"\nservices = {json.dumps(services)}\n'
                 f'first_port = {FIRST_PORT}\npublic_key_file = "{public}"\nsecret_key_file = "{secret}"\n'
                 f'run_dir = "{run_dirs[name]}"\n')
    _, intruder = keys.generate_key_pair(tmp_path / "intruder", "intruder")
    path.write_text(path.read_text() + text)
    return path, intruder


async def intruder_run(config, secret, authorized) -> tuple[int, bool]:
    """An unauthorised key connected to every inter-host endpoint of ``config`` (read as no host): the messages it
    received, and whether its Stop request to the planner was answered."""
    endpoints = [config.endpoint(name, kind) for name in config.service_names() for kind in ("data", "status")]
    curve = b.CurveKeys(secret, authorized, config.curve_keys().server_key_files, loopback=True)
    with b.Bus(curve=curve) as bus:
        subscriber = b.LatestSubscriber(bus, endpoints)
        client = b.RequestClient(bus, config.endpoint("planner", "cmd"), source="intruder", timeout_s=3.0)
        try:
            await client.request(m.Stop())
            answered = True
        except TimeoutError:
            answered = False
        subscriber.drain()
        return sum(subscriber.received.values()), answered


async def compute_host_dies_mid_goal(client: StackClient, compute: HostStack) -> tuple[float, bool]:
    """Start a goal, SIGKILL the compute host's launcher and planner while the arm servoes; the seconds until the
    commander reports the arm stopped, and whether it servoed again within ``WATCH_AFTER_S`` after that."""
    arm = client.subscribe("arm_commander-bubble", ("arm_state/bubble",))
    await client.set_goal("pushing", dy_m=-0.03, tolerance_mm=3.0, timeout_s=GOAL_TIMEOUT_S)
    await client.start()
    deadline = time.monotonic() + 30.0
    while True:  # wait until the arm servoes towards a target
        await arm.wait(1.0)
        if arm.latest("arm_state/bubble", 1.0, m.ArmState).value.servo_active:
            break
        assert time.monotonic() < deadline, "the arm never started servoing"
    planner_pid = (await client.status()).status.pid
    os.kill(compute.process.pid, signal.SIGKILL)  # the launcher first: it must not restart the planner
    os.kill(planner_pid, signal.SIGKILL)
    killed = time.monotonic()
    while arm.latest("arm_state/bubble", 1.0, m.ArmState).value.servo_active:
        await arm.wait(1.0)
        assert time.monotonic() - killed < 5.0, "the arm kept servoing after the compute host died"
    stop_s = time.monotonic() - killed
    watched = time.monotonic()
    servoed_again = False
    while time.monotonic() - watched < WATCH_AFTER_S:
        await arm.wait(0.5)
        servoed_again |= arm.latest("arm_state/bubble", 1.0, m.ArmState).value.servo_active
    return stop_s, servoed_again


def test_two_hosts_push_the_cube_with_curve_while_an_unauthorised_peer_gets_nothing(tmp_path):
    config_path, intruder = split_config(tmp_path)
    robot = HostStack(config_path, tmp_path / "robot.log", "robot")
    compute = HostStack(config_path, tmp_path / "compute.log", "compute")
    client = StackClient(load_config(config_path, host="robot"))
    try:
        robot.wait_ready(client)
        assert "[planner]" not in robot.text() and "[sim_world]" not in compute.text()

        async def push_while_intruded():
            await client.set_goal("pushing", dy_m=0.03, tolerance_mm=3.0, timeout_s=GOAL_TIMEOUT_S)
            await client.start()
            received, answered = await intruder_run(load_config(config_path), intruder, tmp_path / "authorized")
            reply = await client.wait(GOAL_TIMEOUT_S + 10)
            true = await true_error_mm(client, reply.goal.target_pose, "pushing")
            return reply, true, received, answered

        reply, true, received, answered = asyncio.run(push_while_intruded())
        assert received == 0 and not answered
        assert reply.outcome == "reached", (reply.outcome, reply.outcome_reason, reply.error_mm,
                                            compute.text()[-2000:], robot.text()[-2000:])
        assert true is not None and true < 5.0, true
        status = subprocess.run([sys.executable, "-m", "hydrosoft.services.commands.status", str(config_path), "--json",
                                 "--wait", "4"], capture_output=True, text=True, timeout=60,
                                env={**os.environ, "HYDROSOFT_HOST": "compute"})
        services = json.loads(status.stdout)["services"]
        assert all(report is not None for report in services.values()), services
        assert services["planner"]["errors"].get("curve_refused", 0) >= 1, services["planner"]

        stop_s, servoed_again = asyncio.run(compute_host_dies_mid_goal(client, compute))
        print(f"arm stopped {stop_s:.3f} s after the compute host died")
        assert stop_s < HOST_LOSS_STOP_BOUND_S, stop_s
        assert not servoed_again
    finally:
        client.close()
        compute.stop()
        robot.stop()
    for stack in (robot, compute):
        assert not children_left(stack.process.pid), children_left(stack.process.pid)
