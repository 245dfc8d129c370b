"""The client API of the running sim stack under attack and after a crash (real processes, two launches of one
config in this module):

1. A goal whose task name is 65,300 characters (its header just under the 64 KiB limit), then GetStatus at 1000/s
   for ``FLOOD_S``: every later request is answered, the planner's heartbeat never pauses as long as the arm
   commander's watchdog timeout, and a normal goal is then reached: the rotation task's, turning the cube by
   ``TURN_DEG`` (the config is deploy/sim.toml with its rotation scene, the task's end-to-end check on the stack).
2. The leftover client: ``hydrosoft-stack goal ... --wait 600`` runs a goal; the launcher is SIGKILLed; the client
   exits within seconds, non-zero, saying the stack is gone; each service's own log file holds its shutdown lines;
   the same config launched again: its arm does not move, and a goal of the old launch is refused by the new
   planner and by a client of the old launch.

Every process is stopped by its pid (launchers by their process group, the client by its pid); every wait has a
timeout. Ground truth for the arm is the simulated controller's own TCP pose (``test_stack_faults.tcp_truth``).
"""

from __future__ import annotations

import asyncio
import math
import os
import re
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import msgspec
import numpy as np
import pytest
import torch
import zmq
from stack_process import Stack, children_left, stack_config, tracked_object_pose
from test_stack_faults import HELD_M, tcp_truth

from hydrosoft.geometry import se3
from hydrosoft.services.bus import messages as msg
from hydrosoft.services.bus.sockets import Bus
from hydrosoft.services.client import EXIT_STACK_GONE, ClientError, Pursuit, StackClient, StackGone, true_error_mm
from hydrosoft.services.bus.config import load_config

pytestmark = pytest.mark.slow

GOAL_TIMEOUT_S = 240.0
#: The flood: GetStatus at FLOOD_HZ for FLOOD_S, sent in bursts every FLOOD_TICK_S.
FLOOD_HZ = 1000
FLOOD_S = 5.0
FLOOD_TICK_S = 0.01
#: Requests sent one by one after the flood, each of which must be answered ok.
AFTER_FLOOD_REQUESTS = 20
#: The rotation goal after the flood (deg about base z) and its tolerance (mm, ADD over the cube's points).
TURN_DEG = 30.0
TURN_TOLERANCE_MM = 3.0
#: From the launcher's SIGKILL to the leftover client's exit, s: its status request's timeout (3 s), the check of
#: the launcher's pid, the client's exit, and slack for a loaded 2-core machine.
CLIENT_EXIT_BOUND_S = 3.0 + 4.0
#: How long the relaunched stack is watched for motion of its arm, s (the old client re-sent its goal 3 s after
#: the new planner was ready).
WATCH_S = 8.0
SERVICES_EXIT_TIMEOUT_S = 15.0


@pytest.fixture(scope="module")
def launch(tmp_path_factory):
    """The first launch of a private copy of deploy/sim.toml with the rotation scene on the table (compiled plant: a
    goal must be reached)."""
    folder = tmp_path_factory.mktemp("requests")
    config_path = stack_config(folder, compiled_plant=True, task="rotation")
    stack = Stack(config_path, folder / "launcher-1.log")
    stacks = [stack]
    try:
        client = StackClient(load_config(config_path))
        try:
            stack.wait_ready(client)
        finally:
            client.close()
        yield config_path, stacks
    finally:
        for started in stacks:
            started.stop()


def service_pids(stack: Stack) -> dict[str, int]:
    """The pid of each service the launcher reported ready (the newest run of each)."""
    found = re.findall(r"\[launcher\] (\S+) ready (?:again )?\(pid (\d+)", stack.text())
    return {name: int(pid) for name, pid in found}


def alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return False
    return state != "Z"


async def heartbeat_stamps(bus: Bus, endpoint: str, until: asyncio.Event) -> list[int]:
    """Every planner heartbeat's ``stamp_ns`` (the planner's own clock) received until ``until`` is set."""
    sub = bus.socket(zmq.SUB, endpoint, bind=False, options=[(zmq.SUBSCRIBE, b"heartbeat/planner"),
                                                             (zmq.RCVHWM, 100_000)])
    stamps = []
    while not until.is_set():
        if await sub.poll(50):
            frames = await sub.recv_multipart()
            stamps.append(msg.decode(frames)[1].stamp_ns)
    return stamps


