"""``hydrosoft-stack bench recording``: what recording costs the running sim stack, measured in one run.

The benchmark launches the sim stack of CONFIG (default ``deploy/sim.toml``, with a private run_dir and a free
127.0.0.N for the simulated UR controller), starts a pushing goal too far to be reached in the run (so the planner
plans throughout) and then measures three phases of ``--seconds`` each: ``without`` a recorder, ``with`` one (the
recorder service writing an MCAP file, started mid-run as ``launch --record`` starts it) and ``without_again``
(to tell the recorder's cost from the episode's drift). Per phase:

- the planner's rate: plans per second received, and their mean ``solve_ms``;
- the bus latency per topic: a probe subscriber in this process reads every message of the arm commander, the F/T
  reader, the bubble camera and the planner, and takes its age on arrival (``time.monotonic_ns()`` minus the
  publisher's ``stamp_ns``: one host, one clock); p50 and p99 in ms, and the rate received;
- with the recorder: its CPU use (% of one core, from ``/proc``) and the file's size and growth (MB per second of
  the span its messages cover, from the file's statistics record).

It prints one JSON document (and a table without ``--json``). Every process it starts is stopped by its pid.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import shutil
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import zmq
from mcap.reader import make_reader

from hydrosoft.services.bus import messages as msg
from hydrosoft.services.benchmarks.launched_stack import (
    Child,
    add_config_argument,
    cpu_time_s,
    private_config,
    stack_ready_s,
    start_goal,
)
from hydrosoft.services.bus.sockets import Bus
from hydrosoft.services.client import StackClient
from hydrosoft.services.bus.config import StackConfig, load_config

#: Longest wait for the recorder to report READY, s.
RECORDER_READY_S = 120.0
#: After the goal starts, the planner settles for this long before the first phase, s.
SETTLE_S = 5.0
#: The goal: push the object this far along x (m), with a timeout beyond the run (s): it stays running.
GOAL_DX_M = 0.1
GOAL_TIMEOUT_S = 3600.0
PHASES = ("without", "with", "without_again")


def latency_summary(ages_ns: dict[str, list[int]], seconds: float) -> dict[str, dict[str, float]]:
    """Per topic: p50 and p99 age (ms) and the messages per second received over ``seconds``."""
    summary = {}
    for topic, ages in sorted(ages_ns.items()):
        ms = np.asarray(ages, dtype=np.float64) * 1e-6
        summary[topic] = {"p50_ms": round(float(np.percentile(ms, 50)), 3),
                          "p99_ms": round(float(np.percentile(ms, 99)), 3), "hz": round(len(ages) / seconds, 2)}
    return summary


async def probe(config: StackConfig, seconds: float) -> dict[str, object]:
    """Read every message of the arm commanders, F/T readers, bubble cameras and the planner for ``seconds``: the
    plan rate, mean solve time and each topic's latency."""
    names = ["planner"] + [f"{m}-{a.name}" for a in config.arms for m in ("arm_commander", "ft_reader",
                                                                          "bubble_camera")]
    ages: dict[str, list[int]] = defaultdict(list)
    solve_ms: list[float] = []
    with Bus() as bus:
        sock = bus.socket(zmq.SUB, [config.endpoint(n) for n in names], bind=False,
                          options=[(zmq.RCVHWM, 10000), (zmq.MAXMSGSIZE, msg.MAX_FRAME_BYTES), (zmq.SUBSCRIBE, b"")])
        await asyncio.sleep(0.5)  # connect, and drop what queued meanwhile
        while await sock.poll(0):
            await sock.recv_multipart(copy=False)
        end_s = time.monotonic() + seconds
        while (left_s := end_s - time.monotonic()) > 0:
            if not await sock.poll(max(1, int(left_s * 1000))):
                continue
            frames = await sock.recv_multipart(copy=False)
            received_ns = time.monotonic_ns()
            topic, message = msg.decode(frames)
            ages[topic].append(received_ns - message.stamp_ns)
            if isinstance(message, msg.Plan):
                solve_ms.append(message.solve_ms)
    plans = sum(len(v) for k, v in ages.items() if k.startswith("plan/"))
    return {"plan_hz": round(plans / seconds, 3), "mean_solve_ms": round(float(np.mean(solve_ms)), 1) if solve_ms
            else None, "latency": latency_summary(ages, seconds)}


def recorded_span_s(path: Path) -> float:
    """The time from a closed MCAP file's first message to its last (log times, from its statistics record), s."""
    with open(path, "rb") as stream:
        statistics = make_reader(stream).get_summary().statistics
    return (statistics.message_end_time - statistics.message_start_time) * 1e-9


async def _status(config_path: Path) -> msg.StatusReply:
    async with StackClient(config_path) as client:
        return await client.status()


