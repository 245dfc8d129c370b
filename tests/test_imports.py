"""Every module of the installed packages imports on its own, and their import graph has no cycles.

The graph is read from the source with ``ast``: an edge for each ``import`` or ``from ... import`` at a module's top
level (inside ``if``/``try`` blocks too, ``if TYPE_CHECKING:`` included), none for imports inside functions. A
package's ``__init__`` is a node of its own; importing a submodule adds no edge to its package.
"""

import ast
import json
import subprocess
import sys
from graphlib import CycleError, TopologicalSorter
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = {"hydrosoft": ROOT / "hydrosoft", "hydrosoft.services": ROOT / "services",
            "hydrosoft.drivers": ROOT / "drivers"}
"""Import name -> source folder, as pyproject.toml's ``package-dir`` maps them."""


def module_files() -> dict[str, Path]:
    """Every module of ``PACKAGES``: dotted name -> file (a package's name maps to its ``__init__.py``)."""
    modules = {}
    for package, folder in PACKAGES.items():
        for path in sorted(folder.rglob("*.py")):
            parts = path.relative_to(folder).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            modules[".".join((package, *parts))] = path
    return modules


def _top_level_imports(tree: ast.Module):
    """The ``Import``/``ImportFrom`` nodes of a module outside function and class bodies."""
    pending = list(tree.body)
    while pending:
        node = pending.pop()
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node
        elif isinstance(node, (ast.If, ast.Try, ast.With)):
            for field in ("body", "orelse", "finalbody", "handlers"):
                for child in getattr(node, field, []):
                    pending.extend(child.body if isinstance(child, ast.ExceptHandler) else [child])


def import_graph(modules: dict[str, Path]) -> dict[str, set[str]]:
    """Module -> the modules of ``modules`` it imports at its top level (module docstring)."""
    graph = {}
    for name, path in modules.items():
        is_package = path.name == "__init__.py"
        targets = set()
        for node in _top_level_imports(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                candidates = [alias.name for alias in node.names]
            else:
                base = node.module or ""
                if node.level:
                    anchor = name.split(".") if is_package else name.split(".")[:-1]
                    anchor = anchor[:len(anchor) - node.level + 1]
                    base = ".".join(anchor + ([base] if base else []))
                submodules = [f"{base}.{alias.name}" for alias in node.names if f"{base}.{alias.name}" in modules]
                candidates = submodules if len(submodules) == len(node.names) else [*submodules, base]
            targets.update(candidate for candidate in candidates if candidate in modules)
        graph[name] = targets - {name}
    return graph


def test_import_graph_has_no_cycles():
    graph = import_graph(module_files())
    try:
        TopologicalSorter(graph).prepare()
    except CycleError as error:
        pytest.fail(f"import cycle: {' -> '.join(error.args[1])}")


def test_import_graph_sees_a_cycle(tmp_path):
    """The graph reader finds a cycle through a relative ``from . import`` and an ``if TYPE_CHECKING:`` block."""
    (tmp_path / "a.py").write_text("from . import b\n")
    (tmp_path / "b.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pkg.a import x\n")
    (tmp_path / "c.py").write_text("def f():\n    import pkg.a\n")
    graph = import_graph({"pkg.a": tmp_path / "a.py", "pkg.b": tmp_path / "b.py", "pkg.c": tmp_path / "c.py"})
    assert graph == {"pkg.a": {"pkg.b"}, "pkg.b": {"pkg.a"}, "pkg.c": set()}
    with pytest.raises(CycleError):
        TopologicalSorter(graph).prepare()


IMPORT_EACH_ALONE = """
import importlib, json, sys, traceback
failed = {}
for name in json.loads(sys.argv[1]):
    ours = [key for key in sys.modules if key == "hydrosoft" or key.startswith("hydrosoft.")]
    for key in ours:
        del sys.modules[key]
    try:
        importlib.import_module(name)
    except BaseException:
        failed[name] = traceback.format_exc(limit=-3)
print(json.dumps(failed))
"""


def test_each_module_imports_alone():
    """One fresh interpreter imports each module in turn, with every ``hydrosoft`` module dropped from
    ``sys.modules`` before the next (third-party libraries stay loaded, which keeps this to seconds): a module that
    works only when another of ours was imported first fails here."""
    names = sorted(module_files())
    result = subprocess.run([sys.executable, "-c", IMPORT_EACH_ALONE, json.dumps(names)], cwd=ROOT,
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    failed = json.loads(result.stdout.strip().splitlines()[-1])
    assert not failed, "\n".join(f"{name}:\n{trace}" for name, trace in failed.items())


SENSOR_START = """
import json, sys
import numpy as np
from hydrosoft.services.bus.config import load_config
config = load_config(sys.argv[1])
from hydrosoft.services import arm_commander, ft_reader
from hydrosoft.services.tag_tracker import config_layout
config_layout(config, np.asarray(config.camera.pose, dtype=np.float64))
heavy = ("torch", "torch._dynamo", "hydrosoft.dynamics")
light = [key for key in heavy if key in sys.modules]
from hydrosoft.services.bubble_camera import BubbleDepth
BubbleDepth.nominal(config, config.arms[0].name)
print(json.dumps({"light": light, "bubble": [key for key in heavy[1:] if key in sys.modules]}))
"""


def test_sensor_services_start_without_the_compiler():
    """The tag tracker, arm commander and F/T reader import and lay out their start without torch, and the bubble
    camera without torch's compiler (``torch._dynamo``) or the model: each would cost every start (and every restart
    after a fault) seconds of CPU and a hundred MB or more (docs/benchmarks.md, "Stack start")."""
    result = subprocess.run([sys.executable, "-c", SENSOR_START, str(ROOT / "deploy" / "sim.toml")], cwd=ROOT,
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    imported = json.loads(result.stdout.strip().splitlines()[-1])
    assert imported == {"light": [], "bubble": []}
