"""A sim stack launched by a benchmark: a private copy of its config, the launcher as a child process stopped by
its pid, goals started as soon as the planner can start them, and the CPU time and memory of its processes."""

from __future__ import annotations

import argparse
import asyncio
import os
import signal
import socket
import subprocess
import time
from pathlib import Path

from hydrosoft.services.client import ClientError, StackClient
from hydrosoft.services.commands.launch import die_with_parent
from hydrosoft.services.bus.config import load_config

DEFAULT_CONFIG = Path(__file__).resolve().parents[2] / "deploy" / "sim.toml"
#: Longest wait for the whole stack to report ready, s (the planner and sim_world compile on two busy cores), unless
#: the config's own readiness timeouts add up to more (``stack_ready_s``).
STACK_READY_S = 300.0
#: The launcher's shutdown bound plus a margin, s.
STOP_WAIT_S = 20.0
#: How long a goal's start may be refused (no object pose yet) before the benchmark gives up, s.
GOAL_START_S = 60.0


def stack_ready_s(config) -> float:
    """How long to wait for the stack of ``config`` (a ``StackConfig``) to report ready, s: ``STACK_READY_S``, or
    the sum of its services' ``ready_timeout_s`` when that is longer (the launcher starts them one after the other
    and gives up only past one of them)."""
    return max(STACK_READY_S, sum(config.service(name).ready_timeout_s for name in config.service_names()))


def add_config_argument(parser: argparse.ArgumentParser) -> None:
    """``--config``: the sim stack config a benchmark launches (made private by ``private_config``)."""
    parser.add_argument("--config", type=Path, default=DEFAULT_CONFIG, help="a sim stack config (default "
                        "deploy/sim.toml; its run_dir and UR address are made private)")


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


def _stat_cpu_s(stat: Path) -> float:
    """User plus system CPU time (s) in a Linux ``stat`` file of a process or a thread."""
    fields = stat.read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def cpu_time_s(pid: int) -> float:
    """User plus system CPU time of process ``pid`` so far, s (Linux ``/proc/PID/stat``)."""
    return _stat_cpu_s(Path(f"/proc/{pid}/stat"))


def thread_cpu_times_s(pid: int) -> dict[int, tuple[str, float]]:
    """Per thread of process ``pid``: its id -> (its name, user plus system CPU time so far, s) (Linux
    ``/proc/PID/task``). Threads that end while they are read are left out."""
    threads = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            threads[int(task.name)] = ((task / "comm").read_text().strip(), _stat_cpu_s(task / "stat"))
        except OSError:
            continue
    return threads


def resident_mb(pid: int) -> float:
    """Resident memory of process ``pid`` now, MB (Linux ``/proc/PID/status``, ``VmRSS``)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise ValueError(f"/proc/{pid}/status has no VmRSS line")


class Child:
    """A process in its own session, its output to a file; ``wait_for`` a line, ``stop`` by pid (SIGINT, then
    SIGKILL of its group). It gets SIGTERM when this process dies (``die_with_parent``): a benchmark killed by a
    signal that skips its ``finally`` leaves no stack running."""

    def __init__(self, command: list[str], log: Path) -> None:
        self.log = log
        self._out = log.open("wb")
        self.process = subprocess.Popen(command, stdout=self._out, stderr=subprocess.STDOUT, start_new_session=True,
                                        preexec_fn=die_with_parent(os.getpid()))

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


async def start_goal(config_path: Path, task: str, **goal) -> StackClient:
    """Set and start a goal (``StackClient.set_goal``'s keywords), trying again while the planner has no object
    pose yet (the tag tracker's first). Returns the client that started it (close it when done)."""
    deadline_s = time.monotonic() + GOAL_START_S
    client = StackClient(config_path)
    await client.set_goal(task, **goal)
    while True:
        try:
            await client.start()
            return client
        except ClientError:
            if time.monotonic() > deadline_s:
                client.close()
                raise
        await asyncio.sleep(1.0)
