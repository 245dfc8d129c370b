"""The planner's start-up: which precompiled functions one process builds for its solver worker processes to load
(``services/planner.py``: ``share_sizes``, ``build_precompiled``), without compiling anything."""

from __future__ import annotations

from pathlib import Path

import pytest

from hydrosoft import compilation
from hydrosoft.services import planner
from hydrosoft.services.bus.config import load_config

SIM_TOML = Path(__file__).parents[2] / "deploy" / "sim.toml"


@pytest.mark.parametrize("samples, workers, sizes", [
    (64, 2, [32]),  # the paper planner: one share size, so one batch shape per function
    (64, 3, [21, 22]),  # 22, 21, 21 as tensor_split cuts them
    (16, 1, [16]),
    (2, 3, [1]),  # an empty share runs nothing
])
def test_the_share_sizes_are_the_batches_the_workers_solve(samples, workers, sizes):
    assert planner.share_sizes(samples, workers) == sizes


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
    assert (alone.samples, alone.workers, alone.worker_processes, alone.elites) == (32, 1, False, 8)
    assert (alone.spacing, alone.horizon, alone.dtype) == (config.planner.spacing, config.planner.horizon, "float32")
    assert setting == compilation.Precompiling(tmp_path / "planner", build=True)
    assert after == compilation.Precompiling(tmp_path, build=False)


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
    assert (alone.grad_steps, alone.samples, alone.workers, alone.horizon) == (0, 32, 1, config.planner.horizon)
    assert config.planner.grad_steps == 2 and setting == compilation.Precompiling(tmp_path / "planner", build=True)