def measure(config: Path, seconds: float, keep: Path | None = None) -> dict[str, object]:
    """Launch the stack of ``config``, push, and measure the three phases (module docstring). ``keep``: a folder to
    keep the logs and the recording in (default: a temporary one, removed)."""
    root = Path(tempfile.mkdtemp(prefix="hs-rec-", dir="/tmp"))
    children: list[Child] = []
    try:
        config_path = private_config(config, root)
        stack_config = load_config(config_path)
        stack = Child([sys.executable, "-m", "hydrosoft.services.commands.launch", str(config_path)],
                      root / "launcher.log")
        children.append(stack)
        stack.wait_for("stack ready", stack_ready_s(stack_config))

        async def goal() -> None:
            (await start_goal(config_path, stack_config.scene.task, dx_m=GOAL_DX_M, timeout_s=GOAL_TIMEOUT_S)).close()

        asyncio.run(goal())
        time.sleep(SETTLE_S)
        result: dict[str, object] = {"seconds_per_phase": seconds}
        result["without"] = asyncio.run(probe(stack_config, seconds))
        recording = root / "bench.mcap"
        recorder = Child([sys.executable, "-m", "hydrosoft.services.recorder", str(config_path), "--record",
                          str(recording)], root / "recorder.log")
        children.append(recorder)
        recorder.wait_for("READY recorder", RECORDER_READY_S)
        cpu_before_s, tic_s = cpu_time_s(recorder.process.pid), time.monotonic()
        result["with"] = asyncio.run(probe(stack_config, seconds))
        result["recorder_cpu_percent"] = round(
            100 * (cpu_time_s(recorder.process.pid) - cpu_before_s) / (time.monotonic() - tic_s), 1)
        recorder.stop()
        result["recording_mb"] = round(recording.stat().st_size / 1e6, 1)
        result["recording_s"] = round(recorded_span_s(recording), 1)
        result["recording_mb_per_s"] = round(recording.stat().st_size / 1e6 / result["recording_s"], 3)
        result["without_again"] = asyncio.run(probe(stack_config, seconds))
        status = asyncio.run(_status(config_path))
        result["episode"] = {"outcome": status.outcome, "solves": status.solves,
                             "mean_solve_ms": round(status.mean_solve_ms, 1)}
        return result
    finally:
        for child in reversed(children):
            child.stop()
        if keep is not None:
            keep.mkdir(parents=True, exist_ok=True)
            for path in [*root.glob("*.log"), *root.glob("*.mcap"), *root.glob("*.toml")]:
                shutil.copy2(path, keep)
        shutil.rmtree(root, ignore_errors=True)


def format_table(result: dict[str, object]) -> str:
    """The phases side by side: plan rate, solve time and per-topic p50/p99 latency."""
    topics = sorted({t for phase in PHASES for t in result[phase]["latency"]})
    lines = [f"{'':<24}" + "".join(f"{phase:>24}" for phase in PHASES)]
    lines.append(f"{'plans/s':<24}" + "".join(f"{result[p]['plan_hz']:>24}" for p in PHASES))
    lines.append(f"{'mean solve ms':<24}" + "".join(f"{str(result[p]['mean_solve_ms']):>24}" for p in PHASES))
    for topic in topics:
        cells = []
        for phase in PHASES:
            row = result[phase]["latency"].get(topic)
            cells.append(f"{row['p50_ms']:.2f}/{row['p99_ms']:.2f} ms {row['hz']:.0f} Hz" if row else "-")
        lines.append(f"{topic:<24}" + "".join(f"{cell:>24}" for cell in cells))
    lines.append(f"recording: {result['recording_mb']} MB over {result.get('recording_s', '?')} s "
                 f"({result['recording_mb_per_s']} MB/s), recorder CPU "
                 f"{result['recorder_cpu_percent']} % of one core")
    return "\n".join(lines)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of ``hydrosoft-stack bench recording``."""
    add_config_argument(parser)
    parser.add_argument("--seconds", type=float, default=20.0,
                        help="length of each phase, s (default 20; the run takes the stack's start, 1-3 min on 2 "
                             "cores and up to 4.2 min under load, plus about 3 x SECONDS + 20 s)")
    parser.add_argument("--keep", type=Path, default=None, metavar="DIR",
                        help="copy the logs and the recording to DIR")
    parser.add_argument("--json", action="store_true", help="print only the JSON document")


def run(args: argparse.Namespace) -> int:
    """Run ``hydrosoft-stack bench recording``; 0 when every phase was measured."""
    result = measure(args.config, args.seconds, args.keep)
    if not args.json:
        print(format_table(result))
    print(json.dumps(result))
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m hydrosoft.services.benchmarks.recording",
                                     description=__doc__.split("\n")[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
