"""A service run as its own process for the service tests: started with its config and name, READY awaited with a
timeout, stopped by its pid (SIGINT, then SIGKILL)."""

from __future__ import annotations

import selectors
import signal
import subprocess
import sys

READY_TIMEOUT_S = 60.0
STOP_TIMEOUT_S = 10.0


class ServiceProcess:
    """``python -m hydrosoft.services.MODULE CONFIG --name NAME``; waits for its READY line, stops it by pid."""

    def __init__(self, module: str, name: str, config_path, log_path) -> None:
        self.name = name
        self.log_path = log_path
        self._log = log_path.open("wb")
        self.proc = subprocess.Popen([sys.executable, "-m", f"hydrosoft.services.{module}", str(config_path),
                                      "--name", name], stdout=subprocess.PIPE, stderr=self._log)

    def wait_ready(self, timeout_s: float = READY_TIMEOUT_S) -> None:
        with selectors.DefaultSelector() as selector:
            selector.register(self.proc.stdout, selectors.EVENT_READ)
            line = self.proc.stdout.readline().decode() if selector.select(timeout_s) else ""
        if not line.startswith(f"READY {self.name} {self.proc.pid}"):
            raise AssertionError(f"{self.name} not READY within {timeout_s} s ({line!r}):\n{self.log()}")

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")[-4000:]

    def stop(self) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(STOP_TIMEOUT_S)
        self._log.close()
        return self.proc.returncode
