"""The planner's start-up: which precompiled functions one process builds for its solver worker processes to load
(``services/planner.py``: ``share_sizes``, ``build_precompiled``), without compiling anything; and a planner started
before its arm commander (``await_arm_commanders``), as a process with the quick preset."""

from __future__ import annotations

import asyncio
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from hydrosoft import compilation
from hydrosoft.control import worker_processes
from hydrosoft.services import planner
from hydrosoft.services.bus import messages as msg
from hydrosoft.services.bus.config import load_config
from hydrosoft.services.bus.messages import BusError
from hydrosoft.services.bus.runtime import AWAIT_ARMS_ENV
from hydrosoft.services.bus.sockets import Bus, LatestSubscriber, Publisher, RequestClient, Stale
from service_process import ServiceProcess
from stack_process import quick_planner

SIM_TOML = Path(__file__).parents[2] / "deploy" / "sim.toml"


@pytest.mark.parametrize("samples, workers, sizes", [
    (64, 2, [32]),  # the paper planner: one share size, so one batch shape per function
    (64, 3, [21, 22]),  # 22, 21, 21 as tensor_split cuts them
    (16, 1, [16]),
    (2, 3, [1]),  # an empty share runs nothing
])
def test_the_share_sizes_are_the_batches_the_workers_solve(samples, workers, sizes):
    assert planner.share_sizes(samples, workers) == sizes


@pytest.mark.parametrize("samples, workers, chunks, sizes", [
    (64, 2, 4, [16]),  # work sharing: four chunks of 16, one batch shape per function
    (64, 2, 8, [8]),
    (64, 2, 5, [12, 13]),  # 13, 13, 13, 13, 12
    (64, 1, 4, [64]),  # one worker never cuts its batch
    (64, 2, 0, [32]),  # 0: one chunk per worker
])
def test_the_share_sizes_are_the_chunks_when_the_samples_are_cut_into_chunks(samples, workers, chunks, sizes):
    assert planner.share_sizes(samples, workers, chunks) == sizes


def test_one_process_builds_one_core_per_share_size_as_a_lone_worker_then_stops_building(tmp_path, monkeypatch):
    """``build_precompiled`` makes, per share size, a core of one worker without processes whose solve batch is
    that share (what each worker process runs), with building on while its compiled functions are made, and solves
    once on it; functions made after it load or trace again (nothing else builds)."""
    config = load_config(SIM_TOML)  # the paper planner: B = 64 over 2 worker processes
    made = []
    monkeypatch.setattr(planner.PlannerCore, "build", classmethod(
        lambda cls, config: made.append((config.planner, compilation.precompiling())) or object()))
    solved = []
    monkeypatch.setattr(planner, "compile_step", solved.append)
    compilation.use_precompiled(tmp_path)
    try:
        planner.build_precompiled(config, tmp_path / "planner")
        after = compilation.precompiling()
    finally:
        compilation.use_precompiled(None)
    assert len(made) == len(solved) == 1
    (alone, setting), = made
    (chunk,) = planner.share_sizes(config.planner.samples, config.planner.workers, config.planner.chunks)
    assert (alone.samples, alone.workers, alone.chunks, alone.worker_processes, alone.elites) == (chunk, 1, 0, False, 8)
    assert (alone.spacing, alone.horizon, alone.dtype) == (config.planner.spacing, config.planner.horizon, "float32")
    assert setting == compilation.Precompiling(tmp_path / "planner", build=True)
    assert after == compilation.Precompiling(tmp_path, build=False)


