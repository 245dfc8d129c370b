"""Processes for the recording tests: a private stack config under a short /tmp path, the fake publisher
(``fakes/bus_publisher.py``), the recorder, a real service, and the replay command; each started with its log in
a file, awaited READY with a timeout, and stopped by its pid (SIGINT, then SIGKILL), or killed on purpose.
"""

from __future__ import annotations

import selectors
import shutil
import signal
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

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


class Proc:
    """One process started with ``command``; stderr (and stdout after READY) go to ``log_path``."""

    def __init__(self, command: Sequence[str], name: str, log_path: Path) -> None:
        self.name = name
        self.log_path = log_path
        self._log = log_path.open("wb")
        self.proc = subprocess.Popen([str(part) for part in command], stdout=subprocess.PIPE, stderr=self._log)

    @property
    def pid(self) -> int:
        return self.proc.pid

    def wait_ready(self, timeout_s: float = READY_TIMEOUT_S) -> None:
        with selectors.DefaultSelector() as selector:
            selector.register(self.proc.stdout, selectors.EVENT_READ)
            line = self.proc.stdout.readline().decode() if selector.select(timeout_s) else ""
        if not line.startswith(f"READY {self.name} {self.proc.pid}"):
            raise AssertionError(f"{self.name} not READY within {timeout_s} s ({line!r}):\n{self.log()}")

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")[-6000:]

    def kill(self) -> None:
        """SIGKILL, as a crash would."""
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(STOP_TIMEOUT_S)

    def stop(self) -> int:
        """SIGINT, then SIGKILL after ``STOP_TIMEOUT_S``; the exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(STOP_TIMEOUT_S)
        self.proc.stdout.close()
        self._log.close()
        return self.proc.returncode


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
