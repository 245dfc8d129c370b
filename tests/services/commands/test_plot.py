"""``hydrosoft-stack plot``: the series it draws, from hand-made messages, the four PNGs of a real recording
(``conftest.recorded_run``), and long synthetic recordings: plotted in memory that does not grow with the file, with
hundreds of stops in a few timeline lanes."""

from __future__ import annotations

import argparse
import gc
import json
import tracemalloc

import msgspec
import numpy as np
import pytest
from mcap.writer import Writer
from PIL import Image

from hydrosoft.services.bus import messages as msg
from hydrosoft.services.commands.plot import MAX_BUCKETS, PLOTTED_TOPICS, Envelope, Tally, run, series
from hydrosoft.services.recording.mcap_format import (
    RecordedMessage,
    RecordingReader,
    encode_raw,
    raw_channel_metadata,
    raw_channel_name,
    raw_encoding,
    raw_schema,
)

POSE = np.array([0.0, 0.0, 0.02, 1.0, 0.0, 0.0, 0.0])


def at(topic: str, message: msg.Message, t_s: float) -> RecordedMessage:
    stamped = type(message)(**{**{f: getattr(message, f) for f in message.__struct_fields__},
                               "stamp_ns": int(1e9 + t_s * 1e9)})
    return RecordedMessage(topic, stamped, 0)


def arm(servo: bool, reason: str = "", holding: bool = False) -> msg.ArmState:
    return msg.ArmState(arm="bubble", tcp_pose=POSE, tcp_speed=np.zeros(6), running=True, protective_stop=False,
                        emergency_stop=False, servo_active=servo, stop_reason=reason, holding=holding)


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
        at("arm_state/bubble", arm(True), 1.42),
        at("arm_state/bubble", arm(False, "hold: target deadline passed 0.012 s ago", holding=True), 1.44),
        at("arm_state/bubble", arm(True), 1.46),
        at("arm_state/bubble", arm(False, "hold: target deadline passed 0.034 s ago", holding=True), 1.48),
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
    assert {lane: points(events) for lane, events in run_series.events.items()} == {
        "bubble stop: deadline passed": [(1.4, 1)], "bubble hold: target deadline passed": [(1.44, 1), (1.48, 1)],
        "planner degraded": [(1.5, 1)]}
    assert run_series.event_totals == {"bubble stop: deadline passed": 1, "bubble hold: target deadline passed": 2,
                                       "planner degraded": 1}
    assert points(run_series.errors["planner: stale_input"]) == [(1.5, 2), (2.5, 3)]


def test_a_recording_gives_four_pngs(recorded_run, tmp_path, capsys):
    out = tmp_path / "plots"
    assert run(argparse.Namespace(recording=recorded_run.clean, out=out)) == 0
    written = capsys.readouterr().out.split()
    assert sorted(p.rsplit("/", 1)[1] for p in written) == ["contact_forces.png", "events.png", "object_error.png",
                                                            "planner.png"]
    for path in written:
        with Image.open(path) as image:
            assert image.size[0] >= 600 and image.getextrema() != ((255, 255), (255, 255), (255, 255), (255, 255))


# --- long runs: bounded series, streamed files, readable events -----------------------------------------------------

REASONS = ("target deadline passed", "heartbeat lost", "force 41 N > 40 N")


def test_a_long_series_keeps_a_bounded_number_of_points_and_every_peak_and_count():
    line, events = Envelope(max_buckets=100), Tally(max_buckets=100)
    t = np.arange(100_000) * 0.01
    values = np.sin(t)
    values[54_321] = 7.0  # one spike among a hundred thousand points
    for time_s, value in zip(t, values):
        line.add(float(time_s), float(value))
        events.add(float(time_s))
    kept = line.points()
    assert len(kept) <= 200 and [p[0] for p in kept] == sorted(p[0] for p in kept)
    assert max(v for _, v in kept) == 7.0 and min(v for _, v in kept) == pytest.approx(-1.0, abs=1e-6)
    assert len(events.counts()) <= 100 and sum(n for _, n in events.counts()) == events.total == 100_000


