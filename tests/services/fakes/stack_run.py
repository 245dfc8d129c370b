"""Test helpers: the real launcher as a subprocess over fake services (``fake_service.py``), its output read line by
line with arrival times, and checks that none of its processes is left.

``LauncherRun.cleanup`` SIGKILLs the launcher and every process group it reported (by pid), so a failing test
leaves nothing running.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path

FAKES_DIR = Path(__file__).resolve().parent
REPO = FAKES_DIR.parents[2]
#: Longest a test waits for one expected line, s (fake services start in ~0.5 s each on a busy 2-core machine).
LINE_TIMEOUT_S = 20.0
#: Longest a test waits for the launcher to exit after its shutdown began, s.
EXIT_TIMEOUT_S = 15.0

_PID_LINE = re.compile(r"^\[launcher\] .*\(pid (\d+)")
_CHILD_LINE = re.compile(r": child (\d+)$")
#: What the command line of a process this helper may kill contains (a pid could have been reused meanwhile).
_OURS = (b"fake_service", b"sleep")


def short_run_root() -> Path:
    """A fresh directory under /tmp with a short path (ipc socket paths must stay under 108 bytes)."""
    return Path(tempfile.mkdtemp(prefix="hs-", dir="/tmp"))


def write_config(root: Path, arms: list[str], extra: str = "") -> Path:
    """A stack config in ``root`` with ``run_dir = root/run``, the arms ``arms`` and ``extra`` TOML appended."""
    arm_tables = "".join(f'[[arms]]\nname = "{arm}"\nur_host = "127.0.0.{10 + i}"\n\n' for i, arm in enumerate(arms))
    path = root / "stack.toml"
    path.write_text(f'run_dir = "{root}/run"\n\n{arm_tables}{extra}')
    return path


def proc_state(pid: int) -> tuple[str, int] | None:
    """(state letter, process group) of ``pid`` from /proc, or None when there is no such process."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except (FileNotFoundError, ProcessLookupError):
        return None
    fields = text[text.rindex(")") + 2:].split()
    return fields[0], int(fields[2])


def alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie, which an unreaping container init may leave, counts as gone)."""
    state = proc_state(pid)
    return state is not None and state[0] != "Z"


def group_members(pgid: int) -> list[int]:
    """Live (non-zombie) processes in process group ``pgid``."""
    members = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            state = proc_state(int(entry.name))
            if state is not None and state[1] == pgid and state[0] != "Z":
                members.append(int(entry.name))
    return members


def _cmdline(pid: int) -> bytes:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes()
    except (FileNotFoundError, ProcessLookupError):
        return b""


def wait_until(condition: Callable[[], bool], timeout_s: float, period_s: float = 0.05) -> bool:
    """Poll ``condition`` until it holds or ``timeout_s`` passed; whether it held."""
    deadline_s = time.monotonic() + timeout_s
    while time.monotonic() < deadline_s:
        if condition():
            return True
        time.sleep(period_s)
    return condition()


class LauncherRun:
    """``python -m hydrosoft.services.commands.launch CONFIG ARGS`` running fake services (modes by service name)."""

    def __init__(self, config: Path, *args: str, modes: dict[str, str] | None = None) -> None:
        env = {**os.environ, "HYDROSOFT_SERVICE_MODULE": "fake_service",
               "HYDROSOFT_FAKE_MODES": ",".join(f"{name}={mode}" for name, mode in (modes or {}).items()),
               "PYTHONPATH": os.pathsep.join(filter(None, [str(FAKES_DIR), os.environ.get("PYTHONPATH")]))}
        self.lines: list[tuple[float, str]] = []
        self._lock = threading.Lock()
        self.process = subprocess.Popen([sys.executable, "-m", "hydrosoft.services.commands.launch", str(config), *args],
                                        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                        env=env, cwd=REPO, start_new_session=True)
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.process.stdout is not None
        for raw in self.process.stdout:
            with self._lock:
                self.lines.append((time.monotonic(), raw.decode(errors="replace").rstrip("\n")))

    def text(self) -> str:
        with self._lock:
            return "\n".join(line for _, line in self.lines)

    def find(self, predicate: Callable[[str], bool]) -> list[tuple[float, str]]:
        """Every (arrival time, line) so far whose line satisfies ``predicate``."""
        with self._lock:
            return [(t, line) for t, line in self.lines if predicate(line)]

    def wait_for(self, text: str, timeout_s: float = LINE_TIMEOUT_S) -> tuple[float, str]:
        """The first line containing ``text``, waiting up to ``timeout_s``; AssertionError with the log if none."""
        if wait_until(lambda: bool(self.find(lambda line: text in line)), timeout_s):
            return self.find(lambda line: text in line)[0]
        raise AssertionError(f"no line with {text!r} within {timeout_s} s; launcher log:\n{self.text()[-6000:]}")

    def index(self, text: str) -> int:
        """Line number of the first line containing ``text`` (AssertionError if none)."""
        with self._lock:
            for number, (_, line) in enumerate(self.lines):
                if text in line:
                    return number
        raise AssertionError(f"no line with {text!r}; launcher log:\n{self.text()[-6000:]}")

    def pids(self) -> set[int]:
        """Every service pid the launcher reported and every child pid a fake logged."""
        found = set()
        for _, line in self.find(lambda line: True):
            for pattern in (_PID_LINE, _CHILD_LINE):
                match = pattern.search(line)
                if match and match.group(1):
                    found.add(int(match.group(1)))
        return found

    def wait_exit(self, timeout_s: float = EXIT_TIMEOUT_S) -> int:
        """The launcher's exit code, waiting up to ``timeout_s`` (subprocess.TimeoutExpired past it)."""
        code = self.process.wait(timeout_s)
        self._reader.join(timeout_s)
        return code

    def cleanup(self) -> None:
        """SIGKILL the launcher and every process group it reported; reap the launcher."""
        if self.process.poll() is None:
            self.process.kill()
            self.process.wait(EXIT_TIMEOUT_S)
        for pid in self.pids():
            for member in {pid, *group_members(pid)}:
                if alive(member) and any(word in _cmdline(member) for word in _OURS):
                    with contextlib.suppress(ProcessLookupError):
                        os.kill(member, signal.SIGKILL)
        if self.process.stdout is not None:
            self.process.stdout.close()


def remove_tree(root: Path) -> None:
    shutil.rmtree(root, ignore_errors=True)
