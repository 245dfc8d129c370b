"""The small planner shared by the task tests (single-threaded torch comes from tests/conftest.py)."""

from __future__ import annotations

from hydrosoft.tasks.evaluation import PlannerSettings

QUICK_PLANNER = dict(spacing=0.0125, samples=16, elites=4, horizon=6, grad_steps=1, open_loop_iterations=3)


def quick_planner(model: str = "nh", **overrides) -> PlannerSettings:
    """The small planner of ``bench control --quick``: 96 surface points, B = 16, K = 6, G = 1."""
    return PlannerSettings(model=model, **{**QUICK_PLANNER, **overrides})
