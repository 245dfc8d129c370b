"""The README's API example runs as written, and its first two commands are the ones CI runs."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_readme_python_example_runs(capsys):
    text = (ROOT / "README.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    assert blocks, "README has no python example"
    exec(compile(blocks[0], "README.md", "exec"), {})
    out = capsys.readouterr().out
    assert "planar SE(2) model" in out


def test_ci_runs_the_readme_test_command():
    readme = (ROOT / "README.md").read_text()
    commands = re.findall(r"```bash\n(.*?)```", readme, flags=re.S)[0].strip().splitlines()
    test_command = commands[1].replace("python3 -m pip install", "").split("&&")
    ci = (ROOT / ".ci" / "run").read_text()
    assert "pip install torch==2.13.0 -e '.[dev]'" in ci and "python3 -m pytest -q" in ci
    assert test_command[-1].strip() == "python3 -m pytest -q"
