"""The documentation keeps its word: the README's command list is the CLI's, every file a doc names exists, no file
points outside the repository, and the README stays a short guide."""

import argparse
import os
import re
import shlex
from pathlib import Path

import pytest

from hydrosoft.services.commands.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
README_MAX_LINES = 350
SKIPPED_DIRS = {".git", ".venv", "__pycache__", ".pytest_cache", ".hypothesis", "build", "dist", "out"}
TOP_LEVEL = ("hydrosoft/", "services/", "drivers/", "deploy/", "tests/", "docs/", "results/", ".ci/")
"""A path a doc names is checked when it starts with one of these folders (or is a relative link)."""
OUTSIDE_REFERENCE = re.compile(r"\.\./shared|(?<![\w.])/(?:work|home|Users|root)/")
"""A reference to the design folder beside the repository, or an absolute path in some machine's home or work tree."""


def repo_files(suffixes: tuple[str, ...]) -> list[Path]:
    """The repository's files with these suffixes, without environments, caches and build outputs."""
    found = []
    for folder, subfolders, files in os.walk(ROOT):
        subfolders[:] = [name for name in subfolders if name not in SKIPPED_DIRS and not name.endswith(".egg-info")]
        found += [Path(folder, name) for name in files if Path(name).suffix in suffixes]
    return sorted(found)


def docs() -> list[Path]:
    """Every Markdown file of the repository."""
    return repo_files((".md",))


def cli_commands(parser: argparse.ArgumentParser, prefix: tuple[str, ...] = ()) -> dict[tuple[str, ...], set[str]]:
    """Every leaf command of the parser (``("bench", "model")``) -> the option strings it takes."""
    commands = {}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                commands.update(cli_commands(sub, (*prefix, name)))
    if not commands and prefix:
        commands[prefix] = {option for action in parser._actions for option in action.option_strings}
    return commands


def readme_commands(text: str) -> dict[tuple[str, ...], set[str]]:
    """The README's command list (the code block under "## Commands"): each command -> the options its lines show."""
    section = text.split("\n## Commands", 1)[1].split("\n## ", 1)[0]
    block = re.search(r"```\n(.*?)```", section, flags=re.S).group(1)
    listed: dict[tuple[str, ...], set[str]] = {}
    for line in block.splitlines():
        words = shlex.split(line.split("  #", 1)[0].replace("[", " ").replace("]", " ").replace("|", " "))
        if not words or words[0] != "hydrosoft-stack" or words[1:2] == ["--help"]:
            continue
        path = tuple(words[1:3]) if words[1] in GROUPS else tuple(words[1:2])
        listed.setdefault(path, set()).update(word.split("=")[0] for word in words if word.startswith("-"))
    return listed


GROUPS = {path[0] for path in cli_commands(build_parser()) if len(path) == 2}


def test_readme_lists_every_command_of_the_cli_and_no_other():
    cli = cli_commands(build_parser())
    listed = readme_commands(README.read_text())
    assert sorted(listed) == sorted(cli), "README's command list and `hydrosoft-stack --help` disagree"
    unknown = {" ".join(path): sorted(options - cli[path]) for path, options in listed.items() if options - cli[path]}
    assert not unknown, f"README shows options these commands do not take: {unknown}"


def test_the_command_list_check_sees_a_missing_command():
    text = README.read_text()
    listed = readme_commands(text)
    dropped = next(path for path in listed if len(path) == 2)
    lines = [line for line in text.splitlines() if not line.startswith(f"hydrosoft-stack {' '.join(dropped)}")]
    assert dropped not in readme_commands("\n".join(lines))


def named_paths(doc: Path) -> list[tuple[str, Path | None]]:
    """The files a doc names: its relative links and the repository paths it writes in backticks, each with where
    it may lie (relative to the doc or to the repository root: either is accepted)."""
    text = doc.read_text()
    names = [target for target in re.findall(r"\]\(([^)\s]+)\)", text) if not re.match(r"[a-z]+:|#", target)]
    for span in re.findall(r"`([^`\n]+)`", text):
        for word in span.split():
            word = word.strip(".,;:()'\"")
            if word.startswith(TOP_LEVEL) and not re.search(r"[*<>{}$]|\b[A-Z]{2,}\b(?!\.md)", word):
                names.append(word)
    return [name.split("#")[0].split("::")[0] for name in names]


def test_every_file_a_doc_names_exists():
    missing = []
    for doc in docs():
        for name in named_paths(doc):
            if not ((doc.parent / name).exists() or (ROOT / name).exists()):
                missing.append(f"{doc.relative_to(ROOT)}: {name}")
    assert not missing, "docs name files that do not exist:\n" + "\n".join(missing)


def test_every_test_a_doc_names_exists():
    """``tests/...py::name`` in a doc (docs/safety.md cites its tests so) names a test function of that file."""
    missing = []
    for doc in docs():
        for path, name in re.findall(r"(tests/[\w/]+\.py)::(\w+)", doc.read_text()):
            source = ROOT / path
            if not source.exists() or not re.search(rf"^\s*(async )?def {name}\(", source.read_text(), flags=re.M):
                missing.append(f"{doc.relative_to(ROOT)}: {path}::{name}")
    assert not missing, "docs cite tests that do not exist:\n" + "\n".join(missing)


def test_the_path_check_sees_a_missing_file(tmp_path):
    doc = tmp_path / "guide.md"
    doc.write_text("See [the model](model.md) and `deploy/nowhere.toml`, not `deploy/sim.toml` or `services/NAME.py`.")
    (tmp_path / "model.md").write_text("")
    assert named_paths(doc) == ["model.md", "deploy/nowhere.toml", "deploy/sim.toml"]


def test_no_file_refers_outside_the_repository():
    found = []
    for path in repo_files((".py", ".md", ".toml", ".service", ".txt", ".cfg", ".sh", ".yml", ".yaml")):
        for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            if OUTSIDE_REFERENCE.search(line):
                found.append(f"{path.relative_to(ROOT)}:{number}: {line.strip()}")
    assert not found, "files refer to paths outside the repository:\n" + "\n".join(found)


@pytest.mark.parametrize("line, bad", [("see ../" "shared/ARCHITECTURE.md", True), ("``/" "work/x/devices.md``", True),
                                       ("cd /" "home/me/repo", True), ("/opt/hydrosoft/.venv/bin/pip", False),
                                       ("docs/devices.md section 7", False)])  # split literals: this file passes too
def test_the_outside_reference_pattern(line, bad):
    assert bool(OUTSIDE_REFERENCE.search(line)) == bad


def test_readme_is_a_short_guide():
    lines = len(README.read_text().splitlines())
    assert lines <= README_MAX_LINES, f"README.md has {lines} lines (at most {README_MAX_LINES})"
