"""A single integrator x_{k+1} = x_k + u_k towards a goal, as a picklable problem for ``WorkerProcesses``' tests (the
worker processes import this module by name: the tests put its folder on their ``PYTHONPATH``)."""
from __future__ import annotations

import os
import time
from typing import NamedTuple

import torch

from hydrosoft.control import effort_cost


class State(NamedTuple):
    pos: torch.Tensor  # (B, 3) m
    steps: torch.Tensor  # (B,) int64, steps taken: a non-float leaf rides along


def integrator(state: State, u: torch.Tensor) -> State:
    """Single integrator on a (B, 1, 3) action."""
    return State(state.pos + u[:, 0], state.steps + 1)


def build(goal: tuple[float, float, float]):
    """``(dynamics, stage_cost, terminal_cost)`` towards ``goal`` (m); a goal with a NaN raises, as a broken
    problem would."""
    if any(g != g for g in goal):
        raise ValueError(f"goal {goal} is not finite")
    target = torch.tensor(goal, dtype=torch.float64)

    def to_goal(state: State) -> torch.Tensor:
        return (state.pos - target.to(state.pos)).square().sum(-1)

    def stage(states: list[State], u: torch.Tensor) -> torch.Tensor:
        return sum(to_goal(state) for state in states) + 0.01 * effort_cost(u)

    return integrator, stage, to_goal


def no_compiler(graph, example_inputs):
    """A ``torch.compile`` backend that fails, as one without a C++ compiler does."""
    raise RuntimeError("no C++ compiler here")


def build_without_compiler(goal: tuple[float, float, float]):
    """``build`` with its dynamics compiled (``compilation.CompiledFunction``) by a backend that fails: the worker's
    step falls back to eager at its first call."""
    from hydrosoft.compilation import CompiledFunction
    _, stage, to_goal = build(goal)
    return CompiledFunction(integrator, backend=no_compiler), stage, to_goal


def build_compiled(goal: tuple[float, float, float]):
    """``build`` with its dynamics compiled by inductor (``compilation.CompiledFunction``): precompiled, built or
    loaded, when the environment names a precompiled directory (``compilation.use_precompiled``)."""
    from hydrosoft.compilation import CompiledFunction
    _, stage, to_goal = build(goal)
    return CompiledFunction(integrator, options={}), stage, to_goal


SLOW_STEP_S = 0.002
"""How long the slow worker's step sleeps per call (``build_one_slow``)."""


def build_one_slow(problem: tuple[tuple[float, float, float], str | None]):
    """``build(goal)`` for ``problem = (goal, marker)``, in the one worker process that creates the file ``marker``
    first with a step that sleeps ``SLOW_STEP_S`` per call (a worker the machine delays); the others, and all of
    them when ``marker`` is None, as ``build``."""
    goal, marker = problem
    dynamics, stage, to_goal = build(goal)
    if marker is None:
        return dynamics, stage, to_goal
    try:
        os.close(os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
    except FileExistsError:
        return dynamics, stage, to_goal

    def slow(state: State, u: torch.Tensor) -> State:
        time.sleep(SLOW_STEP_S)
        return dynamics(state, u)

    return slow, stage, to_goal
