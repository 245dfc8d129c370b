"""Compiled artefacts: their keys, records and the start of a compiled part (``services/bus/artefacts.py``), without
torch compiling anything."""

from __future__ import annotations

import json
import time
from collections import Counter
from pathlib import Path

import msgspec
import pytest

from hydrosoft import compilation
from hydrosoft.services.bus import artefacts
from hydrosoft.services.bus.config import load_config

SIM_TOML = Path(__file__).parents[3] / "deploy" / "sim.toml"


@pytest.fixture
def config():
    return load_config(SIM_TOML)


def changed(config, section: str, **values):
    return msgspec.structs.replace(config, **{section: msgspec.structs.replace(getattr(config, section), **values)})


def test_a_key_changes_with_the_graph_shaping_config_and_the_torch_version(config):
    planner, plant = artefacts.planner_key(config, "2.13.0"), artefacts.plant_key(config, "2.13.0")
    assert planner.key != plant.key and len(planner.key) == 12
    assert artefacts.planner_key(config, "2.13.0") == planner  # the same config and torch: the same key
    assert artefacts.planner_key(config, "2.12.1").key != planner.key
    assert artefacts.plant_key(config, "2.12.1").key != plant.key
    more_samples = changed(config, "planner", samples=2 * config.planner.samples)
    assert artefacts.planner_key(more_samples, "2.13.0").key != planner.key
    assert artefacts.plant_key(more_samples, "2.13.0") == plant  # the plant's graphs do not depend on it
    finer_plant = changed(config, "sim", spacing_factor=0.25)
    assert artefacts.plant_key(finer_plant, "2.13.0").key != plant.key
    assert artefacts.planner_key(finer_plant, "2.13.0") == planner
    other_task = changed(config, "scene", task="rotation")
    assert artefacts.planner_key(other_task, "2.13.0").key != planner.key
    assert artefacts.plant_key(other_task, "2.13.0").key != plant.key


def test_runtime_settings_keep_the_key(config):
    """Timing, priority and device settings do not shape the graphs: changing them rebuilds nothing."""
    planner, plant = artefacts.planner_key(config, "2.13.0"), artefacts.plant_key(config, "2.13.0")
    timing = changed(changed(config, "planner", target_lead_s=0.7, heartbeat_period_s=0.05, stall_s=30.0,
                             nice=(config.planner.nice + 5) % 20), "sim", image_noise=0.0)
    assert artefacts.planner_key(timing, "2.13.0") == planner and artefacts.plant_key(timing, "2.13.0") == plant


def test_a_record_is_ready_for_its_key_and_stale_for_another(tmp_path, config):
    key = artefacts.planner_key(config, "2.13.0")
    assert artefacts.check(tmp_path, key) == "missing artefact"
    artefacts.record(tmp_path, key, 12.5)
    assert artefacts.check(tmp_path, key) == "ready"
    saved = json.loads(artefacts.record_path(tmp_path, key).read_text())
    assert saved["key"] == key.key and saved["compile_s"] == 12.5
    assert artefacts.check(tmp_path, artefacts.planner_key(config, "2.14.0")) == (
        "stale artefact (torch 2.13.0 -> 2.14.0)")
    assert artefacts.check(tmp_path, artefacts.planner_key(changed(config, "planner", horizon=config.planner.horizon + 1), "2.13.0")) == (
        "stale artefact (config changed)")
    assert artefacts.check(tmp_path, artefacts.plant_key(config, "2.13.0")) == "missing artefact"  # per part
    other = artefacts.planner_key(changed(config, "scene", task="rotation"), "2.13.0")
    artefacts.record(tmp_path, other, 3.0)  # another config's planner beside it
    assert artefacts.check(tmp_path, other) == "ready" and artefacts.check(tmp_path, key) == "ready"


def test_an_unreadable_record_is_missing(tmp_path, config):
    key = artefacts.plant_key(config, "2.13.0")
    artefacts.record_path(tmp_path, key).parent.mkdir(parents=True)
    artefacts.record_path(tmp_path, key).write_text('{"key": "abc"')
    assert artefacts.check(tmp_path, key) == "missing artefact"


