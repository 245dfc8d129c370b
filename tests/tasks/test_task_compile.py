"""``PlannerSettings(compile=True)``: the planner steps through one ``CompiledStep`` per setup, evaluates its costs
through compiled cost terms, and plans what the eager planner plans. Traced with dynamo's ``eager`` backend (graph
capture without inductor's C++ compile: a few seconds); ``tests/dynamics/test_fast_path.py`` checks the inductor
kernels against the eager step."""

from __future__ import annotations

import functools

import pytest
import torch
from conftest import quick_planner

from hydrosoft.dynamics import CompiledStep
from hydrosoft.tasks import make_task
from hydrosoft.tasks.evaluation import prepare, run_episode


def test_the_default_planner_steps_eagerly():
    setup = prepare(make_task("pushing"), quick_planner(samples=4, horizon=2))
    assert isinstance(setup.dynamics, functools.partial) and setup.dynamics.args == (setup.planner_model,)


def test_a_compiled_planner_shares_one_compiled_step_and_plans_like_the_eager_one(fresh_dynamo):
    task = make_task("pushing")
    small = dict(samples=4, elites=2, horizon=2)
    setup = prepare(task, quick_planner(compile=True, **small), compile_options={"backend": "eager"})
    assert isinstance(setup.dynamics, CompiledStep) and setup.dynamics.model is setup.planner_model
    compiled = run_episode(setup, task.sample_goal(0), "closed", steps=2)
    eager = run_episode(prepare(task, quick_planner(**small)), task.sample_goal(0), "closed", steps=2)
    assert setup.dynamics.compiled  # no fallback: the grad and no-grad rollouts both traced
    assert setup.cost_terms.stage.compiled and setup.cost_terms.terminal.compiled  # the costs too, as the step
    assert compiled.solves == 2 and compiled.status == eager.status
    assert torch.allclose(compiled.actions, eager.actions, rtol=0, atol=1e-12)
    assert compiled.errors_mm == pytest.approx(eager.errors_mm, abs=1e-9)
