"""The experiment client's resume of a goal on a restarted planner, against a scripted planner (no sockets)."""

from __future__ import annotations

import asyncio
from pathlib import Path

import msgspec
import numpy as np
import pytest

from hydrosoft.services import messages as msg
from hydrosoft.services.client import ClientError, StackClient

SIM_CONFIG = Path(__file__).resolve().parents[2] / "deploy" / "sim.toml"
TARGET = np.array([0.04, 0.0, 0.025, 1.0, 0.0, 0.0, 0.0])


class ScriptedPlanner:
    """Answers the client's requests as a planner would: pid 1 runs the goal, then "restarts" as pid 2, which
    refuses the first ``refusals`` Starts for lack of fresh input, then runs the goal and reaches it."""

    def __init__(self, refusals: int, refusal: str = msg.NO_FRESH_INPUT + " (object_pose/object: nothing yet)"):
        self.pid, self.running, self.goal, self.outcome = 1, False, None, ""
        self.refusals, self.refusal = refusals, refusal
        self.requests: list[str] = []

    async def request(self, request: msg.Request) -> msg.Reply:
        self.requests.append(type(request).__name__)
        if isinstance(request, msg.SetGoal):
            self.goal = request.goal
        elif isinstance(request, msg.Start):
            if self.pid == 2 and self.refusals > 0:
                self.refusals -= 1
                return msg.CommandReply(ok=False, error=self.refusal)
            self.running, self.outcome = True, "running"
            self.goal = msgspec.structs.replace(self.goal, target_pose=TARGET)
        elif isinstance(request, msg.GetStatus):
            reply = msg.StatusReply(ok=True, running=self.running, goal=self.goal, outcome=self.outcome,
                                    status=msg.ServiceStatus(state="ready", pid=self.pid, uptime_s=1.0))
            if self.running and self.pid == 1:  # the planner dies; the launcher brings up pid 2, idle
                self.pid, self.running, self.goal, self.outcome = 2, False, None, ""
            elif self.running:
                self.running, self.outcome = False, "reached"
            return reply
        return msg.CommandReply(ok=True)


def run_goal(planner: ScriptedPlanner) -> tuple[msg.StatusReply, StackClient]:
    async def main():
        client = StackClient(SIM_CONFIG)
        client.requests = planner
        try:
            await client.set_goal("pushing", dx_m=0.04, timeout_s=30.0)
            await client.start()
            return await client.wait(10.0), client
        finally:
            client.close()

    return asyncio.run(main())


def test_a_restarted_planner_without_fresh_input_is_asked_again_until_it_starts_the_goal():
    planner = ScriptedPlanner(refusals=2)
    reply, client = run_goal(planner)
    assert reply.outcome == "reached" and client.resumes == 1
    assert planner.requests.count("Start") == 1 + 3  # the first start, two refused resumes, the one that ran
    assert np.array_equal(planner.goal.target_pose, TARGET)  # resumed with the absolute target


def test_any_other_refusal_of_the_resumed_goal_is_raised():
    planner = ScriptedPlanner(refusals=1, refusal="no goal: send SetGoal first")
    with pytest.raises(ClientError, match="no goal"):
        run_goal(planner)
