"""The command-line body shared by the services: how a service process ends."""

from __future__ import annotations

import subprocess
import sys

EXITS_WITH_BUFFERED_OUTPUT = """
import logging, sys
from hydrosoft.services.bus.service_cli import exit_process
logging.basicConfig(stream=sys.stderr, level="INFO")
logging.getLogger("svc").info("stopped (exit 3)")
print("last line", end="")  # a pipe is block-buffered: only a flush sends it
exit_process(3)
print("never")
"""


def test_exit_process_flushes_the_output_and_exits_with_the_code():
    done = subprocess.run([sys.executable, "-c", EXITS_WITH_BUFFERED_OUTPUT], capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 3, done.stderr
    assert done.stdout == "last line"
    assert "stopped (exit 3)" in done.stderr
