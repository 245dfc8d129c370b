"""Processes for the recording tests: a private stack config under a short /tmp path, the fake publisher
(``fakes/bus_publisher.py``), the recorder, a real service, and the replay command; each started with its log in
a file, awaited READY with a timeout, and stopped by its pid (SIGINT, then SIGKILL), or killed on purpose.
"""

from __future__ import annotations

import shutil
import sys
import tempfile
from pathlib import Path

from service_process import ReadyProcess

FAKES_DIR = Path(__file__).resolve().parent / "fakes"
READY_TIMEOUT_S = 90.0  # torch and the scene compile on a busy 2-core machine
STOP_TIMEOUT_S = 15.0


def short_root() -> Path:
    """A fresh directory under /tmp with a short path (ipc socket paths must stay under 108 bytes)."""
    return Path(tempfile.mkdtemp(prefix="hsr-", dir="/tmp"))


def remove_root(root: Path) -> None:
    shutil.rmtree(root, ignore_errors=True)


def write_config(root: Path, name: str = "stack.toml") -> Path:
    """A sim config with ``run_dir = root/run`` (created) and one arm, ``bubble`` (the pushing scene)."""
    (root / "run").mkdir(exist_ok=True)
    path = root / name
    path.write_text(f'run_dir = "{root}/run"\nmode = "sim"\n[[arms]]\nname = "bubble"\n')
    return path


class Proc(ReadyProcess):
    """A process of the recording tests, with their longer bounds (torch and the scene compile on a busy
    machine)."""

    ready_timeout_s = READY_TIMEOUT_S
    stop_timeout_s = STOP_TIMEOUT_S


def publisher(config: Path, root: Path) -> Proc:
    """The fake publisher (``fakes/bus_publisher.py``), running as ``ft_reader-bubble``."""
    return Proc([sys.executable, FAKES_DIR / "bus_publisher.py", config], "ft_reader-bubble", root / "publisher.log")


def recorder(config: Path, root: Path, *args: object, name: str = "recorder") -> Proc:
    """``python -m hydrosoft.services.recorder CONFIG --name NAME ARGS...``."""
    return Proc([sys.executable, "-m", "hydrosoft.services.recorder", config, "--name", name, *args], name,
                root / f"{name}.log")


def service(module: str, config: Path, root: Path, log_name: str | None = None) -> Proc:
    """A real service of the stack, ``python -m hydrosoft.services.MODULE CONFIG --name MODULE``."""
    return Proc([sys.executable, "-m", f"hydrosoft.services.{module}", config, "--name", module], module,
                root / f"{log_name or module}.log")
