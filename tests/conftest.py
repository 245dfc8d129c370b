"""Test-wide settings.

- torch runs single-threaded: on two shared cores OpenMP worker threads stall each other (a B = 64 step measured
  ~10x slower with 2 threads than with 1 while another process was busy), and the suite's figures stay stable.
- hypothesis runs derandomized under CI so a red build is reproducible.
"""

import os

import pytest
import torch
from hypothesis import settings

settings.register_profile("ci", derandomize=True, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")


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
