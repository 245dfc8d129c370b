"""Test-wide settings.

- torch runs single-threaded: on two shared cores OpenMP worker threads stall each other (a B = 64 step measured
  ~10x slower with 2 threads than with 1 while another process was busy), and the suite's figures stay stable.
- hypothesis runs derandomized under CI so a red build is reproducible.
- the suite runs on two pytest-xdist workers (``-n 2 --dist loadgroup``, the README's command): the tests that
  start the stack's processes or simulated devices (``tests/services``, ``tests/drivers``) form one group that runs
  one test at a time on one worker, beside the model tests on the other, so two stacks never share two cores.
- the other tests are handed out one at a time to whichever worker is free, in collection order, except that the
  modules with a test marked ``slow`` come first: a long test handed out last would leave the other worker idle
  while it runs (the PF rolling finding, 167 s, was among the last).
"""

import os
import shutil
import tempfile
from pathlib import Path

import pytest
import torch
from hypothesis import settings

TESTS = Path(__file__).resolve().parent
PROCESS_DIRS = ("services", "drivers")

settings.register_profile("ci", derandomize=True, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")


def in_process_group(item: pytest.Item) -> bool:
    """Whether ``item`` lies under ``PROCESS_DIRS``."""
    return item.path.resolve().relative_to(TESTS).parts[0] in PROCESS_DIRS


def pytest_collection_modifyitems(config, items):
    """Put the tests under ``PROCESS_DIRS`` into one xdist group, and the other modules with a ``slow`` test
    first, each module's tests together and in their order (module docstring)."""
    slow_modules = set()
    for item in items:
        if in_process_group(item):
            item.add_marker(pytest.mark.xdist_group("processes"))
        elif item.get_closest_marker("slow"):
            slow_modules.add(item.path)
    items.sort(key=lambda item: item.path not in slow_modules)  # stable: the order within each part is kept


@pytest.fixture
def tmp_path():
    """A fresh directory with a short path, /tmp/hst-XXXXXXXX, removed after the test, in place of pytest's own.

    The stack's ipc:// endpoints are Unix sockets in a config's run_dir, whose paths may have at most 107 bytes;
    under pytest-xdist pytest's paths (/tmp/pytest-of-USER/pytest-N/popen-gwK/TEST_NAME0) leave too few of them.
    """
    root = Path(tempfile.mkdtemp(prefix="hst-", dir="/tmp"))
    yield root
    shutil.rmtree(root, ignore_errors=True)


@pytest.fixture(autouse=True)
def one_thread():
    """Run each test with one torch thread and restore the setting after."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture
def fresh_dynamo():
    """Start and end the test with empty dynamo caches and counters (the test counts graphs, or adds many)."""
    torch._dynamo.reset()
    yield
    torch._dynamo.reset()
