"""CEM-GD's shares in worker processes: the same plans as threads, new goals, and failures that raise instead of
hanging (real processes, each stopped by the test)."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import pytest
import torch

from hydrosoft import compilation
from hydrosoft.control import CemGd, CemGdConfig
from hydrosoft.control.worker_processes import WorkerError, WorkerProcesses

HERE = Path(__file__).parent
sys.path.insert(0, str(HERE))
import integrator_problem as problem  # noqa: E402 - the folder the worker processes import it from, too

LOW = torch.full((1, 3), -0.1, dtype=torch.float64)
GOAL = (0.5, -0.3, 0.2)


@pytest.fixture(autouse=True)
def _importable_problem(monkeypatch):
    """The worker processes find ``integrator_problem`` on their path."""
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [str(HERE), os.environ.get("PYTHONPATH")])))


def start(config: CemGdConfig, timeout_s: float = 60.0) -> WorkerProcesses:
    return WorkerProcesses(problem.build, config.workers, LOW, -LOW, config, torch.float64, timeout_s=timeout_s)


def solver(config: CemGdConfig, goal=GOAL, processes: WorkerProcesses | None = None) -> CemGd:
    return CemGd(*problem.build(goal), LOW, -LOW, config, dtype=torch.float64, processes=processes)


def x0(pos=(0.0, 0.0, 0.0)) -> problem.State:
    return problem.State(torch.tensor([pos], dtype=torch.float64), torch.zeros(1, dtype=torch.int64))


def assert_stopped(pids: list[int]) -> None:
    for pid in pids:
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)


def test_processes_plan_what_threads_plan_and_follow_a_new_goal():
    """Three workers over 64 samples (22, 21, 21): three receding-horizon solves give the plans, costs, warm starts
    and predicted states of the threads' solver; after ``set_problem`` with another goal, those of a fresh solver
    for it. The processes are others than this one, and ``close`` stops them."""
    config = CemGdConfig(seed=3, workers=3)
    workers = start(config)
    pids = workers.pids
    try:
        assert len(set(pids)) == 3 and os.getpid() not in pids
        for goal, start_pos in ((GOAL, (0.0, 0.0, 0.0)), ((-0.2, 0.1, 0.0), (0.1, 0.2, -0.1))):
            workers.set_problem(goal)
            threads, processes = solver(config, goal), solver(config, goal, workers)
            state = x0(start_pos)
            for _ in range(3):
                expected, result = threads.solve(state), processes.solve(state)
                torch.testing.assert_close(result.plan, expected.plan, rtol=0, atol=1e-12)
                assert result.cost == pytest.approx(expected.cost, rel=1e-12)
                torch.testing.assert_close(processes.mean, threads.mean, rtol=0, atol=1e-12)
                for got, want in zip(result.states, expected.states, strict=True):
                    torch.testing.assert_close(got.pos, want.pos, rtol=0, atol=1e-12)
                    assert torch.equal(got.steps, want.steps)
                state = result.states[0]
    finally:
        workers.close()
    assert_stopped(pids)


def test_the_plan_does_not_depend_on_which_worker_ran_which_chunk(tmp_path):
    """Work sharing: 64 samples in 8 chunks of 8 over two workers, each chunk to whichever worker is free. With one
    worker slowed (its step sleeps), the other takes most chunks, so the assignment changes; the plans, costs, warm
    starts and predicted states stay the same, bit for bit, over three receding-horizon solves."""
    config = CemGdConfig(seed=3, workers=2, chunks=8)
    workers = WorkerProcesses(problem.build_one_slow, 2, LOW, -LOW, config, torch.float64, timeout_s=60.0)
    pids = workers.pids

    def solves(marker: Path | None) -> tuple[list, list, list[list[int]]]:
        workers.set_problem((GOAL, None if marker is None else str(marker)))
        cem = solver(config, processes=workers)
        results, means, assignments, state = [], [], [], x0()
        for _ in range(3):
            result = cem.solve(state)
            results.append(result)
            means.append(cem.mean.clone())
            assignments.append(workers.assignment)
            state = result.states[0]
        return results, means, assignments

    try:
        even, even_means, even_assignments = solves(None)
        skewed, skewed_means, skewed_assignments = solves(tmp_path / "slow")
    finally:
        workers.close()
    assert_stopped(pids)
    assert (tmp_path / "slow").exists()
    assert all(sorted(set(a)) == [0, 1] for a in even_assignments)  # both workers ran chunks of each solve
    assert all(max(Counter(a).values()) >= 6 for a in skewed_assignments)  # the fast one took most of them
    assert skewed_assignments != even_assignments
    for got, want, got_mean, want_mean in zip(skewed, even, skewed_means, even_means, strict=True):
        assert torch.equal(got.plan, want.plan) and torch.equal(got.action, want.action)
        assert got.cost == want.cost
        assert torch.equal(got_mean, want_mean)
        for got_state, want_state in zip(got.states, want.states, strict=True):
            assert torch.equal(got_state.pos, want_state.pos) and torch.equal(got_state.steps, want_state.steps)


def test_chunks_plan_what_the_threads_plan_on_the_same_chunks():
    """Five chunks over two processes (13, 13, 13, 13, 12 samples) give the plans of two threads that share the same
    chunks, and a chunk-per-worker solver's to float rounding."""
    config = CemGdConfig(seed=1, workers=2, chunks=5)
    workers = start(config)
    pids = workers.pids
    try:
        workers.set_problem(GOAL)
        processes, threads = solver(config, processes=workers), solver(config)
        halves = solver(CemGdConfig(seed=1, workers=2))
        state = x0()
        for _ in range(3):
            result, expected, by_halves = processes.solve(state), threads.solve(state), halves.solve(state)
            assert len(workers.assignment) == 5
            torch.testing.assert_close(result.plan, expected.plan, rtol=0, atol=1e-12)
            torch.testing.assert_close(result.plan, by_halves.plan, rtol=0, atol=1e-12)
            state = result.states[0]
    finally:
        workers.close()
    assert_stopped(pids)


