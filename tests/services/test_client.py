"""The experiment client's goal against a scripted planner (no sockets): a goal belongs to one stack launch, a
restarted planner's goal is interrupted unless resumed on request, and a stack that is gone is noticed within
seconds."""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
import time
from pathlib import Path

import msgspec
import numpy as np
import pytest

from hydrosoft.services import client as c
from hydrosoft.services.bus import messages as msg
from hydrosoft.services.client import ClientError, StackClient, StackGone
from hydrosoft.services.bus.config import load_config

SIM_CONFIG = Path(__file__).resolve().parents[2] / "deploy" / "sim.toml"
TARGET = np.array([0.04, 0.0, 0.025, 1.0, 0.0, 0.0, 0.0])
LAUNCH = "a" * 32


class ScriptedPlanner:
    """Answers the client's requests as a planner of launch ``LAUNCH`` would: pid 1 runs the goal, then "restarts"
    as pid 2 (of launch ``restarted_as``), which refuses the first ``refusals`` Starts for lack of fresh input, then
    runs the goal and reaches it. ``silent``: once the goal started, every request after its first status times out
    instead."""

    def __init__(self, refusals: int = 0, refusal: str = msg.NO_FRESH_INPUT + " (object_pose/object: nothing yet)",
                 restarted_as: str = LAUNCH, silent: bool = False):
        self.pid, self.running, self.goal, self.outcome = 1, False, None, ""
        self.instance, self.restarted_as, self.silent = LAUNCH, restarted_as, silent
        self.gone = False  # silent, and the goal has started: every request times out
        self.refusals, self.refusal = refusals, refusal
        self.requests: list[str] = []
        self.goals: list[msg.Goal] = []

    async def request(self, request: msg.Request) -> msg.Reply:
        if self.gone:
            await asyncio.sleep(0.05)
            raise TimeoutError(f"no reply to {type(request).__name__} within 0.05 s")
        self.requests.append(type(request).__name__)
        if isinstance(request, msg.SetGoal):
            self.goal = request.goal
            self.goals.append(request.goal)
        elif isinstance(request, msg.Start):
            if self.pid == 2 and self.refusals > 0:
                self.refusals -= 1
                return msg.CommandReply(ok=False, error=self.refusal)
            self.running, self.outcome = True, "running"
            self.goal = msgspec.structs.replace(self.goal, target_pose=TARGET)
        elif isinstance(request, msg.GetStatus):
            status = msg.ServiceStatus(state="ready", pid=self.pid, uptime_s=1.0, instance=self.instance)
            reply = msg.StatusReply(ok=True, running=self.running, goal=self.goal, outcome=self.outcome, status=status)
            if self.running and self.silent:
                self.gone = True
            elif self.running and self.pid == 1:  # the planner dies; pid 2 comes up, idle
                self.pid, self.running, self.goal, self.outcome = 2, False, None, ""
                self.instance = self.restarted_as
            elif self.running:
                self.running, self.outcome = False, "reached"
            return reply
        return msg.CommandReply(ok=True)


def client_config(tmp_path: Path):
    """deploy/sim.toml with a private run_dir (where the client looks for the launcher's lock file)."""
    return msgspec.structs.replace(load_config(SIM_CONFIG), run_dir=str(tmp_path))


def run_goal(planner: ScriptedPlanner, tmp_path: Path, resume: bool = False,
             wait_s: float = 10.0) -> tuple[msg.StatusReply, StackClient]:
    async def main():
        client = StackClient(client_config(tmp_path))
        client.requests = planner
        try:
            await client.set_goal("pushing", dx_m=0.04, timeout_s=30.0)
            await client.start()
            return await client.wait(wait_s, resume=resume), client
        finally:
            client.close()

    return asyncio.run(main())


def test_a_goal_carries_the_launch_it_was_set_on(tmp_path):
    planner = ScriptedPlanner(restarted_as=LAUNCH)
    run_goal(planner, tmp_path, resume=True)
    assert planner.requests[0] == "GetStatus"  # the launch is learned before the first goal
    assert all(goal.instance == LAUNCH for goal in planner.goals)


