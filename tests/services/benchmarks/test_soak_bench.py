"""``bench soak``: its plain parts (the latency split from plan stamps, the windows, the growth, the table, the
memory probe). The whole benchmark launches the sim stack for minutes, so it is run by hand (``hydrosoft-stack
bench soak``), not here."""

from __future__ import annotations

import argparse
import math
import os

import numpy as np
import pytest

from hydrosoft.services.bus import messages as msg
import threading
import time

from hydrosoft.services.benchmarks.launched_stack import resident_mb, thread_cpu_times_s
from hydrosoft.services.benchmarks.soak import (
    ROLLING_RADIUS_M,
    SOAK_GOALS,
    Samples,
    add_arguments,
    format_table,
    growth,
    latency_series,
    latency_split,
    run,
    servo_ticks,
    tail_parts,
    thread_split,
    window_summary,
)

MS = 1_000_000


def plan(image_ms: float, solve_ms: float) -> msg.Plan:
    """A plan whose image was taken at ``image_ms``, 10 ms before its pose, 5 ms before it was taken, 2 ms before
    the solve, which took ``solve_ms``."""
    stamps = np.cumsum([image_ms, 10, 5, 2, solve_ms]) * MS
    return msg.Plan(task="pushing", actions=np.zeros((2, 1, 6)), predicted_object_poses=np.tile([0, 0, 0, 1, 0, 0, 0.0],
                    (2, 1)), predicted_forces=np.zeros((1, 3, 3)), cost=1.0, solve_ms=solve_ms,
                    **dict(zip(("image_stamp_ns", "pose_stamp_ns", "inputs_ns", "solve_start_ns", "targets_ns"),
                               (int(v) for v in stamps))))


def parts_plan(detection_ms: float, queue_ms: float, estimation_ms: float, solve_ms: float) -> msg.Plan:
    """A plan whose parts took these times (ms), its image at 1 s."""
    stamps = np.cumsum([1000.0, detection_ms, queue_ms, estimation_ms, solve_ms]) * MS
    return msg.Plan(task="pushing", actions=np.zeros((2, 1, 6)), predicted_object_poses=np.tile([0, 0, 0, 1, 0, 0, 0.0],
                    (2, 1)), predicted_forces=np.zeros((1, 3, 3)), cost=1.0, solve_ms=solve_ms,
                    **dict(zip(("image_stamp_ns", "pose_stamp_ns", "inputs_ns", "solve_start_ns", "targets_ns"),
                               (int(v) for v in stamps))))


def test_the_rolling_goals_are_rolls_of_the_sim_cylinder():
    """Each rolling goal turns the cylinder by its move over the task scene's radius, the same way round (a move alone
    is a slide: no goal of it was ever reached)."""
    from hydrosoft.tasks import make_task

    radius_m = float(make_task("rolling").scene.object.params["radius"])
    assert ROLLING_RADIUS_M == radius_m
    for goal in SOAK_GOALS["rolling"]:
        assert goal["dx_m"] != 0 and goal["dpitch_rad"] == pytest.approx(goal["dx_m"] / radius_m, rel=1e-12)
    assert {math.copysign(1, goal["dx_m"]) for goal in SOAK_GOALS["rolling"]} == {-1.0, 1.0}  # back and forth


def test_the_tail_names_the_parts_that_made_the_slowest_plans_slow():
    typical = [parts_plan(20, 5 + k % 10, 4, 60 + k % 7) for k in range(96)]
    slow_solve = [parts_plan(20, 5, 4, 150), parts_plan(20, 5, 4, 140)]  # a solve's tail alone
    late_both = [parts_plan(60, 61, 4, 120), parts_plan(20, 61, 4, 125)]  # a late pose and a slow solve together
    tail = tail_parts(typical + slow_solve + late_both, fraction=0.04)
    assert tail["plans"] == 4 and tail["total_from_ms"] == 169.0
    solve, queue, detection = tail["parts"]["solve"], tail["parts"]["queue"], tail["parts"]["detection"]
    assert solve["above_p90"] == 4 and queue["above_p90"] == 2 and detection["above_p90"] == 1
    assert tail["together"] == 2 and tail["parts"]["estimation"]["excess_share"] == 0.0
    assert tail["solver_ms"] == 133.75 and tail["solver_p50_ms"] == 63.0  # the plans' own solve_ms
    assert solve["mean_ms"] == 133.75 and solve["excess_share"] > 0.5 > queue["excess_share"] > 0.0
    assert sum(row["excess_share"] for row in tail["parts"].values()) == pytest.approx(1.0, abs=0.002)
    assert tail_parts(typical[:10], fraction=0.02)["plans"] == 1
    unstamped = parts_plan(20, 5, 4, 60)
    assert tail_parts([msg.Plan(**{**{f: getattr(unstamped, f) for f in unstamped.__struct_fields__},
                                   "image_stamp_ns": 0})]) == {}


