"""``hydrosoft-stack compile``: it compiles the planner's step as the planner's start-up does, or says why not."""

from __future__ import annotations

import functools
from pathlib import Path

import pytest
import torch

from hydrosoft.dynamics import CompiledStep
from hydrosoft.services.commands.cli import main
from hydrosoft.services.bus.service_cli import CACHE_ENV
from hydrosoft.tasks import evaluation
from hydrosoft.tasks.base import compiled_cost_terms
from stack_process import quick_planner

SIM_TOML = Path(__file__).parents[2] / "deploy" / "sim.toml"


@pytest.fixture
def no_cache_env(monkeypatch):
    """TORCHINDUCTOR_CACHE_DIR unset for the test and restored after it."""
    monkeypatch.setenv(CACHE_ENV, "placeholder")  # records the variable's state before the test
    monkeypatch.delenv(CACHE_ENV)


def compiled_config(tmp_path: Path) -> Path:
    """deploy/sim.toml with the planner compiled and its compile cache under ``tmp_path``."""
    path = tmp_path / "compiled.toml"
    text = quick_planner(SIM_TOML.read_text()).replace('preset = "quick"', 'preset = "quick"\ncompile = true', 1)
    path.write_text(f'compile_cache_dir = "{tmp_path}/cache"\n' + text)
    return path


def failing_backend(graph, example_inputs):
    raise RuntimeError("no C++ compiler")


def test_an_eager_planner_has_nothing_to_compile(tmp_path, capsys):
    path = tmp_path / "quick.toml"
    path.write_text(quick_planner(SIM_TOML.read_text()))
    assert main(["compile", str(path)]) == 0
    assert "nothing to compile" in capsys.readouterr().out


def test_a_bad_config_is_refused_by_key(tmp_path, capsys):
    path = tmp_path / "bad.toml"
    path.write_text(SIM_TOML.read_text().replace('preset = "paper"', 'preset = "paper"\nsdf_solver_steps = -1', 1))
    assert main(["compile", str(path)]) == 2
    assert "planner.sdf_solver_steps" in capsys.readouterr().err


def test_it_compiles_the_planner_step_into_the_configs_cache(tmp_path, capsys, monkeypatch, no_cache_env):
    """Wiring only: dynamo's ``eager`` backend stands in for inductor (whose C++ compile takes minutes)."""
    backends = []

    def recording_backend(graph, example_inputs):
        backends.append(len(example_inputs))
        return graph.forward

    monkeypatch.setattr(evaluation, "CompiledStep", functools.partial(CompiledStep, backend=recording_backend))
    monkeypatch.setattr(evaluation, "compiled_cost_terms", functools.partial(compiled_cost_terms, backend="eager"))
    try:
        assert main(["compile", str(compiled_config(tmp_path))]) == 0
    finally:
        torch._dynamo.reset()
    out = capsys.readouterr().out
    assert f"into {tmp_path}/cache" in out and "planner step and costs compiled in" in out
    assert len(backends) >= 2  # a solve's signatures: gradient-enabled and no-grad rollouts at least


@pytest.mark.parametrize("failing, named, unnamed", [
    ("step", ["(step: "], "cost:"),
    ("costs", ["(stage cost: ", "; terminal cost: "], "step:"),
])
def test_a_part_that_falls_back_to_eager_fails_and_is_named(failing, named, unnamed, tmp_path, capsys, monkeypatch,
                                                            no_cache_env):
    backends = {"step": "eager", "costs": "eager", failing: failing_backend}
    monkeypatch.setattr(evaluation, "CompiledStep", functools.partial(CompiledStep, backend=backends["step"]))
    monkeypatch.setattr(evaluation, "compiled_cost_terms", functools.partial(compiled_cost_terms,
                                                                          backend=backends["costs"]))
    try:
        with pytest.warns(RuntimeWarning, match="running eager"):
            assert main(["compile", str(compiled_config(tmp_path))]) == 1
    finally:
        torch._dynamo.reset()
    err = capsys.readouterr().err
    assert "fell back to eager" in err and "no C++ compiler" in err and unnamed not in err
    assert all(text in err for text in named)