async def flood(config_path: Path) -> tuple[Counter, float, int]:
    """The 65,300-character goal, then the GetStatus flood from one connection; returns the flood's answers by kind,
    the planner's longest heartbeat gap (s) over the flood and its outcome, and the answers ok to the requests sent
    after it."""
    config = load_config(config_path)
    endpoint = config.endpoint("planner", "cmd")
    with Bus() as bus:
        raw = bus.socket(zmq.DEALER, endpoint, bind=False, options=[(zmq.RCVHWM, 100_000), (zmq.SNDHWM, 100_000)])
        goal = msg.Goal(task="t" * 65_300, tolerance_mm=5.0, timeout_s=60.0)
        header = msgspec.msgpack.encode(msg.SetGoal(goal=goal))
        assert len(header) < msg.MAX_HEADER_BYTES
        await raw.send_multipart([b"goal", b"cmd/set_goal", header])
        answer = await asyncio.wait_for(raw.recv_multipart(), 5.0)
        refusal = msg.decode(answer[1:])[1]
        assert not refusal.ok and len(refusal.error) < 2000, refusal

        stop = asyncio.Event()
        listening = asyncio.create_task(heartbeat_stamps(bus, config.endpoint("planner", "status"), stop))
        await asyncio.sleep(1.0)  # the heartbeat subscription is up
        request = msg.encode(msg.GetStatus())
        sent, answers = 0, Counter()

        async def read_answers():
            while True:
                frames = await raw.recv_multipart()
                reply = msg.decode(frames[1:])[1]
                answers["ok" if reply.ok else reply.error.partition(":")[0]] += 1

        reading = asyncio.create_task(read_answers())
        start_s = time.monotonic()
        while (elapsed_s := time.monotonic() - start_s) < FLOOD_S:
            while sent < elapsed_s * FLOOD_HZ:
                sent += 1
                await raw.send_multipart([sent.to_bytes(4, "big"), *request])
            await asyncio.sleep(FLOOD_TICK_S)
        deadline_s = time.monotonic() + 10.0
        while sum(answers.values()) < sent and time.monotonic() < deadline_s:
            await asyncio.sleep(0.1)
        stop.set()
        stamps = await listening
        reading.cancel()
        gaps = np.diff(np.array(stamps)) * 1e-9
        answers["unanswered"] = sent - sum(answers.values())

        client = StackClient(config)
        try:
            ok = 0
            for _ in range(AFTER_FLOOD_REQUESTS):
                ok += (await client.status()).ok
        finally:
            client.close()
        return answers, float(gaps.max()), ok


def test_a_huge_goal_and_a_request_flood_leave_the_api_and_the_heartbeat_up_and_a_goal_is_reached(launch):
    config_path, stacks = launch
    answers, longest_gap_s, ok_after = asyncio.run(flood(config_path))
    print(f"flood answers {dict(answers)}, longest planner heartbeat gap {longest_gap_s * 1e3:.0f} ms")
    config = load_config(config_path)
    assert answers["unanswered"] == 0 and answers["ok"] > 0, answers
    assert longest_gap_s < config.limits.heartbeat_timeout_s, longest_gap_s
    assert ok_after == AFTER_FLOOD_REQUESTS

    async def turn():
        client = StackClient(config)
        try:
            start = await tracked_object_pose(client)
            await client.set_goal("rotation", dyaw_rad=math.radians(TURN_DEG), tolerance_mm=TURN_TOLERANCE_MM,
                                  timeout_s=GOAL_TIMEOUT_S)
            await client.start()
            reply = await client.wait(GOAL_TIMEOUT_S + 10)
            return reply, start, await true_error_mm(client, np.asarray(reply.goal.target_pose), "rotation")
        finally:
            client.close()

    reply, start, true = asyncio.run(turn())
    assert reply.outcome == "reached", (reply.outcome, reply.outcome_reason, stacks[0].text()[-3000:])
    assert true is not None and true < 2 * TURN_TOLERANCE_MM, true  # sim_world's cube, not only the tracked one
    turned_deg = math.degrees(float(se3.angle_between(torch.as_tensor(start[3:]),
                                                      torch.as_tensor(reply.goal.target_pose[3:]))))
    assert abs(turned_deg - TURN_DEG) < 0.5, turned_deg  # the goal asked for the turn
    print(f"rotation {TURN_DEG:.0f} deg: reached in {reply.elapsed_s:.1f} s, error {reply.error_mm:.2f} mm (tracked), "
          f"{true:.2f} mm (true), {reply.solves} solves")
    errors = reply.status.errors
    assert errors.get("rate_limited", 0) > 0 and errors.get("range", 0) >= 1, errors


