"""The paper's qualitative findings (V-D, Table III) on the quick planner (96 points, B = 16, K = 6, G = 1),
goal 0 of each task, a finer NH plant. End-to-end and slow: a few episodes of 24-56 steps each."""

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
#: take 3.5 times NH's. Not shorter: the gap grows with every step, so a shorter cut checks the finding with less
#: margin (same seeds: 2.1-4.0 mm, 1.12-1.33 times, after 24 steps; 1.3-2.8 mm, 1.06-1.16 times, after 20) for at
#: most a fifth of the test's time (2026-11-28, suite10).
ROLLING_STEPS = 30

#: control steps of the rotation comparison, of the goal-sized 30: both have turned the cube most of the way, and
#: PF's correction overshoots where NH's does not. Goal 0 after 24 steps (2026-11-28, docs/benchmarks.md, "The test
#: suite"), planner seeds 0 (the test's), 1 and 2: NH at 0.04, 0.28 and 0.03 mm (from 19.12 mm), PF at 1.02, 0.79
#: and 0.74 mm, 0.98, 0.51 and 0.71 mm behind (2.8-25 times NH's). After all 30 steps the gap had shrunk to 0.08,
#: 0.11 and 0.00 mm (seed 2: both 0.22 mm), so the cut checks the finding with a wider margin, for 6 steps fewer.
ROTATION_STEPS = 24

#: control steps of the pushing comparison, of the goal-sized 56: the closed loop has pushed the cube most of the way,
#: the open loop's plan has fallen far behind. Goal 0 after 40 steps (2026-11-28, docs/benchmarks.md, "The test
#: suite"), planner seeds 0 (the test's), 1 and 2: closed loop at 15.65, 16.79 and 14.05 mm (from 78.5 mm; the bound
#: 0.5 x is 39.25 mm, crossed at step 28-30), open loop at 43.89, 46.12 and 45.26 mm,
#: 28.2-31.2 mm behind (seed 0 after all 56 steps: closed 3.77, open 34.22 mm, 30.5 mm behind).
PUSHING_STEPS = 40

#: control steps of the frictionless (PFF) pushing check, of the goal-sized 56. Goal 0, planner seed 0 (2026-11-28,
#: docs/benchmarks.md, "The test suite"): PFF stays within 78.5-78.7 mm of its 78.5 mm start for 16 steps (77.9 mm
#: after all 56), where NH, which has shear, has pushed the cube 20.5 mm closer (10.6 mm by step 10): a model that
#: could push fails the 10 % bound well before this cut.
PFF_STEPS = 16


def episode(name: str, model: str, loop: str, steps: int | None = None):
    task = make_task(name)
    return run_episode(prepare(task, quick_planner(model)), task.sample_goal(0), loop, steps)


def test_pff_cannot_move_the_object_in_planar_pushing():
    """No shear in the model: the planner finds no action that helps, the error stays at its start (~78 mm) for
    ``PFF_STEPS`` (16) steps, in which NH's closed loop gets 20.5 mm closer."""
    result = episode("pushing", "pff", "closed", PFF_STEPS)
    assert result.initial_error_mm > 30
    assert abs(result.error_mm - result.initial_error_mm) < 0.1 * result.initial_error_mm


def test_closed_loop_beats_open_loop_for_nh_pushing():
    """After ``PUSHING_STEPS`` (40) of the goal-sized 56, NH's closed loop has pushed the cube more than half way and
    is ahead of its open loop, by 28.2-31.2 mm on goal 0 with planner seeds 0, 1 and 2."""
    closed = episode("pushing", "nh", "closed", PUSHING_STEPS)
    opened = episode("pushing", "nh", "open", PUSHING_STEPS)
    assert closed.error_mm < 0.5 * closed.initial_error_mm  # it does push the cube most of the way
    assert closed.error_mm < opened.error_mm


@pytest.mark.parametrize("name", ["rotation", "rolling"])
def test_nh_reaches_lower_closed_loop_error_than_pf(name):
    """NH's closed-loop error ends below 0.6 of its start and below PF's: rotation after ``ROTATION_STEPS`` (24) of
    its 30 steps, where NH leads PF by 0.51-0.98 mm (2.8-25 times), rolling after ``ROLLING_STEPS`` (30) of its 52
    steps, where NH leads PF by 3.5-5.7 mm (1.38-2.25 times), each measured on goal 0 with planner seeds 0, 1 and 2."""
    steps = {"rotation": ROTATION_STEPS, "rolling": ROLLING_STEPS}[name]
    nh = episode(name, "nh", "closed", steps)
    pf = episode(name, "pf", "closed", steps)
    assert nh.error_mm < 0.6 * nh.initial_error_mm
    assert nh.error_mm < pf.error_mm
