"""``hydrosoft-stack bench soak``: the sim stack idle, then running goals back to back, measured in one run.

The benchmark launches the sim stack of CONFIG (default ``deploy/sim.toml``, made private: its own run_dir and
127.0.0.N), then:

- **idle** (``--idle-seconds``, no goal): each service's CPU use (% of one core, from ``/proc``) and the sum, and
  its split over threads (``thread_split``): the asyncio loop's main thread, ZeroMQ's I/O threads and the others
  (worker threads, and native ones such as ur_rtde's receive threads in the arm commander);
- **soak** (``--minutes``): goals back to back, there and back again (pushing: +-3 cm along x; rolling: +-3 cm
  rolls, turned 3 cm / radius about y; rotation: +-20 deg), each waited for (``GOAL_TIMEOUT_S``) and its outcome
  (with the reason of one not reached), true error and re-approaches of a lost object kept. Meanwhile every
  ``SAMPLE_PERIOD_S`` each service's resident memory and CPU time are sampled, and every plan the planner publishes
  is read for its way from the camera to the arm targets (``msg.Plan``'s stamps), split into detection (image to
  the tracker's pose), queue (pose to the planner taking it), estimation (to the solve's start), solve (to the
  targets sent) and the total;
- each service's error counts at the end (``status``: e.g. sim_world's ``physics_behind``, ticks that lost
  simulated time);
- the first and the last ``--window`` seconds of the soak compared: per service the mean memory (MB) and CPU
  use, and the latency split (p50 and p99, ms), with each one's growth (last / first - 1). The issue's target:
  neither memory nor the loop latency grows by more than 10 % over 10 minutes;
- over the whole soak (``whole``): the latency split, and the replanning rate (``replanning_hz``: plans published
  per second of the goals' wall time);
- the slowest plans (``tail``, ``tail_parts``): which parts made the p99 of the total, one part alone or several
  late together;
- the total's p50, p99 and largest per ``SERIES_PERIOD_S`` of the soak (``series``, ``latency_series``): whether the
  slow plans gather at a time (the goals' start, one goal) or spread over the soak;
- the arm commanders' servo ticks (``servo_ticks``): the intervals between the ``arm_state`` messages each commander
  publishes while it servoes (one per tick), p50, p99 and largest, and how many exceeded ``LATE_TICK_PERIODS``
  servo periods: a commander that waits for a core ticks late, and a few late periods in a row let the controller's
  watchdog stop the arm;
- the host's load average (``load_average``: ``os.getloadavg``'s 1-minute figure when the idle phase starts, when the
  goals start and when they end): other work on the machine slows the stack, so figures compare only at like loads;
- with ``--background-load CORES``, that much other work made on purpose (``cpu_load``) from the idle phase to the
  end, and the CPU it got (``background_load``): the stack's margin against a known load, in any hour.

It prints a table and one JSON document (only the document with ``--json``). Every process it starts is stopped
by its pid. Latencies are the planner host's monotonic clock, so they are meaningful in sim mode; in the lab the
image stamp is the camera's own clock.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import shutil
import sys
import tempfile
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import zmq

from hydrosoft.services.bus import messages as msg
from hydrosoft.services.benchmarks.cpu_load import load_processes
from hydrosoft.services.benchmarks.launched_stack import (
    Child,
    add_config_argument,
    cpu_time_s,
    private_config,
    resident_mb,
    stack_ready_s,
    start_goal,
    thread_cpu_times_s,
)
from hydrosoft.services.bus.sockets import Bus
from hydrosoft.services.client import true_error_mm
from hydrosoft.services.bus.config import StackConfig, load_config
from hydrosoft.services.commands.status import collect

SAMPLE_PERIOD_S = 5.0  # memory and CPU time of every service, this often
GOAL_TIMEOUT_S = 120.0  # one goal of the soak
STATUS_WINDOW_S = 5.0  # how long to listen for the services' status (their pids)
#: The sim cylinder's radius, m (the rolling task's scene): a roll by d along x turns it by d / radius about y.
ROLLING_RADIUS_M = 0.025
#: The goals of the soak per task: keyword arguments of ``StackClient.set_goal``, alternated. A rolling goal is a
#: roll (moved along x and turned about y as rolling without slipping does): a move alone asks the cylinder to slide,
#: which the bubble cannot do, and every such goal failed for want of progress.
SOAK_GOALS = {
    "pushing": ({"dx_m": 0.03}, {"dx_m": -0.03}),
    "rolling": ({"dx_m": 0.03, "dpitch_rad": 0.03 / ROLLING_RADIUS_M},
                {"dx_m": -0.03, "dpitch_rad": -0.03 / ROLLING_RADIUS_M}),
    "rotation": ({"dyaw_rad": 0.35}, {"dyaw_rad": -0.35}),
}
#: The stages of a plan's way from the camera to the targets: name -> (from stamp, to stamp) of ``msg.Plan``.
STAGES = {
    "detection": ("image_stamp_ns", "pose_stamp_ns"),
    "queue": ("pose_stamp_ns", "inputs_ns"),
    "estimation": ("inputs_ns", "solve_start_ns"),
    "solve": ("solve_start_ns", "targets_ns"),
    "total": ("image_stamp_ns", "targets_ns"),
}
#: The parts that add up to a plan's total (``STAGES`` less the total).
PARTS = ("detection", "queue", "estimation", "solve")
#: ``tail_parts`` looks at this fraction of the plans, the slowest by their total (at least one plan).
TAIL_FRACTION = 0.02
SERIES_PERIOD_S = 10.0  # the length of each stretch of the soak ``latency_series`` sums up, s
LATE_TICK_PERIODS = 2.0  # ``servo_ticks`` counts an interval between two servo ticks longer than this many periods


def latency_split(plans: list[msg.Plan]) -> dict[str, dict[str, float]]:
    """Per stage of ``STAGES``: p50 and p99 (ms) over the plans that carry both of its stamps."""
    split = {}
    for stage, (start, end) in STAGES.items():
        ms = [_stage_ms(p, stage) for p in plans if getattr(p, start) and getattr(p, end)]
        if ms:
            split[stage] = {"p50_ms": round(float(np.percentile(ms, 50)), 2),
                            "p99_ms": round(float(np.percentile(ms, 99)), 2), "plans": len(ms)}
    return split


def _stage_ms(plan: msg.Plan, stage: str) -> float:
    """The time (ms) ``plan`` spent in ``stage`` of ``STAGES``, between its two stamps."""
    start, end = STAGES[stage]
    return (getattr(plan, end) - getattr(plan, start)) * 1e-6


def tail_parts(plans: list[msg.Plan], fraction: float = TAIL_FRACTION) -> dict[str, object]:
    """What made the slowest ``fraction`` of the plans (by their total, camera image to arm targets) slow.

    Over the plans that carry every stamp: ``plans`` (how many are in the tail) and ``total_from_ms`` (the fastest
    of them); per part of ``PARTS`` its mean in the tail (``mean_ms``) and its p50 and p90 over all plans;
    ``excess_share``, each part's share of the tail's time over the parts' p50s (sum of ``max(0, part - p50)``
    over the tail plans, divided by that of all parts; 0 to 1); ``above_p90``, in how many tail plans the part
    was above its own p90; ``together``, in how many tail plans two or more parts were above their p90 (late
    together, e.g. a slow solve on a late pose) rather than one part alone; and ``solver_ms``, the tail's mean of
    the solver's own time (``msg.Plan.solve_ms``: the CEM steps and the slower worker share's compute; the solve
    part adds the shares' transport, a worker's wait for a core, and the targets' making and sending), and
    ``solver_p50_ms``, its p50 over all plans. Empty when no plan has every stamp."""
    whole = [p for p in plans if all(getattr(p, stamp) for stage in PARTS for stamp in STAGES[stage])]
    if not whole:
        return {}
    ms = {stage: np.array([_stage_ms(p, stage) for p in whole]) for stage in (*PARTS, "total")}
    count = max(1, math.ceil(fraction * len(whole)))
    tail = np.argsort(ms["total"])[-count:]
    p50 = {part: float(np.percentile(ms[part], 50)) for part in PARTS}
    p90 = {part: float(np.percentile(ms[part], 90)) for part in PARTS}
    excess = {part: float(np.clip(ms[part][tail] - p50[part], 0, None).sum()) for part in PARTS}
    late = {part: ms[part][tail] > p90[part] for part in PARTS}
    excess_sum = sum(excess.values())
    return {"plans": int(count), "total_from_ms": round(float(ms["total"][tail].min()), 2),
            "parts": {part: {"mean_ms": round(float(ms[part][tail].mean()), 2), "p50_ms": round(p50[part], 2),
                             "p90_ms": round(p90[part], 2),
                             "excess_share": round(excess[part] / excess_sum, 3) if excess_sum > 0 else 0.0,
                             "above_p90": int(late[part].sum())} for part in PARTS},
            "together": int((np.sum([late[part] for part in PARTS], axis=0) >= 2).sum()),
            "solver_ms": round(float(np.mean([whole[i].solve_ms for i in tail])), 2),
            "solver_p50_ms": round(float(np.percentile([p.solve_ms for p in whole], 50)), 2)}


def latency_series(plans: list[tuple[float, msg.Plan]], period_s: float = SERIES_PERIOD_S) -> list[dict[str, float]]:
    """Per ``period_s`` of the soak (``plans``: ``(t_s, Plan)``, times since the soak began), from its first stretch
    to its last: ``from_s`` and, over the plans published in it that carry both stamps of the total, ``plans`` and
    the total's ``p50_ms``, ``p99_ms`` and ``max_ms`` (a stretch without such a plan has ``plans`` 0 only)."""
    start, end = STAGES["total"]
    timed = [(t_s, _stage_ms(plan, "total")) for t_s, plan in plans if getattr(plan, start) and getattr(plan, end)]
    if not timed:
        return []
    series = []
    for index in range(int(max(t_s for t_s, _ in timed) // period_s) + 1):
        ms = [value for t_s, value in timed if index * period_s <= t_s < (index + 1) * period_s]
        row: dict[str, float] = {"from_s": round(index * period_s, 1), "plans": len(ms)}
        if ms:
            row.update(p50_ms=round(float(np.percentile(ms, 50)), 1), p99_ms=round(float(np.percentile(ms, 99)), 1),
                       max_ms=round(max(ms), 1))
        series.append(row)
    return series


def servo_ticks(states: list[msg.ArmState], period_s: float) -> dict[str, float]:
    """The intervals (ms) between consecutive ``states`` of one arm (in the order published) that both servoed
    (``servo_active``), each a commander tick: ``ticks`` (intervals), ``p50_ms``, ``p99_ms``, ``max_ms``, and ``late``,
    those over ``LATE_TICK_PERIODS`` x ``period_s`` (s). Empty when fewer than two servoed."""
    ms = [(b.stamp_ns - a.stamp_ns) * 1e-6 for a, b in zip(states, states[1:])
          if a.servo_active and b.servo_active and b.seq == a.seq + 1]
    if not ms:
        return {}
    return {"ticks": len(ms), "p50_ms": round(float(np.percentile(ms, 50)), 2),
            "p99_ms": round(float(np.percentile(ms, 99)), 2), "max_ms": round(max(ms), 2),
            "late": sum(m > LATE_TICK_PERIODS * period_s * 1e3 for m in ms)}


@dataclass
class Samples:
    """What the soak saw: per service ``(t_s, resident MB, CPU time s)`` samples, the plans ``(t_s, Plan)``
    (times since the soak began), and each arm's states in the order published."""

    usage: dict[str, list[tuple[float, float, float]]] = field(default_factory=lambda: defaultdict(list))
    plans: list[tuple[float, msg.Plan]] = field(default_factory=list)
    arm_states: dict[str, list[msg.ArmState]] = field(default_factory=lambda: defaultdict(list))


def window_summary(samples: Samples, start_s: float, end_s: float) -> dict[str, object]:
    """Within ``[start_s, end_s]``: per service its mean memory (MB) and CPU use (% of one core, between the first
    and the last sample), and the plans' latency split."""
    services = {}
    for name, rows in sorted(samples.usage.items()):
        inside = [row for row in rows if start_s <= row[0] <= end_s]
        if len(inside) < 2:
            continue
        cpu = 100 * (inside[-1][2] - inside[0][2]) / (inside[-1][0] - inside[0][0])
        services[name] = {"rss_mb": round(float(np.mean([r[1] for r in inside])), 1), "cpu_percent": round(cpu, 1)}
    plans = [plan for t, plan in samples.plans if start_s <= t <= end_s]
    return {"from_s": round(start_s, 1), "to_s": round(end_s, 1), "services": services,
            "latency": latency_split(plans)}


def growth(first: dict[str, object], last: dict[str, object]) -> dict[str, float]:
    """``last / first - 1`` of each service's memory (``rss.NAME``) and each stage's p50 latency
    (``latency.STAGE``)."""
    out = {}
    for name, row in first["services"].items():
        if name in last["services"] and row["rss_mb"] > 0:
            out[f"rss.{name}"] = round(last["services"][name]["rss_mb"] / row["rss_mb"] - 1, 3)
    for stage, row in first["latency"].items():
        if stage in last["latency"] and row["p50_ms"] > 0:
            out[f"latency.{stage}"] = round(last["latency"][stage]["p50_ms"] / row["p50_ms"] - 1, 3)
    return out


def thread_split(pid: int, before: dict[int, tuple[str, float]], after: dict[int, tuple[str, float]],
                 seconds: float) -> dict[str, object]:
    """A process's CPU use between two ``thread_cpu_times_s`` readings ``seconds`` apart, split by thread (% of one
    core, 0.1 % steps): ``main`` (the thread whose id is ``pid``), ``zmq`` (ZeroMQ's ``ZMQbg/...`` threads, summed)
    and ``others`` (every other thread that used CPU, busiest first; a thread that started between the readings
    counts from zero)."""
    split: dict[str, object] = {"main": 0.0, "zmq": 0.0, "others": []}
    for tid, (name, end_s) in after.items():
        percent = 100 * (end_s - before.get(tid, (name, 0.0))[1]) / seconds
        if tid == pid:
            split["main"] = round(percent, 1)
        elif name.startswith("ZMQbg"):
            split["zmq"] = round(split["zmq"] + percent, 1)
        elif round(percent, 1) > 0:
            split["others"].append(round(percent, 1))
    split["others"].sort(reverse=True)
    return split


def _thread_times(pids: dict[str, int]) -> dict[str, dict[int, tuple[str, float]]]:
    times = {}
    for name, pid in pids.items():
        try:
            times[name] = thread_cpu_times_s(pid)
        except OSError:  # the service died (the launcher restarts it): no split for it
            continue
    return times


async def _sample(pids: dict[str, int], samples: Samples, t0_s: float, until_s: float) -> None:
    """Sample each service's memory and CPU time every ``SAMPLE_PERIOD_S`` until ``until_s`` (monotonic; inf: until
    cancelled)."""
    while time.monotonic() < until_s:
        now_s = time.monotonic() - t0_s
        for name, pid in pids.items():
            try:
                samples.usage[name].append((now_s, resident_mb(pid), cpu_time_s(pid)))
            except (OSError, ValueError):  # the service died (the launcher restarts it): a gap, not an error
                continue
        await asyncio.sleep(SAMPLE_PERIOD_S)


def _subscriber(bus: Bus, endpoints: list[str], prefix: bytes) -> zmq.asyncio.Socket:
    """A SUB socket on ``endpoints`` for the topics that start with ``prefix``, queueing up to 1000 messages."""
    return bus.socket(zmq.SUB, endpoints, bind=False,
                      options=[(zmq.RCVHWM, 1000), (zmq.MAXMSGSIZE, msg.MAX_FRAME_BYTES), (zmq.SUBSCRIBE, prefix)])


async def _read_plans(config: StackConfig, samples: Samples, t0_s: float, until_s: float) -> None:
    """Keep every plan the planner publishes until ``until_s`` (monotonic; inf: until cancelled)."""
    with Bus() as bus:
        sock = _subscriber(bus, [config.endpoint("planner")], b"plan/")
        while (left_s := until_s - time.monotonic()) > 0:
            if not await sock.poll(max(1, int(min(left_s, 1.0) * 1000))):
                continue
            _, plan = msg.decode(await sock.recv_multipart(copy=False))
            if isinstance(plan, msg.Plan):
                samples.plans.append((time.monotonic() - t0_s, plan))


async def _read_arm_states(config: StackConfig, samples: Samples) -> None:
    """Keep every state each arm commander publishes until cancelled."""
    with Bus() as bus:
        sock = _subscriber(bus, [config.endpoint(f"arm_commander-{arm.name}") for arm in config.arms], b"arm_state/")
        while True:
            _, state = msg.decode(await sock.recv_multipart(copy=False))
            if isinstance(state, msg.ArmState):
                samples.arm_states[state.arm].append(state)


async def _goals(config_path: Path, task: str, until_s: float) -> list[dict[str, object]]:
    """Goals of ``SOAK_GOALS[task]`` back to back until ``until_s`` (monotonic); each one's outcome, planner error,
    true error (mm), solves, re-approaches of a lost cube and wall time."""
    results = []
    while time.monotonic() < until_s:
        goal = SOAK_GOALS[task][len(results) % 2]
        tic_s = time.monotonic()
        client = await start_goal(config_path, task, tolerance_mm=3.0, timeout_s=GOAL_TIMEOUT_S, **goal)
        try:
            reply = await client.wait(GOAL_TIMEOUT_S + 10)
            true = await true_error_mm(client, reply.goal.target_pose, task)
        finally:
            client.close()
        results.append({"goal": goal, "outcome": reply.outcome, "reason": reply.outcome_reason,
                        "error_mm": round(reply.error_mm, 2),
                        "true_error_mm": None if true is None else round(true, 2), "solves": reply.solves,
                        "reapproaches": reply.reapproaches, "seconds": round(time.monotonic() - tic_s, 1)})
        lost = f", {reply.reapproaches} re-approaches" if reply.reapproaches else ""
        why = f" ({reply.outcome_reason})" if reply.outcome_reason else ""
        print(f"[soak] goal {len(results)} {goal}: {reply.outcome}{why}, {reply.error_mm:.2f} mm, {reply.solves} "
              f"solves{lost}", file=sys.stderr, flush=True)
    return results


async def _soak(config_path: Path, config: StackConfig, pids: dict[str, int], idle_s: float, soak_s: float,
                window_s: float) -> dict[str, object]:
    """The idle phase, then the soak, measured (module docstring)."""
    idle = Samples()
    load_average = {"idle_start": _load_average()}
    t0_s = time.monotonic()
    threads_before = _thread_times(pids)
    await _sample(pids, idle, t0_s, t0_s + idle_s)
    threads_after, idle_end_s = _thread_times(pids), time.monotonic()
    idle_summary = window_summary(idle, 0.0, idle_s)
    threads = {name: thread_split(pids[name], threads_before[name], threads_after[name], idle_end_s - t0_s)
               for name in sorted(threads_before.keys() & threads_after.keys())}
    samples = Samples()
    load_average["soak_start"] = _load_average()
    t0_s = time.monotonic()
    until_s = t0_s + soak_s
    watchers = [asyncio.create_task(_sample(pids, samples, t0_s, math.inf)),
                asyncio.create_task(_read_plans(config, samples, t0_s, math.inf)),
                asyncio.create_task(_read_arm_states(config, samples))]
    try:
        goals = await _goals(config_path, config.scene.task, until_s)
    finally:
        for task in watchers:
            task.cancel()
        await asyncio.gather(*watchers, return_exceptions=True)
    load_average["soak_end"] = _load_average()
    end_s = max(t for rows in samples.usage.values() for t, _, _ in rows)
    first = window_summary(samples, 0.0, window_s)
    last = window_summary(samples, end_s - window_s, end_s)
    goal_s = sum(goal["seconds"] for goal in goals)
    return {"idle": {"seconds": idle_s, "services": idle_summary["services"], "threads": threads,
                     "cpu_percent_total": round(sum(s["cpu_percent"] for s in idle_summary["services"].values()), 1)},
            "soak_seconds": round(end_s, 1), "goals": goals, "first": first, "last": last,
            "growth": growth(first, last), "whole": window_summary(samples, 0.0, end_s),
            "tail": tail_parts([plan for _, plan in samples.plans]),
            "series": latency_series(samples.plans),
            "servo_ticks": {arm: servo_ticks(states, 1.0 / config.limits.servo_rate_hz)
                            for arm, states in sorted(samples.arm_states.items())},
            "replanning_hz": round(len(samples.plans) / goal_s, 2) if goal_s > 0 else 0.0,
            "load_average": load_average}


def _load_average() -> float:
    """The host's 1-minute load average (runnable processes, all users)."""
    return round(os.getloadavg()[0], 2)


def start_background_load(cores: float, root: Path) -> list[Child]:
    """``cpu_load`` processes that together take ``cores`` of the host's cores, their output in ``root``."""
    return [Child([sys.executable, "-m", "hydrosoft.services.benchmarks.cpu_load", repr(fraction)],
                  root / f"cpu_load-{index}.log")
            for index, fraction in enumerate(load_processes(cores))]


def measure(config: Path, minutes: float, window_s: float, idle_s: float, keep: Path | None = None,
            background_cores: float = 0.0) -> dict[str, object]:
    """Launch the stack of ``config``, measure it idle, soak it with goals for ``minutes`` and compare the first and
    the last ``window_s`` (module docstring). ``keep``: a folder to keep the logs in. ``background_cores``: other work
    on the host, in cores, from the idle phase to the end."""
    root = Path(tempfile.mkdtemp(prefix="hs-soak-", dir="/tmp"))
    stack = None
    load: list[Child] = []
    try:
        config_path = private_config(config, root)
        stack_config = load_config(config_path)
        if stack_config.scene.task not in SOAK_GOALS:
            raise ValueError(f"bench soak has goals for {sorted(SOAK_GOALS)}, not {stack_config.scene.task!r}")
        stack = Child([sys.executable, "-m", "hydrosoft.services.commands.launch", str(config_path)],
                      root / "launcher.log")
        stack.wait_for("stack ready", stack_ready_s(stack_config))
        names = stack_config.service_names()
        reports = asyncio.run(collect(stack_config, names, STATUS_WINDOW_S))
        pids = {name: report["pid"] for name, report in reports.items() if report is not None}
        missing = sorted(set(names) - set(pids))
        if missing:
            raise RuntimeError(f"no status (pid) from {missing}; see {root / 'launcher.log'}")
        load = start_background_load(background_cores, root)
        load_start = [(time.monotonic(), cpu_time_s(child.process.pid)) for child in load]
        result = asyncio.run(_soak(config_path, stack_config, pids, idle_s, 60 * minutes, window_s))
        got = sum((cpu_time_s(child.process.pid) - cpu_s) / (time.monotonic() - t_s)
                  for child, (t_s, cpu_s) in zip(load, load_start))
        result["background_load"] = {"cores": background_cores, "processes": len(load),
                                     "cpu_percent": round(100 * got, 1)}
        reports = asyncio.run(collect(stack_config, names, STATUS_WINDOW_S))
        errors = {name: report["errors"] for name, report in reports.items() if report and report["errors"]}
        return {"config": str(config), "window_s": window_s, **result, "errors": errors}
    finally:
        for child in load:
            child.stop()
        if stack is not None:
            stack.stop()
        if keep is not None:
            keep.mkdir(parents=True, exist_ok=True)
            for path in [*root.glob("*.log"), *root.glob("*.toml")]:
                shutil.copy2(path, keep)
        shutil.rmtree(root, ignore_errors=True)


def format_table(result: dict[str, object]) -> str:
    """Idle CPU, then per service and latency stage the first and last window side by side with the growth."""
    first, last, grown = result["first"], result["last"], result["growth"]
    load = result.get("load_average", {})
    background = result.get("background_load", {})
    lines = ["load average (1 min) at the idle phase's start, the goals' start and end: "
             + " / ".join(str(load.get(key, "-")) for key in ("idle_start", "soak_start", "soak_end"))
             + (f"; background load asked {background['cores']} cores, got {background['cpu_percent']} % of one core"
                if background.get("processes") else ""),
             f"idle: {result['idle']['cpu_percent_total']} % of one core in all ("
             + ", ".join(f"{n} {s['cpu_percent']}" for n, s in result["idle"]["services"].items()) + ")"]
    for name, split in result["idle"].get("threads", {}).items():
        lines.append(f"  idle {name}: main thread {split['main']}, zmq {split['zmq']}, other threads "
                     + (" + ".join(str(p) for p in split["others"]) or "none"))
    outcomes = [g["outcome"] for g in result["goals"]]
    reapproaches = sum(g.get("reapproaches", 0) for g in result["goals"])
    lines.append(f"soak: {result['soak_seconds']} s, {len(outcomes)} goals, {outcomes.count('reached')} reached, "
                 f"{reapproaches} re-approaches of a lost cube")
    whole = result["whole"]["latency"].get("total")
    lines.append(f"replanning: {result['replanning_hz']} Hz over the goals' time; camera to arm targets over the "
                 "whole soak: " + (f"{whole['p50_ms']} / {whole['p99_ms']} ms (p50 / p99, {whole['plans']} plans)"
                                   if whole else "no plans"))
    tail = result.get("tail")
    if tail:
        parts = tail["parts"]
        lines.append(f"slowest {tail['plans']} plans (total >= {tail['total_from_ms']} ms), per part its mean there "
                     "(its p50 / p90 over all plans), share of the time over the p50s, plans above its p90: "
                     + "; ".join(f"{part} {row['mean_ms']} ({row['p50_ms']} / {row['p90_ms']}) ms, "
                                 f"{round(100 * row['excess_share'])} %, {row['above_p90']}"
                                 for part, row in parts.items())
                     + f"; two or more parts above their p90 in {tail['together']} of {tail['plans']}; the solver's "
                     f"own time there {tail['solver_ms']} ms (p50 over all plans {tail['solver_p50_ms']} ms)")
    series = result.get("series")
    if series:
        lines.append(f"camera to arm targets per {SERIES_PERIOD_S:g} s of the soak, p99 (largest) ms: "
                     + ", ".join(f"{row['p99_ms']} ({row['max_ms']})" if row["plans"] else "-" for row in series))
    for arm, ticks in result.get("servo_ticks", {}).items():
        lines.append(f"arm commander {arm}'s servo ticks: " + (
            f"{ticks['ticks']} intervals, p50 / p99 / largest {ticks['p50_ms']} / {ticks['p99_ms']} / "
            f"{ticks['max_ms']} ms, {ticks['late']} over {LATE_TICK_PERIODS:g} periods" if ticks else "none servoed"))
    lines.append("errors counted: " + ("; ".join(f"{name} " + ", ".join(f"{kind} {n}" for kind, n in kinds.items())
                                                 for name, kinds in result["errors"].items()) or "none"))
    lines.append(f"{'':<24}{'first window':>24}{'last window':>24}{'growth':>10}")
    for name, row in first["services"].items():
        end = last["services"].get(name, {})
        lines.append(f"{name:<24}{row['rss_mb']:>12} MB {row['cpu_percent']:>6} %"
                     f"{end.get('rss_mb', '-'):>12} MB {end.get('cpu_percent', '-'):>6} %"
                     f"{grown.get(f'rss.{name}', '-'):>10}")
    for stage, row in first["latency"].items():
        end = last["latency"].get(stage)
        cell = f"{end['p50_ms']}/{end['p99_ms']} ms" if end else "-"
        lines.append(f"{'latency ' + stage:<24}{str(row['p50_ms']) + '/' + str(row['p99_ms']) + ' ms':>24}{cell:>24}"
                     f"{grown.get(f'latency.{stage}', '-'):>10}")
    return "\n".join(lines)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of ``hydrosoft-stack bench soak``."""
    add_config_argument(parser)
    parser.add_argument("--minutes", type=float, default=10.0, help="length of the soak, min (default 10)")
    parser.add_argument("--window", type=float, default=60.0,
                        help="the first and last windows compared, s (default 60)")
    parser.add_argument("--idle-seconds", type=float, default=30.0,
                        help="how long the idle stack is measured before the goals, s (default 30)")
    parser.add_argument("--keep", type=Path, default=None, metavar="DIR", help="copy the logs to DIR")
    parser.add_argument("--background-load", type=float, default=0.0, metavar="CORES",
                        help="other work on the host made on purpose from the idle phase to the end, in cores (e.g. "
                        "0.3: a process spinning 30 %% of each 10 ms); measures the stack's margin in any hour "
                        "(default 0: none)")
    parser.add_argument("--json", action="store_true", help="print only the JSON document")


def run(args: argparse.Namespace) -> int:
    """Run ``hydrosoft-stack bench soak``; 0 when it was measured."""
    if args.window * 2 > 60 * args.minutes:
        print("error: --window must be at most half the soak (--minutes)", file=sys.stderr)
        return 2
    shortest_s = 2 * SAMPLE_PERIOD_S
    if args.idle_seconds < shortest_s or args.window < shortest_s:
        print(f"error: --idle-seconds and --window must be at least {shortest_s:g} s (two samples, "
              f"{SAMPLE_PERIOD_S:g} s apart, make a CPU figure)", file=sys.stderr)
        return 2
    if not (0.0 <= args.background_load <= (os.cpu_count() or 1)):
        print(f"error: --background-load must be between 0 and this host's {os.cpu_count()} cores",
              file=sys.stderr)
        return 2
    result = measure(args.config, args.minutes, args.window, args.idle_seconds, args.keep, args.background_load)
    if not args.json:
        print(format_table(result))
    print(json.dumps(result))
    return 0
