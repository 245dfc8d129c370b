"""Replay: its plain parts, and the clean recording of ``conftest.recorded_run`` replayed onto a fresh bus (another
run_dir): every topic comes back at its recorded rate (within 5 %) with exactly the recorded contents, and a fresh
tag tracker, fed the recorded images, gives the poses the live tracker gave.

Every process is stopped by its pid; every wait has a timeout.
"""

from __future__ import annotations

import asyncio
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import zmq
from fakes.bus_publisher import topics
from mcap.records import Channel
from recording_processes import remove_root, service, short_root, write_config
from test_recorder import assert_same

from hydrosoft.services.bus import messages as msg
from hydrosoft.services.bus.sockets import Bus
from hydrosoft.services.bus.config import load_config
from hydrosoft.services.recording.mcap_format import RecordedMessage, raw_channel_metadata, read_recording
from hydrosoft.services.commands.replay import (
    MAX_BEHIND_S,
    ReplayError,
    ReplayStats,
    Schedule,
    endpoint_kind,
    in_stamp_order,
    plan_publishers,
)

REPLAY_TIMEOUT_S = 60.0
RATE_TOLERANCE = 0.05
MIN_RATE_MESSAGES = 10  # topics with fewer messages are compared by count and contents only


def channel(topic: str, kind: type[msg.Message], source: str) -> Channel:
    return Channel(id=len(topic), schema_id=1, topic=f"{source}/{topic}", message_encoding="json",
                   metadata=raw_channel_metadata(topic, kind, source))


def item(topic: str, stamp_ns: int) -> RecordedMessage:
    return RecordedMessage(topic, msg.Heartbeat(period_s=0.1, stamp_ns=stamp_ns), stamp_ns)


def test_a_late_replay_catches_up_a_little_and_slips_past_that_without_a_burst():
    """Messages every 10 ms at rate 2 (due every 5 ms); the replay stalls 0.5 s before the fourth message."""
    stats = ReplayStats()
    schedule = Schedule(2.0, stats)
    stamps = [k * 10_000_000 for k in range(8)]
    assert schedule.wait_s(stamps[0], 100.0) == 0.0  # anchors the schedule
    assert schedule.wait_s(stamps[1], 100.0) == pytest.approx(0.005)
    assert schedule.wait_s(stamps[2], 100.01 + MAX_BEHIND_S / 2) == 0.0  # a little late: sent at once, caught up
    assert stats.max_late_s == pytest.approx(MAX_BEHIND_S / 2) and stats.slipped_s == 0
    assert schedule.wait_s(stamps[3], 100.5) == 0.0  # stalled: slips to now
    assert stats.slipped_s == pytest.approx(0.5 - 0.015)
    now = 100.5
    for stamp in stamps[4:]:  # the rest keep the recorded spacing from the late message: no burst
        assert schedule.wait_s(stamp, now) == pytest.approx(0.005)
        now += 0.005


def test_messages_go_out_in_stamp_order_and_each_kind_to_its_endpoint():
    received = [item("a", s) for s in (10, 30, 20, 40, 25, 100, 90, 200)]
    assert [i.message.stamp_ns for i in in_stamp_order(received, window_ns=50)] == [10, 20, 25, 30, 40, 90, 100, 200]
    assert [endpoint_kind(k) for k in (msg.Wrench, msg.Heartbeat, msg.ServiceStatus, msg.StatusReply, msg.Stop)] == [
        "data", "status", "status", None, None]
    config = load_config(write_config(short_root()))
    channels = {f"{source}/{topic}": channel(topic, kind, source) for topic, kind, source in [
        ("wrench/bubble", msg.Wrench, "ft_reader-bubble"), ("heartbeat/planner", msg.Heartbeat, "planner"),
        ("reply/status", msg.StatusReply, "planner")]}
    routes, skipped = plan_publishers(channels, config)
    assert routes == {"ft_reader-bubble/wrench/bubble": (config.endpoint("ft_reader-bubble"), "ft_reader-bubble"),
                      "planner/heartbeat/planner": (config.endpoint("planner", "status"), "planner")}
    assert list(skipped) == ["planner/reply/status"]
    channels["someone/wrench/other"] = channel("wrench/other", msg.Wrench, "someone")
    with pytest.raises(ReplayError, match="'someone'.*--topics"):
        plan_publishers(channels, config)
    remove_root(Path(config.run_dir).parent)


