"""``hydrosoft-stack compile``: it builds the artefacts of a config's compiled plant and planner as their services'
start-ups do, rebuilds a stale one, or says why it cannot."""

from __future__ import annotations

import functools
import os
import re
from pathlib import Path

import pytest
import torch

from hydrosoft.compilation import PRECOMPILED_ENV
from hydrosoft.dynamics import CompiledStep
from hydrosoft.services import sim_world
from hydrosoft.services.bus import artefacts
from hydrosoft.services.commands.cli import main
from hydrosoft.services.bus.config import load_config
from hydrosoft.services.bus.service_cli import CACHE_ENV
from hydrosoft.tasks import evaluation
from hydrosoft.tasks.base import compiled_cost_terms
from stack_process import quick_planner

SIM_TOML = Path(__file__).parents[3] / "deploy" / "sim.toml"


@pytest.fixture
def no_cache_env(monkeypatch):
    """TORCHINDUCTOR_CACHE_DIR unset for the test and restored after it."""
    monkeypatch.setenv(CACHE_ENV, "placeholder")  # records the variable's state before the test
    monkeypatch.delenv(CACHE_ENV)


@pytest.fixture(autouse=True)
def precompiled_env_restored(monkeypatch):
    """The precompiled directory ``compiled_parts`` sets (``artefacts.use_precompiled``) unset after the test, so
    that no later test's compiled functions are precompiled into it."""
    monkeypatch.setenv(PRECOMPILED_ENV, "placeholder")  # records the variable's state before the test
    monkeypatch.delenv(PRECOMPILED_ENV)


def compiled_config(tmp_path: Path, plant: bool = True) -> Path:
    """deploy/sim.toml with the planner compiled, the plant compiled or not, and the compile cache under
    ``tmp_path``."""
    path = tmp_path / "compiled.toml"
    text = quick_planner(SIM_TOML.read_text()).replace('preset = "quick"', 'preset = "quick"\ncompile = true', 1)
    if not plant:
        text = re.sub(r"(\[sim\][^\[]*?\n)compile = true", r"\1compile = false", text, count=1)
    path.write_text(f'compile_cache_dir = "{tmp_path}/cache"\n' + text)
    return path


def failing_backend(graph, example_inputs):
    raise RuntimeError("no C++ compiler")


def test_an_eager_stack_has_nothing_to_compile(tmp_path, capsys):
    path = tmp_path / "eager.toml"
    path.write_text(re.sub(r"(\[sim\][^\[]*?\n)compile = true", r"\1compile = false",
                           quick_planner(SIM_TOML.read_text()), count=1))
    assert main(["compile", str(path)]) == 0
    assert "nothing to compile" in capsys.readouterr().out


def test_a_bad_config_is_refused_by_key(tmp_path, capsys):
    path = tmp_path / "bad.toml"
    path.write_text(SIM_TOML.read_text().replace('preset = "paper"', 'preset = "paper"\nsdf_solver_steps = -1', 1))
    assert main(["compile", str(path)]) == 2
    assert "planner.sdf_solver_steps" in capsys.readouterr().err


def test_it_builds_each_parts_artefact_and_rebuilds_a_stale_one(tmp_path, capsys, monkeypatch, no_cache_env):
    """Wiring only: dynamo's ``eager`` backend stands in for inductor (whose C++ compile takes minutes). The cache
    holds the planner's artefact of another torch version (stale) and none of the plant's (missing). The plant
    builds in a process of its own, beside the planner's build here, and so do the planner's functions without
    gradients; their lines come out here."""
    backends = []
    plant_pids = tmp_path / "plant-pids"

    def recording_backend(graph, example_inputs):
        backends.append(len(example_inputs))
        return graph.forward

    def plant_backend(graph, example_inputs):
        with plant_pids.open("a") as file:  # from the plant's process, whose memory this test does not see
            file.write(f"{os.getpid()}\n")
        return graph.forward

    monkeypatch.setattr(evaluation, "CompiledStep", functools.partial(CompiledStep, backend=recording_backend))
    monkeypatch.setattr(evaluation, "compiled_cost_terms", functools.partial(compiled_cost_terms, backend="eager"))
    monkeypatch.setattr(sim_world, "CompiledStep", functools.partial(CompiledStep, backend=plant_backend))
    path, cache = compiled_config(tmp_path), tmp_path / "cache"
    config = load_config(path)
    plant, planner = artefacts.plant_key(config), artefacts.planner_key(config)
    artefacts.record(cache, artefacts.planner_key(config, "2.12.1"), 60.0)
    try:
        assert main(["compile", str(path)]) == 0
    finally:
        torch._dynamo.reset()
    out = capsys.readouterr().out
    assert f"plant: compiling: missing artefact, building {plant.key}" in out
    assert f"planner: compiling: stale artefact (torch 2.12.1 -> {torch.__version__}), building {planner.key}" in out
    assert f"plant: compiled (artefact {plant.key})" in out and f"planner: compiled (artefact {planner.key})" in out
    assert f"artefacts in {cache}" in out
    assert artefacts.check(cache, plant) == artefacts.check(cache, planner) == "ready"
    assert len(backends) >= 2  # a solve's signatures: gradient-enabled and no-grad rollouts at least
    assert plant_pids.read_text().split() and str(os.getpid()) not in plant_pids.read_text().split()
    assert "planner: its functions without gradients built in" in out  # beside the planner's build, which needs them


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
    assert not list((tmp_path / "cache" / artefacts.RECORDS).glob("planner-*.json"))  # nothing recorded for it