def test_the_series_gives_each_stretch_of_the_soak_its_own_total_latency_and_skips_none():
    # Slow plans at the start (a first goal's solves at 150 ms), steady ones later, nothing in the third stretch.
    plans = [(1.0 + k, parts_plan(20, 5, 4, 150)) for k in range(3)]
    plans += [(10.5 + 0.5 * k, parts_plan(20, 5, 4, 60 + k)) for k in range(10)] + [(35.0, parts_plan(20, 5, 4, 70))]
    series = latency_series(plans, period_s=10.0)
    assert [row["from_s"] for row in series] == [0.0, 10.0, 20.0, 30.0]
    assert [row["plans"] for row in series] == [3, 10, 0, 1]
    assert series[0]["p99_ms"] == series[0]["max_ms"] == 179.0  # 20 + 5 + 4 + 150
    assert series[1]["max_ms"] == 98.0 and series[1]["p50_ms"] == pytest.approx(93.5)
    assert "p99_ms" not in series[2] and series[3]["max_ms"] == 99.0
    unstamped = parts_plan(20, 5, 4, 60)
    no_image = msg.Plan(**{**{f: getattr(unstamped, f) for f in unstamped.__struct_fields__}, "image_stamp_ns": 0})
    assert latency_series([(1.0, no_image)]) == []


def arm_state(seq: int, stamp_ms: float, servo_active: bool = True) -> msg.ArmState:
    return msg.ArmState(arm="bubble", tcp_pose=np.array([0.0, 0.0, 0.1, 1.0, 0.0, 0.0, 0.0]), tcp_speed=np.zeros(6),
                        running=True, protective_stop=False, emergency_stop=False, servo_active=servo_active,
                        seq=seq, stamp_ns=int(stamp_ms * MS))


def test_servo_ticks_time_each_servoed_tick_and_count_the_late_ones_but_no_gap_of_a_lost_message_or_a_rest():
    # 8 ms ticks, one 20 ms late (over 2 periods: late) and one 15 ms (not); then a lost message (seq 7 -> 9), a rest
    # (servo inactive for 500 ms) and servoing again: neither of the last two is a tick interval.
    stamps = [0, 8, 16, 36, 44, 59, 67]
    states = [arm_state(seq, ms) for seq, ms in enumerate(stamps, start=1)]
    states += [arm_state(9, 75), arm_state(10, 83, servo_active=False), arm_state(11, 583), arm_state(12, 591)]
    ticks = servo_ticks(states, period_s=0.008)
    assert ticks["ticks"] == 7  # seq 1-7 give 6, and 11 -> 12 one
    assert ticks["max_ms"] == 20.0 and ticks["late"] == 1 and ticks["p50_ms"] == 8.0
    assert servo_ticks(states[:1], period_s=0.008) == {}
    assert servo_ticks([arm_state(1, 0, False), arm_state(2, 8, False)], period_s=0.008) == {}


def test_the_latency_split_takes_each_stage_between_its_stamps():
    split = latency_split([plan(1000.0 + k, 100.0 + k) for k in range(101)])
    assert split["detection"]["p50_ms"] == 10.0 and split["queue"]["p50_ms"] == 5.0
    assert split["estimation"]["p50_ms"] == 2.0 and split["solve"]["p50_ms"] == 150.0
    assert split["total"]["p50_ms"] == 167.0 and split["total"]["p99_ms"] == 216.0 and split["solve"]["plans"] == 101
    unstamped = plan(1000.0, 100.0)
    assert latency_split([msg.Plan(**{**{f: getattr(unstamped, f) for f in unstamped.__struct_fields__},
                                      "image_stamp_ns": 0})]).keys() == {"queue", "estimation", "solve"}