def test_the_start_up_solves_as_often_as_a_worker_takes_to_settle_so_no_goal_pays_for_it(tmp_path, monkeypatch):
    """``compile_step`` solves one solver ``WARM_UP_SOLVES`` times (warm-started after the first, as a goal's solves),
    then tells each solver worker process to settle its garbage collector (``WorkerProcesses.settle``: its first,
    costly settle happens before the planner is ready), and only then settles the planner's own collector. With
    one solve, the first goal's second solve paid for the workers' settle (211 against 31-41 ms); with the samples
    in chunks, a worker's own count of improves no longer followed the solves."""
    (tmp_path / "sim.toml").write_text(quick_planner(SIM_TOML.read_text()))
    core = planner.PlannerCore.build(load_config(tmp_path / "sim.toml"))  # eager, no worker processes: seconds
    events = []
    make_solver = core.solver

    class Workers:
        """The worker processes as ``compile_step`` sees them once its solver is made."""

        def settle(self) -> list[int]:
            events.append("settle workers")
            return [0, 0]

        def close(self) -> None:
            pass

    def counting_solver(*args):
        solver = make_solver(*args)
        events.append("solver")
        solve = solver.solve
        monkeypatch.setattr(solver, "solve", lambda x0: events.append("solve") or solve(x0))
        monkeypatch.setattr(core, "processes", Workers())
        return solver

    monkeypatch.setattr(core, "solver", counting_solver)
    monkeypatch.setattr(worker_processes, "settle_garbage_collector", lambda: events.append("settle"))
    try:
        planner.compile_step(core)
    finally:
        core.close()
    assert planner.WARM_UP_SOLVES == 2
    assert events == ["solver", *["solve"] * planner.WARM_UP_SOLVES, "settle workers", "settle"]


def test_the_functions_without_gradients_build_from_a_solve_without_gradient_steps(tmp_path, monkeypatch):
    """``build_precompiled_rollouts`` (a process of its own beside ``compile``'s planner build) makes the same lone
    worker's core with no gradient steps: its solve runs only the final rollout, without gradients, into the same
    directory, whose functions the full build then loads."""
    config = load_config(SIM_TOML)
    made = []
    monkeypatch.setattr(planner.PlannerCore, "build", classmethod(
        lambda cls, config: made.append((config.planner, compilation.precompiling())) or object()))
    monkeypatch.setattr(planner, "compile_step", lambda core: None)
    planner.build_precompiled_rollouts(config, tmp_path / "planner")
    (alone, setting), = made
    (chunk,) = planner.share_sizes(config.planner.samples, config.planner.workers, config.planner.chunks)
    assert (alone.grad_steps, alone.samples, alone.workers, alone.horizon) == (0, chunk, 1, config.planner.horizon)
    assert config.planner.grad_steps == 2 and setting == compilation.Precompiling(tmp_path / "planner", build=True)


def test_a_planner_started_before_its_arm_commander_takes_no_goal_until_the_commander_publishes(tmp_path, monkeypatch):
    """The launcher starts the planner first, naming the arms it waits for (``$HYDROSOFT_AWAIT_ARMS``): the planner
    builds its solver, then, as long as no state of the bubble arm's commander has arrived, it does not report READY,
    answers no client request (its client API is not served) and says in its status what it waits for; once the
    commander's state arrives it reports READY and answers."""
    run_dir = tmp_path / "run"
    path = tmp_path / "sim.toml"
    path.write_text(quick_planner(SIM_TOML.read_text()).replace('"/tmp/hydrosoft-sim"', f'"{run_dir}"'))
    config = load_config(path)
    monkeypatch.setenv(AWAIT_ARMS_ENV, "bubble")
    process = ServiceProcess("planner", "planner", path, tmp_path / "planner.log")

    async def scenario() -> dict:
        seen = {}
        with Bus() as bus:
            status = LatestSubscriber(bus, config.endpoint("planner", "status"), topics=["status/planner"])
            seen["waiting"] = await wait_for_status(status, lambda s: "arm commanders of bubble" in s.note, 60.0)
            loop = asyncio.get_running_loop()
            seen["ready before"] = await loop.run_in_executor(None, ready_within, process, 1.5)
            seen["reply before"] = await request_status(config, 1.0)
            arm = Publisher(bus, config.endpoint("arm_commander-bubble"), source="arm_commander-bubble")
            ready = loop.run_in_executor(None, ready_within, process, 30.0)
            while not ready.done():
                await arm.send(commander_state(), "arm_state/bubble")
                await asyncio.sleep(0.04)
            seen["ready after"] = ready.result()
            seen["reply after"] = await request_status(config, 5.0)
        return seen

    try:
        seen = asyncio.run(asyncio.wait_for(scenario(), 120.0))
    finally:
        rc = process.stop()
    assert rc == 0, process.log()
    assert seen["waiting"] is not None, process.log()
    assert not seen["ready before"] and seen["reply before"] is None, seen
    assert seen["ready after"], process.log()
    assert seen["reply after"] is not None and seen["reply after"].status.note == "", seen


