"""The torch-free scene parts: the same object and bodies as the full scene, checked the same way."""

import pytest

from hydrosoft.scene_spec import TASK_SCENES, ObjectSpec, SceneError, task_scene_parts
from hydrosoft.tasks.scenes import task_scene


@pytest.mark.parametrize("task", TASK_SCENES)
def test_task_scene_parts_are_the_full_scenes(task):
    parts, scene = task_scene_parts(task), task_scene(task)
    assert parts.object == scene.object
    assert parts.bodies == scene.bodies


def test_unknown_task_scene_is_named():
    with pytest.raises(SceneError, match="unknown task scene 'stacking'; known: pushing"):
        task_scene_parts("stacking")


def test_object_is_checked_as_in_a_scene():
    with pytest.raises(SceneError, match="object.mass: must be a positive number of kg"):
        ObjectSpec(shape="cube", mass=-1.0)
