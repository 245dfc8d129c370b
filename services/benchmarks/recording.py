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
- with the recorder: its CPU use (% of one core, from ``/proc``) and the file's size and growth.

It prints one JSON document (and a table without ``--json``). Every process it starts is stopped by its pid.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import zmq

from hydrosoft.services import messages as msg
from hydrosoft.services.bus import Bus
from hydrosoft.services.client import ClientError, StackClient
from hydrosoft.services.config import StackConfig, load_config

DEFAULT_CONFIG = Path(__file__).resolve().parents[2] / "deploy" / "sim.toml"
#: Longest wait for the whole stack to report ready, s (the planner and sim_world compile on two busy cores).
STACK_READY_S = 300.0
#: Longest wait for the recorder to report READY, s.
RECORDER_READY_S = 120.0
#: After the goal starts, the planner settles for this long before the first phase, s.
SETTLE_S = 5.0
#: The launcher's shutdown bound plus a margin, s.
STOP_WAIT_S = 20.0
#: The goal: push the object this far along x (m), with a timeout beyond the run (s): it stays running.
GOAL_DX_M = 0.1
GOAL_TIMEOUT_S = 3600.0
#: How long the goal's start may be refused (no object pose yet) before the benchmark gives up, s.
GOAL_START_S = 60.0
PHASES = ("without", "with", "without_again")


def private_config(source: Path, root: Path) -> Path:
    """``source`` with its run_dir (and every path under it, such as the FT 300 links) moved to ``root/run`` and each
    arm's UR controller on a free 127.0.0.N (another stack on this host may hold the configured one). Raises
    ValueError when the file does not spell those values as quoted strings."""
    config = load_config(source)
    run_dir = root / "run"
    text = source.read_text().replace(f'"{config.run_dir}', f'"{run_dir}')
    for index, arm in enumerate(config.arms):
        text = text.replace(f'"{arm.ur_host}"', f'"{free_ur_host(index)}"')
    path = root / "stack.toml"
    path.write_text(text)
    private = load_config(path)
    if private.run_dir != str(run_dir) or any(a.ur_host == b.ur_host for a, b in zip(private.arms, config.arms)):
        raise ValueError(f"{source}: could not move run_dir and ur_host (write them as quoted strings)")
    return path


def free_ur_host(offset: int) -> str:
    """A 127.0.0.N whose RTDE port (30004) is free now."""
    for attempt in range(60):
        host = f"127.0.0.{100 + (os.getpid() + offset + attempt) % 100}"
        with socket.socket() as probe:
            try:
                probe.bind((host, 30004))
            except OSError:
                continue
        return host
    raise RuntimeError("no free 127.0.0.N for the simulated UR controller")


def cpu_time_s(pid: int) -> float:
    """User plus system CPU time of process ``pid`` so far, s (Linux ``/proc/PID/stat``)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


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


class Child:
    """A process in its own session, its output to a file; ``wait_for`` a line, ``stop`` by pid (SIGINT, then
    SIGKILL of its group)."""

    def __init__(self, command: list[str], log: Path) -> None:
        self.log = log
        self._out = log.open("wb")
        self.process = subprocess.Popen(command, stdout=self._out, stderr=subprocess.STDOUT, start_new_session=True)

    def wait_for(self, text: str, timeout_s: float) -> None:
        deadline_s = time.monotonic() + timeout_s
        while text not in self.log.read_text(errors="replace"):
            if self.process.poll() is not None or time.monotonic() > deadline_s:
                raise RuntimeError(f"no {text!r} from {self.process.args[:4]} within {timeout_s} s; see {self.log}")
            time.sleep(0.2)

    def stop(self) -> None:
        if self.process.poll() is None:
            os.killpg(self.process.pid, signal.SIGINT)
            try:
                self.process.wait(STOP_WAIT_S)
            except subprocess.TimeoutExpired:
                os.killpg(self.process.pid, signal.SIGKILL)
                self.process.wait(STOP_WAIT_S)
        self._out.close()


async def _goal(config_path: Path, task: str) -> None:
    """Set and start the goal, trying again while the planner has no object pose yet (the tag tracker's first)."""
    deadline_s = time.monotonic() + GOAL_START_S
    async with StackClient(config_path) as client:
        await client.set_goal(task, dx_m=GOAL_DX_M, timeout_s=GOAL_TIMEOUT_S)
        while True:
            try:
                await client.start()
                return
            except ClientError:
                if time.monotonic() > deadline_s:
                    raise
            await asyncio.sleep(1.0)


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
        stack = Child([sys.executable, "-m", "hydrosoft.services.launcher", str(config_path)], root / "launcher.log")
        children.append(stack)
        stack.wait_for("stack ready", STACK_READY_S)
        asyncio.run(_goal(config_path, stack_config.scene.task))
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
        result["recording_mb_per_s"] = round(recording.stat().st_size / 1e6 / seconds, 2)
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
    lines.append(f"recording: {result['recording_mb']} MB ({result['recording_mb_per_s']} MB/s), recorder CPU "
                 f"{result['recorder_cpu_percent']} % of one core")
    return "\n".join(lines)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of ``hydrosoft-stack bench recording``."""
    parser.add_argument("--config", type=Path, default=DEFAULT_CONFIG, help="a sim stack config (default "
                        "deploy/sim.toml; its run_dir and UR address are made private)")
    parser.add_argument("--seconds", type=float, default=20.0, help="length of each phase, s (default 20)")
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