def commander_state() -> msg.ArmState:
    """An arm commander's state at rest."""
    return msg.ArmState(arm="bubble", tcp_pose=np.array([0.0, 0.0, 0.1, 1.0, 0.0, 0.0, 0.0]), tcp_speed=np.zeros(6),
                        running=True, protective_stop=False, emergency_stop=False, servo_active=False)


def ready_within(process: ServiceProcess, timeout_s: float) -> bool:
    """Whether ``process`` printed its READY line within ``timeout_s`` s."""
    try:
        process.wait_ready(timeout_s)
    except AssertionError:
        return False
    return True


async def wait_for_status(status: LatestSubscriber, holds, timeout_s: float) -> msg.ServiceStatus | None:
    """The first status on ``status`` for which ``holds(status)`` within ``timeout_s`` s, or None."""
    deadline_s = time.monotonic() + timeout_s
    while time.monotonic() < deadline_s:
        await status.wait(0.5)
        try:
            received = status.latest("status/planner", math.inf, msg.ServiceStatus).value
        except Stale:
            continue
        if holds(received):
            return received
    return None


async def request_status(config, timeout_s: float) -> msg.StatusReply | None:
    """The planner's answer to GetStatus on its client API within ``timeout_s`` s, or None."""
    with Bus() as bus:
        client = RequestClient(bus, config.endpoint("planner", "cmd"), source="test")
        try:
            return await client.request(msg.GetStatus(), timeout_s)
        except (TimeoutError, BusError):
            return None


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="per-thread niceness in /proc is Linux's")
def test_renice_lowers_the_priority_of_every_thread_of_the_worker_processes():
    """Once ready, the planner renices its solver worker processes, started at its own niceness, to ``planner.nice``:
    every thread of each process (on Linux a thread's niceness is its own), not just the main one."""
    code = "import threading, time; threading.Thread(target=time.sleep, args=(60,)).start(); print(flush=True); " \
           "time.sleep(60)"
    processes = [subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE) for _ in range(2)]
    try:
        for process in processes:
            process.stdout.readline()  # its second thread runs
        own = os.getpriority(os.PRIO_PROCESS, 0)
        planner.renice([process.pid for process in processes] + [2**22 + 1], 3)  # a pid that is gone is left out
        for process in processes:
            threads = [int(tid) for tid in os.listdir(f"/proc/{process.pid}/task")]
            assert len(threads) == 2
            assert [os.getpriority(os.PRIO_PROCESS, tid) for tid in threads] == [own + 3, own + 3]
    finally:
        for process in processes:
            process.kill()
            process.wait()


def _scheduled_in_an_autogroup() -> bool:
    """Whether the kernel schedules this process's session as one group: ``/proc/self/autogroup`` names the group
    only then. It is missing where the kernel has no autogroup, and empty for a process in a CPU cgroup of its own (a
    container's, or a systemd unit's with CPU accounting), where a niceness counts across the whole cgroup."""
    try:
        return bool(open("/proc/self/autogroup").read().strip())
    except OSError:
        return False


@pytest.mark.skipif(not _scheduled_in_an_autogroup(), reason="the kernel schedules no session of ours as a group")
def test_renice_sets_the_scheduling_group_of_a_process_that_leads_its_session_and_no_other():
    """Where the kernel schedules each session as one group, a process's niceness counts only within its group: a
    worker process that leads its own session gets its group's niceness set too, so that against the other programs
    it runs at ``planner.nice``. A process in the planner's own session leaves the planner's group alone."""
    code = "import time; print(flush=True); time.sleep(60)"
    alone = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, start_new_session=True)
    ours = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE)
    try:
        for process in (alone, ours):
            process.stdout.readline()
        group_nice = open("/proc/self/autogroup").read().split()[-1]
        own = os.getpriority(os.PRIO_PROCESS, 0)
        assert planner.renice([alone.pid, ours.pid], 4) == []
        assert open(f"/proc/{alone.pid}/autogroup").read().split()[-1] == str(own + 4)
        assert open(f"/proc/{ours.pid}/autogroup").read().split()[-1] == group_nice
        assert os.getpriority(os.PRIO_PROCESS, ours.pid) == own + 4
    finally:
        for process in (alone, ours):
            process.kill()
            process.wait()