def test_a_worker_settles_its_garbage_collector_when_told_and_not_before():
    """Improves alone never settle a worker's collector, however many chunks it ran (a count of them no longer
    follows the solves): the first ``settle`` freezes the worker's start-up objects (torch's imports among them),
    a second one only what came after."""
    config = CemGdConfig(seed=0, workers=2, chunks=4)
    workers = start(config)
    pids = workers.pids
    try:
        workers.set_problem(GOAL)
        cem = solver(config, processes=workers)
        for _ in range(3):
            cem.solve(x0())
        first = workers.settle()
        cem.solve(x0())
        second = workers.settle()
    finally:
        workers.close()
    assert_stopped(pids)
    assert len(first) == len(second) == 2
    assert all(count > 50_000 for count in first), first
    assert all(count < 5_000 for count in second), second


def test_a_workers_step_that_falls_back_to_eager_is_reported_to_the_parent_once():
    """A worker's compiled step fails to compile and runs eager there: the parent's ``fallbacks`` names the worker,
    the part and the reason, and ``on_fallback`` hears it once, not at every solve."""
    config = CemGdConfig(seed=0, workers=2)
    workers = WorkerProcesses(problem.build_without_compiler, 2, LOW, -LOW, config, torch.float64, timeout_s=60.0)
    pids = workers.pids
    heard = []
    workers.on_fallback = lambda index, why: heard.append((index, why))
    try:
        workers.set_problem(GOAL)
        cem = solver(config, processes=workers)
        assert workers.fallbacks == {}
        for _ in range(2):
            cem.solve(x0())
    finally:
        workers.close()
    assert_stopped(pids)
    assert sorted(workers.fallbacks) == [0, 1]
    assert all(why.startswith("step: ") and "no C++ compiler here" in why for why in workers.fallbacks.values())
    assert sorted(heard) == sorted(workers.fallbacks.items())