def test_a_restarted_planner_without_fresh_input_is_asked_again_until_it_starts_the_goal(tmp_path):
    planner = ScriptedPlanner(refusals=2)
    reply, client = run_goal(planner, tmp_path, resume=True)
    assert reply.outcome == "reached" and client.resumes == 1
    assert planner.requests.count("Start") == 1 + 3  # the first start, two refused resumes, the one that ran
    assert np.array_equal(planner.goal.target_pose, TARGET)  # resumed with the absolute target


def test_any_other_refusal_of_the_resumed_goal_is_raised(tmp_path):
    planner = ScriptedPlanner(refusals=1, refusal="no goal: send SetGoal first")
    with pytest.raises(ClientError, match="no goal"):
        run_goal(planner, tmp_path, resume=True)


def test_a_goal_whose_planner_restarted_is_interrupted_unless_resume_was_asked_for(tmp_path):
    planner = ScriptedPlanner()
    reply, client = run_goal(planner, tmp_path)
    assert reply.outcome == "interrupted" and "restarted" in reply.outcome_reason and client.resumes == 0
    assert planner.requests.count("SetGoal") == 1 and planner.requests.count("Start") == 1


@pytest.mark.parametrize("resume", [False, True])
def test_a_goal_is_never_sent_to_another_launch(tmp_path, resume):
    planner = ScriptedPlanner(restarted_as="b" * 32)
    with pytest.raises(StackGone, match="launched again"):
        run_goal(planner, tmp_path, resume=resume)
    assert planner.requests.count("SetGoal") == 1 and planner.requests.count("Start") == 1


def dead_pid() -> int:
    """The pid of a process that has exited (and been reaped)."""
    process = subprocess.Popen([sys.executable, "-c", "pass"])
    process.wait(10)
    return process.pid


def test_a_silent_planner_whose_launcher_is_gone_ends_the_wait_at_once(tmp_path):
    (tmp_path / c.LAUNCHER_LOCK).write_text(f"{dead_pid()}\n")
    tic = time.monotonic()
    with pytest.raises(StackGone, match="launcher is not running"):
        run_goal(ScriptedPlanner(silent=True), tmp_path, resume=True, wait_s=60.0)
    assert time.monotonic() - tic < 2.0


def test_a_silent_planner_ends_the_wait_after_the_silence_limit_unless_resume_waits_for_its_restart(
        tmp_path, monkeypatch):
    monkeypatch.setattr(c, "SILENT_LIMIT_S", 0.5)
    (tmp_path / c.LAUNCHER_LOCK).write_text(f"{os.getpid()}\n")  # a launcher that runs
    tic = time.monotonic()
    with pytest.raises(StackGone, match="has not answered"):
        run_goal(ScriptedPlanner(silent=True), tmp_path, wait_s=60.0)
    assert 0.5 <= time.monotonic() - tic < 2.0
    with pytest.raises(TimeoutError):  # with resume, a running launcher may yet restart the planner
        run_goal(ScriptedPlanner(silent=True), tmp_path, resume=True, wait_s=1.5)


def test_the_launcher_check_reads_the_lock_file(tmp_path):
    assert c.launcher_running(tmp_path) is None
    (tmp_path / c.LAUNCHER_LOCK).write_text(f"{os.getpid()}\n")
    assert c.launcher_running(tmp_path) is True
    (tmp_path / c.LAUNCHER_LOCK).write_text(f"{dead_pid()}\n")
    assert c.launcher_running(tmp_path) is False
    zombie = subprocess.Popen([sys.executable, "-c", "pass"])  # exited, not yet reaped: as a killed launcher is
    try:
        (tmp_path / c.LAUNCHER_LOCK).write_text(f"{zombie.pid}\n")
        deadline_s = time.monotonic() + 10.0
        while c.launcher_running(tmp_path):
            assert time.monotonic() < deadline_s, "a zombie launcher counts as running"
            time.sleep(0.05)
    finally:
        zombie.wait(10)