async def collect(endpoints: list[str], replay: subprocess.Popen) -> list[tuple[str, msg.Message]]:
    """Every message published on ``endpoints`` until the replay process exits (plus a moment)."""
    received = []
    with Bus() as bus:
        sock = bus.socket(zmq.SUB, endpoints, bind=False, options=[
            (zmq.RCVHWM, 10000), (zmq.RECONNECT_IVL, 10), (zmq.SUBSCRIBE, b"")])
        end_s = None
        while end_s is None or time.monotonic() < end_s:
            if end_s is None and replay.poll() is not None:
                end_s = time.monotonic() + 1.0
            if await sock.poll(100):
                received.append(msg.decode(sock.recv_multipart(zmq.NOBLOCK).result()))
    return received


def rate_hz(stamps_ns: list[int]) -> float:
    """Messages per second: the inverse of the least-squares slope of ``stamps_ns`` over the message index (on a
    busy machine one late send at either end of a few seconds' run moves the first-to-last rate by several per
    cent; the fit weighs every message alike)."""
    slope_ns = np.polyfit(np.arange(len(stamps_ns)), np.asarray(stamps_ns, dtype=np.float64) - stamps_ns[0], 1)[0]
    return 1e9 / float(slope_ns)


def test_a_replay_reproduces_rates_and_contents_and_a_fresh_tag_tracker_gives_the_recorded_poses(recorded_run):
    run = recorded_run
    recorded, _ = read_recording(run.clean)
    replayed_topics = sorted(topics(run.config))
    root = short_root()
    config_path = write_config(root)
    config = load_config(config_path)
    tracker = service("tag_tracker", config_path, root)
    replay = None
    try:
        tracker.wait_ready()
        endpoints = [config.endpoint(name) for name in config.service_names()]
        replay = subprocess.Popen([sys.executable, "-m", "hydrosoft.services.commands.replay", str(run.clean), "--config",
                                   str(config_path), "--json", "--topics", *replayed_topics],
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        received = asyncio.run(asyncio.wait_for(collect(endpoints, replay), REPLAY_TIMEOUT_S))
        out, err = replay.communicate(timeout=REPLAY_TIMEOUT_S)
    finally:
        if replay is not None and replay.poll() is None:
            replay.kill()
            replay.wait()
        tracker.stop()
        remove_root(root)
    assert replay.returncode == 0, err.decode()
    for topic in replayed_topics:
        before = [i.message for i in recorded if i.topic == topic]
        after = [m for t, m in received if t == topic]
        assert len(after) == len(before), topic
        for old, new in zip(before, after):
            assert_same(new, old, ignore=("seq", "stamp_ns"))
        if len(before) >= MIN_RATE_MESSAGES:
            old_hz, new_hz = rate_hz([m.stamp_ns for m in before]), rate_hz([m.stamp_ns for m in after])
            assert abs(new_hz / old_hz - 1) < RATE_TOLERANCE, (topic, old_hz, new_hz)
    live = {i.message.hw_stamp_ns: i.message.pose for i in recorded if i.topic == "object_pose/object"}
    rerun = {m.hw_stamp_ns: m.pose for t, m in received if t == "object_pose/object"}
    common = sorted(set(live) & set(rerun))
    assert len(common) >= 5, (len(live), len(rerun), len(common))  # each tracker skips images when it lags
    for stamp in common:
        np.testing.assert_allclose(rerun[stamp], live[stamp], rtol=0, atol=1e-9)
