"""``hydrosoft-stack compile``: it builds the artefacts of a config's compiled plant and planner as their services'
start-ups do, rebuilds a stale one, or says why it cannot."""

from __future__ import annotations

import functools
import json
from pathlib import Path

import pytest
import torch

from hydrosoft.dynamics import CompiledStep
from hydrosoft.services import sim_world
from hydrosoft.services.bus import artefacts
from hydrosoft.services.commands.cli import main
from hydrosoft.services.bus.service_cli import CACHE_ENV
from hydrosoft.tasks import evaluation
from hydrosoft.tasks.base import compiled_cost_terms

SIM_TOML = Path(__file__).parents[3] / "deploy" / "sim.toml"


@pytest.fixture
def no_cache_env(monkeypatch):
    """TORCHINDUCTOR_CACHE_DIR unset for the test and restored after it."""
    monkeypatch.setenv(CACHE_ENV, "placeholder")  # records the variable's state before the test
    monkeypatch.delenv(CACHE_ENV)


def compiled_config(tmp_path: Path, samples: int = 16, plant: bool = True) -> Path:
    """deploy/sim.toml with the planner compiled (``samples`` samples), the plant compiled or not, and the compile
    cache under ``tmp_path``."""
    path = tmp_path / "compiled.toml"
    text = SIM_TOML.read_text().replace("compile = false ", "compile = true ", 1)
    if not plant:
        text = text.replace("compile = true                      # compiled plant", "compile = false # compiled plant")
    text = text.replace("samples = 16\n", f"samples = {samples}\n", 1)
    path.write_text(f'compile_cache_dir = "{tmp_path}/cache"\n' + text)
    return path


def failing_backend(graph, example_inputs):
    raise RuntimeError("no C++ compiler")


def test_an_eager_stack_has_nothing_to_compile(tmp_path, capsys):
    path = compiled_config(tmp_path, plant=False)
    path.write_text(path.read_text().replace("compile = true ", "compile = false ", 1))
    assert main(["compile", str(path)]) == 0
    assert "nothing to compile" in capsys.readouterr().out


def test_a_bad_config_is_refused_by_key(tmp_path, capsys):
    path = tmp_path / "bad.toml"
    path.write_text(SIM_TOML.read_text().replace("sdf_solver_steps = 3", "sdf_solver_steps = -1", 1))
    assert main(["compile", str(path)]) == 2
    assert "planner.sdf_solver_steps" in capsys.readouterr().err


def test_it_builds_each_parts_artefact_and_rebuilds_a_stale_one(tmp_path, capsys, monkeypatch, no_cache_env):
    """Wiring only: dynamo's ``eager`` backend stands in for inductor (whose C++ compile takes minutes)."""
    backends = []

    def recording_backend(graph, example_inputs):
        backends.append(len(example_inputs))
        return graph.forward

    monkeypatch.setattr(evaluation, "CompiledStep", functools.partial(CompiledStep, backend=recording_backend))
    monkeypatch.setattr(evaluation, "compiled_cost_terms", functools.partial(compiled_cost_terms, backend="eager"))
    monkeypatch.setattr(sim_world, "CompiledStep", functools.partial(CompiledStep, backend="eager"))
    cache = tmp_path / "cache"
    try:
        assert main(["compile", str(compiled_config(tmp_path))]) == 0
        first = capsys.readouterr().out
        built = {part: json.loads(artefacts.record_path(cache, part).read_text())["key"]
                 for part in ("plant", "planner")}
        assert main(["compile", str(compiled_config(tmp_path, samples=32))]) == 0
        second = capsys.readouterr().out
    finally:
        torch._dynamo.reset()
    assert f"plant: compiling: missing artefact, building {built['plant']}" in first
    assert f"planner: compiling: missing artefact, building {built['planner']}" in first
    assert f"planner: compiled (artefact {built['planner']})" in first and f"artefacts in {cache}" in first
    assert len(backends) >= 2  # a solve's signatures: gradient-enabled and no-grad rollouts at least
    # more samples: the planner's artefact is stale and rebuilt, the plant's is loaded
    assert f"plant: compiling: loading artefact {built['plant']}" in second
    rebuilt = json.loads(artefacts.record_path(cache, "planner").read_text())["key"]
    assert rebuilt != built["planner"]
    assert f"planner: compiling: stale artefact (config changed), building {rebuilt}" in second
    assert f"planner: compiled (artefact {rebuilt})" in second


@pytest.mark.parametrize("failing, named, unnamed", [
    ("step", ["(planner: step: "], "cost:"),
    ("costs", ["(planner: stage cost: ", "; terminal cost: "], "step:"),
])
def test_a_part_that_falls_back_to_eager_fails_and_is_named(failing, named, unnamed, tmp_path, capsys, monkeypatch,
                                                            no_cache_env):
    backends = {"step": "eager", "costs": "eager", failing: failing_backend}
    monkeypatch.setattr(evaluation, "CompiledStep", functools.partial(CompiledStep, backend=backends["step"]))
    monkeypatch.setattr(evaluation, "compiled_cost_terms", functools.partial(compiled_cost_terms,
                                                                          backend=backends["costs"]))
    try:
        with pytest.warns(RuntimeWarning, match="running eager"):
            assert main(["compile", str(compiled_config(tmp_path, plant=False))]) == 1
    finally:
        torch._dynamo.reset()
    err = capsys.readouterr().err
    assert "fell back to eager" in err and "no C++ compiler" in err and unnamed not in err
    assert all(text in err for text in named)
    assert not artefacts.record_path(tmp_path / "cache", "planner").exists()  # nothing recorded for it
