"""The task scenes shipped with the package (TOML files beside this module)."""

from __future__ import annotations

from hydrosoft.scene import Scene, parse_scene
from hydrosoft.scene_spec import TASK_SCENES, task_scene_text

__all__ = ["TASK_SCENES", "task_scene"]


def task_scene(name: str) -> Scene:
    """The validated scene of a task: one of ``pushing``, ``rotation``, ``rolling``, ``in_hand``."""
    return parse_scene(task_scene_text(name), origin=f"task scene {name}.toml")