def test_windows_compare_memory_cpu_and_latency_and_the_growth_names_each():
    samples = Samples()
    for t in range(0, 601, 5):  # 100 MB growing 0.1 MB/s; 0.5 s of CPU per 5 s: 10 % of one core
        samples.usage["planner"].append((float(t), 100 + 0.1 * t, 0.1 * t))
        samples.plans.append((float(t), plan(1000.0 * t, 100.0 if t < 300 else 120.0)))
    first, last = window_summary(samples, 0, 60), window_summary(samples, 540, 600)
    assert first["services"]["planner"] == {"rss_mb": 103.0, "cpu_percent": 10.0}
    assert last["services"]["planner"]["rss_mb"] == 157.0 and last["latency"]["solve"]["p50_ms"] == 120.0
    grown = growth(first, last)
    assert grown["rss.planner"] == round(157 / 103 - 1, 3) and grown["latency.solve"] == 0.2
    table = format_table({"idle": {"cpu_percent_total": 12.5, "services": {"planner": {"cpu_percent": 12.5}},
                                   "threads": {"planner": {"main": 2.0, "zmq": 0.5, "others": [6.0, 4.0]}}},
                          "soak_seconds": 600.0, "goals": [{"outcome": "reached", "reapproaches": 1},
                                                           {"outcome": "timeout", "reapproaches": 2}],
                          "first": first, "last": last, "growth": grown,
                          "whole": window_summary(samples, 0, 600), "replanning_hz": 9.5,
                          "errors": {"sim_world": {"physics_behind": 7, "tag_camera": 1}},
                          "load_average": {"idle_start": 1.2, "soak_start": 2.5, "soak_end": 3.75}})
    assert "load average (1 min) at the idle phase's start, the goals' start and end: 1.2 / 2.5 / 3.75" in table
    assert "idle: 12.5 % of one core in all (planner 12.5)" in table
    assert "idle planner: main thread 2.0, zmq 0.5, other threads 6.0 + 4.0" in table
    assert "2 goals, 1 reached, 3 re-approaches of a lost cube" in table
    assert "errors counted: sim_world physics_behind 7, tag_camera 1" in table
    assert "replanning: 9.5 Hz over the goals' time; camera to arm targets over the whole soak: 137.0 / 137.0 ms" in table
    assert "latency solve" in table and "0.2" in table


def test_the_thread_split_names_the_main_thread_zmq_and_the_busiest_others():
    before = {10: ("python3", 1.0), 11: ("ZMQbg/IO/0", 0.5), 12: ("python3", 2.0), 13: ("ZMQbg/Reaper", 0.0)}
    after = {10: ("python3", 1.5), 11: ("ZMQbg/IO/0", 0.6), 12: ("python3", 2.2), 13: ("ZMQbg/Reaper", 0.1),
             14: ("python3", 1.0)}  # 14 started in between
    assert thread_split(10, before, after, 10.0) == {"main": 5.0, "zmq": 2.0, "others": [10.0, 2.0]}


def test_a_busy_thread_of_this_process_shows_among_the_others():
    """A thread spinning while the main thread sleeps: read while it still runs (a thread that ended is gone)."""
    pid, done = os.getpid(), threading.Event()
    worker = threading.Thread(target=lambda: [None for _ in iter(done.is_set, True)])
    before, tic = thread_cpu_times_s(pid), time.monotonic()
    worker.start()
    try:
        time.sleep(1.0)
        after = thread_cpu_times_s(pid)
    finally:
        done.set()
        worker.join()
    split = thread_split(pid, before, after, time.monotonic() - tic)
    # On a loaded machine the spinning thread may get far less than a core; it still gets far more than the sleeper.
    assert split["others"] and split["others"][0] > max(2.0, 10 * split["main"])


def test_resident_memory_of_this_process():
    assert 10 < resident_mb(os.getpid()) < 20_000


@pytest.mark.parametrize("argv, named", [(["--minutes", "1", "--window", "40"], "--window must be at most half"),
                                         (["--idle-seconds", "5"], "--idle-seconds and --window"),
                                         (["--minutes", "1", "--window", "5"], "--idle-seconds and --window"),
                                         (["--background-load", "-0.5"], "--background-load must be between"),
                                         (["--background-load", "nan"], "--background-load must be between"),
                                         (["--background-load", "64"], "--background-load must be between")])
def test_settings_that_cannot_be_measured_are_refused_before_launching(argv, named, capsys):
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    assert run(parser.parse_args(argv)) == 2
    assert named in capsys.readouterr().err
