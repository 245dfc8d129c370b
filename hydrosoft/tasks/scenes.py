"""The task scenes shipped with the package (TOML files beside this module)."""

from __future__ import annotations

from importlib import resources

from hydrosoft.scene import Scene, SceneError, parse_scene

TASK_SCENES = ("pushing", "rotation", "rolling", "in_hand")


def task_scene(name: str) -> Scene:
    """The validated scene of a task: one of ``pushing``, ``rotation``, ``rolling``, ``in_hand``."""
    if name not in TASK_SCENES:
        raise SceneError(f"unknown task scene {name!r}; known: {', '.join(TASK_SCENES)}")
    text = resources.files("hydrosoft.tasks").joinpath(f"{name}.toml").read_bytes()
    return parse_scene(text, origin=f"task scene {name}.toml")