def test_a_leftover_client_gives_up_at_once_and_the_relaunched_stack_does_not_move(launch, tmp_path):
    config_path, stacks = launch
    config = load_config(config_path)
    first = stacks[0]
    client_out = (tmp_path / "client.out").open("wb")
    leftover = subprocess.Popen([sys.executable, "-m", "hydrosoft.services.commands.cli", "goal", "rotation", "--dyaw",
                                 "45", "--tolerance-mm", "1", "--wait", "600", "--config", str(config_path)],
                                stdout=client_out, stderr=subprocess.STDOUT)
    try:
        async def goal_runs() -> tuple[str, np.ndarray]:
            watcher = StackClient(config)
            try:
                deadline_s = time.monotonic() + 60.0
                while not (reply := await watcher.status()).running:
                    assert time.monotonic() < deadline_s, "the leftover client's goal never ran"
                    await asyncio.sleep(0.5)
                return watcher.instance, reply.goal
            finally:
                watcher.close()

        instance, old_goal = asyncio.run(goal_runs())
        pids = service_pids(first)
        os.killpg(first.process.pid, signal.SIGKILL)  # the launcher's group: the launcher alone (services have theirs)
        killed_s = time.monotonic()
        code = leftover.wait(CLIENT_EXIT_BOUND_S + 5.0)
        exit_s = time.monotonic() - killed_s
        text = (tmp_path / "client.out").read_text()
        assert code == EXIT_STACK_GONE and "the stack is gone" in text, (code, text)
        assert exit_s < CLIENT_EXIT_BOUND_S, exit_s

        deadline_s = time.monotonic() + SERVICES_EXIT_TIMEOUT_S
        while any(alive(pid) for pid in pids.values()):
            assert time.monotonic() < deadline_s, {name: pid for name, pid in pids.items() if alive(pid)}
            time.sleep(0.2)
        for name in ("planner", "sim_world", "tag_tracker"):  # their own files, though the launcher's pipe was gone
            log = (Path(config.run_dir) / "logs" / f"{name}.log").read_text()
            assert f"stack launch {instance}" in log and "SIGTERM received" in log and "stopped (exit" in log, log

        second = Stack(config_path, tmp_path / "launcher-2.log")  # the same config, launched again
        stacks.append(second)
        new = StackClient(config)
        try:
            second.wait_ready(new)
            host = config.arms[0].ur_host
            start_pose, moved_m, watch_end_s = tcp_truth(host), 0.0, time.monotonic() + WATCH_S
            while time.monotonic() < watch_end_s:
                moved_m = max(moved_m, float(np.linalg.norm(tcp_truth(host)[:3] - start_pose[:3])))
                time.sleep(0.1)
            reply = asyncio.run(new.status())
            assert moved_m < HELD_M and reply.outcome == "" and not reply.running, (moved_m, reply.outcome)
            assert new.instance != instance

            async def old_goal_refused():
                with pytest.raises(ClientError, match="another launch"):  # the new planner refuses the old goal
                    await new._command(msg.SetGoal(goal=old_goal))
                old = StackClient(config)  # a client of the old launch, asked to resume its goal
                try:
                    old.instance = instance
                    old.pursuit = Pursuit(0, old_goal, time.monotonic())
                    with pytest.raises(StackGone, match="launched again"):
                        await old.wait(10.0, resume=True)
                finally:
                    old.close()

            asyncio.run(old_goal_refused())
            assert tcp_truth(host)[:3] == pytest.approx(start_pose[:3], abs=HELD_M)
        finally:
            new.close()
        assert not children_left(first.process.pid)
    finally:
        if leftover.poll() is None:
            leftover.kill()
            leftover.wait(10)
        client_out.close()
