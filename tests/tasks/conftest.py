"""Shared fixtures of the task tests: single-threaded torch (2 shared cores) and a small planner."""

from __future__ import annotations

import pytest
import torch

from hydrosoft.tasks.evaluation import PlannerSettings

QUICK_PLANNER = dict(spacing=0.0125, samples=16, elites=4, horizon=6, grad_steps=1, open_loop_iterations=3)


@pytest.fixture(autouse=True)
def one_thread():
    """Run each test single-threaded (OpenMP threads stall on shared cores) and restore the setting after."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def quick_planner(model: str = "nh", **overrides) -> PlannerSettings:
    """The small planner of ``bench control --quick``: 96 surface points, B = 16, K = 6, G = 1."""
    return PlannerSettings(model=model, **{**QUICK_PLANNER, **overrides})