def test_worker_processes_load_the_step_one_process_precompiled_and_plan_as_a_fresh_compile(tmp_path, monkeypatch):
    """The planner's start-up in small: this process builds the step's precompiled functions once, on one share's
    batch (32 of 64 samples; horizon 1: a gradient rollout and a no-grad one, 2 functions); two worker processes then
    load them (none builds or traces) and plan what a freshly compiled solver with threads plans: the same plans, so
    the same values and gradients. The workers report their counts to the parent (``precompiled``)."""
    monkeypatch.setattr(compilation, "PRECOMPILED", Counter())
    config = CemGdConfig(seed=3, workers=2, horizon=1, grad_steps=1)
    share = CemGdConfig(seed=3, workers=1, horizon=1, grad_steps=1, samples=config.samples // 2)
    try:
        with compilation.building_precompiled(tmp_path):
            builder = CemGd(*problem.build_compiled(GOAL), LOW, -LOW, share, dtype=torch.float64)
        builder.solve(x0())
        assert compilation.PRECOMPILED == {"built": 2} and len(list(tmp_path.glob("*.pt2"))) == 2
        compilation.use_precompiled(tmp_path)  # as the planner sets it before it starts its worker processes
        workers = WorkerProcesses(problem.build_compiled, 2, LOW, -LOW, config, torch.float64, timeout_s=120.0)
    finally:
        compilation.use_precompiled(None)
    pids = workers.pids
    fresh = CemGd(*problem.build_compiled(GOAL), LOW, -LOW, config, dtype=torch.float64)  # threads, traced here
    try:
        workers.set_problem(GOAL)
        loaded = solver(config, processes=workers)
        state = x0()
        for _ in range(2):
            expected, result = fresh.solve(state), loaded.solve(state)
            torch.testing.assert_close(result.plan, expected.plan, rtol=0, atol=1e-12)
            assert result.cost == pytest.approx(expected.cost, rel=1e-12)
            state = result.states[0]
    finally:
        workers.close()
    assert_stopped(pids)
    assert workers.precompiled() == {"loaded": 4}  # 2 functions in each of the 2 workers; none built nor traced
    assert workers.fallbacks == {} and compilation.PRECOMPILED["built"] == 2


def test_a_broken_problem_raises_the_workers_error_and_stops_them():
    config = CemGdConfig(seed=0, workers=2)
    workers = start(config)
    pids = workers.pids
    with pytest.raises(WorkerError, match="improve before any problem"):
        workers.improve(x0(), list(torch.zeros(64, 10, 1, 3, dtype=torch.float64).tensor_split(2)))
    assert_stopped(pids)
    workers = start(config)
    pids = workers.pids
    with pytest.raises(WorkerError, match="goal .* is not finite"):
        workers.set_problem((float("nan"), 0.0, 0.0))
    assert_stopped(pids)


def test_a_killed_worker_raises_instead_of_hanging():
    config = CemGdConfig(seed=0, workers=2)
    workers = start(config, timeout_s=30.0)
    pids = workers.pids
    workers.set_problem(GOAL)
    os.kill(pids[1], signal.SIGKILL)
    tic = time.monotonic()
    with pytest.raises(WorkerError, match="died"):
        solver(config, processes=workers).solve(x0())
    assert time.monotonic() - tic < 20.0
    assert_stopped(pids)


PARENT = """
import sys, torch
sys.path.insert(0, {here!r})
import integrator_problem as problem
from hydrosoft.control import CemGdConfig
from hydrosoft.control.worker_processes import WorkerProcesses
low = torch.full((1, 3), -0.1, dtype=torch.float64)
workers = WorkerProcesses(problem.build, 2, low, -low, CemGdConfig(workers=2), torch.float64)
print(*workers.pids, flush=True)
sys.stdin.read()
"""


def test_workers_exit_when_their_parent_is_killed():
    """A planner killed outright (no ``close``) leaves no worker behind: each exits when its socket closes."""
    parent = subprocess.Popen([sys.executable, "-c", PARENT.format(here=str(HERE))], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True)
    try:
        pids = [int(pid) for pid in parent.stdout.readline().split()]
        assert len(pids) == 2
    finally:
        parent.kill()
        parent.wait(10)
    deadline = time.monotonic() + 20.0
    alive = pids
    while alive and time.monotonic() < deadline:
        alive = [pid for pid in alive if _alive(pid)]
        time.sleep(0.1)
    for pid in alive:  # stop what the check found, then fail
        os.kill(pid, signal.SIGKILL)
    assert alive == []


def _alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie reparented to init counts as gone)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def test_a_build_defined_in_the_main_module_is_refused_up_front():
    def build(goal):
        return problem.build(goal)

    build.__module__ = "__main__"
    with pytest.raises(ValueError, match="importable"):
        WorkerProcesses(build, 2, LOW, -LOW, CemGdConfig(workers=2), torch.float64)


def test_a_worker_process_starts_without_a_warning(capfd):
    """A worker process imports this module and serves: started as ``python -m`` of a module its package had
    imported already, each printed runpy's RuntimeWarning to the parent's standard error."""
    workers = start(CemGdConfig(seed=0, workers=2))
    pids = workers.pids
    try:
        workers.set_problem(GOAL)
    finally:
        workers.close()
    assert_stopped(pids)
    err = capfd.readouterr().err
    assert "Warning" not in err, err


def test_each_worker_process_leads_a_session_of_its_own_so_the_scheduler_weighs_it_as_a_program():
    """Where the kernel schedules each session as one group (autogroup), two workers in their parent's session shared
    one program's share of the cores, and their niceness counted only against their parent's threads."""
    workers = start(CemGdConfig(seed=0, workers=2))
    pids = workers.pids
    try:
        assert [os.getsid(pid) for pid in pids] == pids
        assert os.getsid(0) not in pids
    finally:
        workers.close()
    assert_stopped(pids)
