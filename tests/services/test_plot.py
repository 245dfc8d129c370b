"""``hydrosoft-stack plot``: the series it draws, from hand-made messages, and the four PNGs of a real recording
(``conftest.recorded_run``)."""

from __future__ import annotations

import argparse

import numpy as np
from PIL import Image

from hydrosoft.services import messages as msg
from hydrosoft.services.plot import run, series
from hydrosoft.services.recording import RecordedMessage

POSE = np.array([0.0, 0.0, 0.02, 1.0, 0.0, 0.0, 0.0])


def at(topic: str, message: msg.Message, t_s: float) -> RecordedMessage:
    stamped = type(message)(**{**{f: getattr(message, f) for f in message.__struct_fields__},
                               "stamp_ns": int(1e9 + t_s * 1e9)})
    return RecordedMessage(topic, stamped, 0)


def arm(servo: bool, reason: str = "") -> msg.ArmState:
    return msg.ArmState(arm="bubble", tcp_pose=POSE, tcp_speed=np.zeros(6), running=True, protective_stop=False,
                        emergency_stop=False, servo_active=servo, stop_reason=reason)


def test_the_series_follow_the_messages():
    goal = msg.Goal(task="pushing", target_pose=POSE + np.array([0.03, 0, 0, 0, 0, 0, 0]), tolerance_mm=5.0,
                    timeout_s=60.0)
    plan = msg.Plan(task="pushing", actions=np.zeros((2, 2, 6)), predicted_object_poses=np.tile(POSE, (2, 1)),
                    predicted_forces=np.ones((2, 3, 3)), cost=1.0, solve_ms=150.0)
    messages = [
        at("eval/object_pose", msg.EvalObjectPose(object="object", pose=POSE), 0.0),  # before any goal: not plotted
        at("reply/status", msg.StatusReply(ok=True, running=True, goal=goal, error_mm=30.0), 0.5),
        at("object_pose/object", msg.ObjectPose(object="object", pose=POSE, tags_used=(1,), quality=1.0), 0.6),
        at("eval/contact_forces", msg.EvalContactForces(bodies=("bubble", "table"), points=np.zeros((3, 3)),
                                                        forces=np.full((2, 3, 3), 2.0)), 0.7),
        at("plan/pushing", plan, 1.0),
        at("plan/pushing", plan, 1.25),
        at("arm_state/bubble", arm(True), 1.3),
        at("arm_state/bubble", arm(False, "deadline passed"), 1.4),
        at("status/planner", msg.ServiceStatus(state="degraded", pid=1, uptime_s=1.0, errors={"stale_input": 2}), 1.5),
        at("status/planner", msg.ServiceStatus(state="degraded", pid=1, uptime_s=2.0, errors={"stale_input": 3}), 2.5),
    ]
    run_series = series(messages)

    def points(values):
        return [tuple(round(float(x), 6) for x in point) for point in values]

    assert points(run_series.error_mm) == [(0.5, 30.0)]
    assert points(run_series.tracked_mm) == [(0.6, 30.0)]
    assert run_series.true_mm == []  # the true pose came before the goal was known
    assert points(run_series.forces["true bubble"]) == [(0.7, round(float(np.linalg.norm([6.0, 6.0, 6.0])), 6))]
    assert points(run_series.forces["predicted table"]) == [(1.0, round(float(np.linalg.norm([3.0] * 3)), 6)),
                                                            (1.25, round(float(np.linalg.norm([3.0] * 3)), 6))]
    assert points(run_series.solve_ms) == [(1.0, 150.0), (1.25, 150.0)]
    assert points(run_series.plan_hz) == [(1.25, 4.0)]
    assert [(round(t, 6), arm_name, reason) for t, arm_name, reason in run_series.stops] == [
        (1.4, "bubble", "deadline passed")]
    assert points(run_series.errors["planner: stale_input"]) == [(1.5, 2), (2.5, 3)]
    assert [(round(t, 6), service, state) for t, service, state in run_series.states] == [(1.5, "planner", "degraded")]


def test_a_recording_gives_four_pngs(recorded_run, tmp_path, capsys):
    out = tmp_path / "plots"
    assert run(argparse.Namespace(recording=recorded_run.clean, out=out)) == 0
    written = capsys.readouterr().out.split()
    assert sorted(p.rsplit("/", 1)[1] for p in written) == ["contact_forces.png", "events.png", "object_error.png",
                                                            "planner.png"]
    for path in written:
        with Image.open(path) as image:
            assert image.size[0] >= 600 and image.getextrema() != ((255, 255), (255, 255), (255, 255), (255, 255))