def write_run(path, seconds: int) -> int:
    """A synthetic recording of ``seconds`` of a pushing run in the recorder's format: a wrench at 100 Hz, arm
    states at 50 Hz with a watchdog stop every half second (three reasons in turn), plans at 5 Hz, the planner's
    status and status reply; returns the number of stops."""
    goal = msg.Goal(task="pushing", target_pose=POSE + np.array([0.03, 0, 0, 0, 0, 0, 0]), tolerance_mm=5.0,
                    timeout_s=60.0)
    plan = msg.Plan(task="pushing", actions=np.zeros((6, 2, 6), np.float32),
                    predicted_object_poses=np.tile(POSE, (6, 1)).astype(np.float32),
                    predicted_forces=np.ones((2, 64, 3), np.float32), cost=1.0, solve_ms=150.0)
    stops = 0
    with open(path, "wb") as stream:
        writer = Writer(stream, chunk_size=1 << 20)
        writer.start()
        channels = {}

        def log(topic: str, message: msg.Message, t_s: float, source: str = "x") -> None:
            kind = type(message)
            if topic not in channels:
                schema = writer.register_schema(kind.__name__, "jsonschema", json.dumps(raw_schema(kind)).encode())
                channels[topic] = writer.register_channel(raw_channel_name(topic, source), raw_encoding(kind), schema,
                                                          raw_channel_metadata(topic, kind, source))
            stamp_ns = int(1e9 + t_s * 1e9)
            writer.add_message(channels[topic], log_time=stamp_ns, publish_time=stamp_ns,
                               data=encode_raw(msgspec.structs.replace(message, stamp_ns=stamp_ns)))

        for tick in range(seconds * 100):
            t_s = tick / 100
            log("wrench/bubble", msg.Wrench(sensor="bubble", wrench=np.full(6, np.sin(t_s)), tared=True), t_s)
            if tick % 2 == 0:
                stopped = tick % 50 == 0 and tick > 0
                stops += stopped
                log("arm_state/bubble", arm(not stopped, REASONS[(tick // 50) % 3] if stopped else ""), t_s)
            if tick % 20 == 0:
                log("plan/pushing", msgspec.structs.replace(plan, solve_ms=100.0 + tick % 7), t_s)
            if tick % 50 == 0:
                log("reply/status", msg.StatusReply(ok=True, running=True, goal=goal, error_mm=30.0 - t_s / 100), t_s)
            if tick % 100 == 0:
                log("status/planner", msg.ServiceStatus(state="ready", pid=1, uptime_s=t_s,
                                                        errors={"stale_input": tick // 100}), t_s)
        writer.finish()
    return stops


def plot_peak_bytes(path, out) -> int:
    """The peak of Python's traced memory while ``plot`` runs on ``path``, bytes."""
    gc.collect()
    tracemalloc.start()
    try:
        assert run(argparse.Namespace(recording=path, out=out)) == 0
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_plot_streams_a_long_recording_in_bounded_memory_with_hundreds_of_stops_in_three_lanes(tmp_path, capsys):
    short, long = tmp_path / "short.mcap", tmp_path / "long.mcap"
    write_run(short, seconds=20)
    stops = write_run(long, seconds=200)  # ten times the messages: 31,000
    plot_peak_bytes(short, tmp_path / "warm-up")  # imports, fonts and caches
    short_peak = plot_peak_bytes(short, tmp_path / "short")
    long_peak = plot_peak_bytes(long, tmp_path / "long")
    assert long_peak < 1.3 * short_peak, (short_peak, long_peak)
    reader = RecordingReader(long, PLOTTED_TOPICS)
    run_series = series(reader)
    assert stops == 399 and run_series.event_totals == {f"bubble stop: {r}": 133 for r in REASONS}
    assert len(run_series.forces["F/T bubble"]) <= 2 * MAX_BUCKETS < 20_000  # 20,000 wrenches
    with Image.open(tmp_path / "long" / "events.png") as image:
        assert image.size[1] < 800  # three lanes, not a line and a label per stop
    capsys.readouterr()