def test_a_stale_artefact_is_rebuilt_with_progress_and_recorded(tmp_path, config):
    old = artefacts.planner_key(config, "2.12.1")
    artefacts.record(tmp_path, old, 30.0)
    key = artefacts.planner_key(config, "2.13.0")
    build = artefacts.PartBuild(key, tmp_path)
    assert not build.ready and build.status == f"compiling: stale artefact (torch 2.12.1 -> 2.13.0), building {key.key}"
    lines, calls = [], []

    def compile_slowly():
        calls.append(1)
        time.sleep(0.5)
        return None

    assert build.run(compile_slowly, lines.append, period_s=0.1)
    assert calls == [1] and build.status == f"compiled (artefact {key.key})"
    assert lines[0].startswith("planner: compiling: stale artefact") and "building its artefact" in lines[0]
    assert sum("still compiling" in line for line in lines) >= 1  # progress while it compiles
    assert lines[-1].startswith(f"planner: compiled (artefact {key.key}) in ")
    assert artefacts.check(tmp_path, key) == "ready"
    again = artefacts.PartBuild(key, tmp_path)
    assert again.ready and again.status == f"compiling: loading artefact {key.key}"


def test_a_part_that_falls_back_to_eager_says_so_and_records_nothing(tmp_path, config):
    key = artefacts.plant_key(config, "2.13.0")
    build = artefacts.PartBuild(key, tmp_path)
    lines = []
    assert not build.run(lambda: "InductorError: no C++ compiler", lines.append)
    assert build.status == "eager: InductorError: no C++ compiler"
    assert "fell back to eager" in lines[-1]
    assert artefacts.check(tmp_path, key) == "missing artefact"


@pytest.mark.parametrize("counted, precompiled", [
    ({"loaded": 2}, True),  # a launch that loaded every function whole
    ({"loaded": 1, "jit": 1}, False),  # one signature had no file: dynamo traced it
    ({}, False),  # nothing precompiled (the planner)
])
def test_the_status_says_whether_the_part_was_precompiled_or_traced(counted, precompiled, tmp_path, config,
                                                                   monkeypatch):
    monkeypatch.setattr(compilation, "PRECOMPILED", Counter())
    key = artefacts.plant_key(config)
    artefacts.record(tmp_path, key, 1.0)
    build = artefacts.PartBuild(key, tmp_path)
    lines = []
    assert build.run(lambda: compilation.PRECOMPILED.update(counted), lines.append)
    assert build.status == f"compiled (artefact {key.key}{', precompiled' if precompiled else ''})"
    assert f"{counted.get('loaded', 0)} loaded, {counted.get('jit', 0)} traced instead)" in lines[-1]


@pytest.mark.parametrize("workers, precompiled", [
    ({"loaded": 16}, True),  # every worker process loaded every function this process built
    ({"loaded": 15, "jit": 1}, False),  # a worker process could not load one: it traced it, and the status says so
])
def test_the_planners_status_counts_what_its_worker_processes_loaded(workers, precompiled, tmp_path, config,
                                                                     monkeypatch):
    """The planner builds its precompiled functions in its own process and its solver worker processes load them:
    the status and the lines count both (``elsewhere``), and a worker that traced one is no longer "precompiled"."""
    monkeypatch.setattr(compilation, "PRECOMPILED", Counter())
    key = artefacts.planner_key(config)
    build = artefacts.PartBuild(key, tmp_path)
    elsewhere = Counter()
    lines = []

    def build_here_then_load_there():
        compilation.PRECOMPILED.update(built=8)
        elsewhere.update(workers)

    assert build.run(build_here_then_load_there, lines.append, elsewhere=lambda: elsewhere)
    assert build.status == f"compiled (artefact {key.key}{', precompiled' if precompiled else ''})"
    assert (f"8 precompiled functions built, {workers['loaded']} loaded, {workers.get('jit', 0)} traced instead)"
            in lines[-1])


def test_the_cache_is_the_environments_then_the_configs_then_torchs(tmp_path, config, monkeypatch):
    monkeypatch.delenv(artefacts.CACHE_ENV, raising=False)
    assert artefacts.cache_dir(config).name.startswith("torchinductor_")
    named = msgspec.structs.replace(config, compile_cache_dir=str(tmp_path / "named"))
    assert artefacts.cache_dir(named) == tmp_path / "named"
    monkeypatch.setenv(artefacts.CACHE_ENV, str(tmp_path / "env"))
    assert artefacts.cache_dir(named) == tmp_path / "env"


@pytest.mark.parametrize("name", ["sim.toml", "sim-bimanual.toml"])
def test_a_shipped_compiled_plant_is_loop_free_so_its_artefact_loads(name):
    """A plant solved to convergence is a ``torch.while_loop``, which torch's compile cache refuses: it would compile
    at every launch, its artefact never loaded. The shipped sim configs fix the solver's steps, as their planners do."""
    config = load_config(SIM_TOML.parent / name)
    assert config.sim.compile
    assert config.sim.sdf_solver_steps is not None
