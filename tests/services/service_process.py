"""A process for the service tests, started with its log in a file, READY awaited with a timeout, stopped by its
pid (SIGINT, then SIGKILL) or killed on purpose. ``ServiceProcess`` is a service of the stack started with its
config and name; ``ReadyProcess`` any command that prints the runtime's READY line."""

from __future__ import annotations

import selectors
import signal
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

READY_TIMEOUT_S = 60.0
STOP_TIMEOUT_S = 10.0


class ReadyProcess:
    """``command`` run as process ``name``: stderr (and stdout after READY) go to ``log_path``. Class attributes
    ``ready_timeout_s`` and ``stop_timeout_s`` bound the READY wait and each stage of ``stop``."""

    ready_timeout_s = READY_TIMEOUT_S
    stop_timeout_s = STOP_TIMEOUT_S

    def __init__(self, command: Sequence[object], name: str, log_path: Path) -> None:
        self.name = name
        self.log_path = log_path
        self._log = log_path.open("wb")
        self.proc = subprocess.Popen([str(part) for part in command], stdout=subprocess.PIPE, stderr=self._log)

    @property
    def pid(self) -> int:
        return self.proc.pid

    def wait_ready(self, timeout_s: float | None = None) -> None:
        timeout_s = self.ready_timeout_s if timeout_s is None else timeout_s
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
        self.proc.wait(self.stop_timeout_s)

    def stop(self) -> int:
        """SIGINT, then SIGKILL after ``stop_timeout_s``; the exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(self.stop_timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(self.stop_timeout_s)
        self.proc.stdout.close()
        self._log.close()
        return self.proc.returncode


class ServiceProcess(ReadyProcess):
    """``python -m hydrosoft.services.MODULE CONFIG --name NAME``."""

    def __init__(self, module: str, name: str, config_path, log_path) -> None:
        super().__init__([sys.executable, "-m", f"hydrosoft.services.{module}", config_path, "--name", name], name,
                         log_path)
