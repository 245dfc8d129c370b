"""The paper's qualitative findings (V-D, Table III) on the quick planner (96 points, B = 16, K = 6, G = 1),
goal 0 of each task, a finer NH plant. End-to-end and slow: a few episodes of 20-56 steps each."""

from __future__ import annotations

import pytest
from conftest import quick_planner

from hydrosoft.tasks import make_task
from hydrosoft.tasks.evaluation import prepare, run_episode

pytestmark = pytest.mark.slow


#: control steps of the rolling comparison, of the goal-sized 52: NH is on its way and ahead. Goal 0 after 30 steps
#: (2026-11-28, docs/benchmarks.md, "The test suite"), planner seeds 0 (the test's), 1 and 2: NH at 9.74, 8.03 and
#: 4.57 mm (from 47.0 mm; the bound 0.6 x is 28.2 mm, crossed at step 16), PF at 13.48, 11.51 and 10.26 mm, 3.7, 3.5
#: and 5.7 mm (1.38-2.25 times NH's) behind; seed 0's gap is 4.1 mm at 40 steps (NH 1.42 mm, arrived). PF's solves
#: take 3.5 times NH's.
ROLLING_STEPS = 30


def episode(name: str, model: str, loop: str, steps: int | None = None):
    task = make_task(name)
    return run_episode(prepare(task, quick_planner(model)), task.sample_goal(0), loop, steps)


def test_pff_cannot_move_the_object_in_planar_pushing():
    """No shear in the model: the planner finds no action that helps, the error stays at its start (~78 mm)."""
    result = episode("pushing", "pff", "closed")
    assert result.initial_error_mm > 30
    assert abs(result.error_mm - result.initial_error_mm) < 0.1 * result.initial_error_mm


def test_closed_loop_beats_open_loop_for_nh_pushing():
    closed = episode("pushing", "nh", "closed")
    opened = episode("pushing", "nh", "open")
    assert closed.error_mm < 0.5 * closed.initial_error_mm  # it does push the cube most of the way
    assert closed.error_mm < opened.error_mm


@pytest.mark.parametrize("name", ["rotation", "rolling"])
def test_nh_reaches_lower_closed_loop_error_than_pf(name):
    """NH's closed-loop error ends below 0.6 of its start and below PF's: rotation over its goal-sized episode,
    rolling after ``ROLLING_STEPS`` (30) of its 52 steps, where NH leads PF by 3.5-5.7 mm (1.38-2.25 times), measured
    on goal 0 with planner seeds 0, 1 and 2."""
    steps = ROLLING_STEPS if name == "rolling" else None  # None: the goal-sized episode
    nh = episode(name, "nh", "closed", steps)
    pf = episode(name, "pf", "closed", steps)
    assert nh.error_mm < 0.6 * nh.initial_error_mm
    assert nh.error_mm < pf.error_mm
