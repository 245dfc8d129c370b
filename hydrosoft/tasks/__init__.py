"""Manipulation tasks of paper V-D (scene, actions, goals, costs) and their open/closed-loop evaluation."""

from __future__ import annotations

from hydrosoft.tasks.base import CostWeights, Task
from hydrosoft.tasks.scenes import TASK_SCENES, task_scene

TASKS = TASK_SCENES


def make_task(name: str, steps: int | None = None) -> Task:
    """The task ``name`` (one of ``TASKS``) with its default episode length, or ``steps`` control steps."""
    from importlib import import_module

    if name not in TASKS:
        raise ValueError(f"unknown task {name!r}; known: {', '.join(TASKS)}")
    factory = import_module(f"hydrosoft.tasks.{name}").make_task
    return factory() if steps is None else factory(steps)


__all__ = ["CostWeights", "TASKS", "Task", "make_task", "task_scene"]
