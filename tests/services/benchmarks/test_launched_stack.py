"""A benchmark's child processes (``launched_stack.Child``): stopped by pid, and never left running when the
benchmark itself is killed."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

PARENT = textwrap.dedent("""
    import sys, time
    from pathlib import Path
    from hydrosoft.services.benchmarks.launched_stack import Child
    child = Child([sys.executable, "-c", "import time; print('up', flush=True); time.sleep(120)"], Path(sys.argv[1]))
    child.wait_for("up", 30.0)
    print(child.process.pid, flush=True)
    time.sleep(120)
""")


def alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie, dead but not yet reaped, counts as dead)."""
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="a parent's death signal is Linux's")
def test_a_child_gets_sigterm_when_the_benchmark_that_started_it_is_killed(tmp_path):
    """SIGKILL skips a benchmark's ``finally`` (which stops its stack by pid): its launcher, a ``Child``, must then
    end by itself. Before, a killed ``bench soak`` left its whole stack running."""
    parent = subprocess.Popen([sys.executable, "-c", PARENT, str(tmp_path / "child.log")], stdout=subprocess.PIPE,
                              text=True)
    child_pid = None
    try:
        child_pid = int(parent.stdout.readline())
        assert alive(child_pid)
        parent.kill()
        parent.wait(10)
        deadline = time.monotonic() + 10.0
        while alive(child_pid) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not alive(child_pid), "the child outlived the benchmark that started it"
    finally:
        if parent.poll() is None:
            parent.kill()
            parent.wait(10)
        if child_pid is not None and alive(child_pid):
            os.kill(child_pid, signal.SIGKILL)
