"""The scene edits the stack applies before compiling a task's scene: a body's material replaced by a fitted one."""

from __future__ import annotations

import pytest

from hydrosoft.scene import SceneError, compile_scene
from hydrosoft.tasks.evaluation import with_body_materials
from hydrosoft.tasks.scenes import task_scene


def test_a_bodys_material_is_replaced_in_the_compiled_model_and_bad_names_are_refused():
    scene = task_scene("pushing")
    model, _, _ = compile_scene(with_body_materials(scene, {"bubble": {"E": 5.1e5, "mu": 0.35}}))
    bubble, table = model.body_names.index("bubble"), model.body_names.index("table")
    assert float(model.material.E[bubble]) == 5.1e5 and float(model.material.mu[bubble]) == 0.35
    assert float(model.material.K[bubble]) == 1e5  # not given: the scene's
    assert float(model.material.E[table]) == 1e6 and float(model.material.mu[table]) == 0.3
    assert with_body_materials(scene, {}) == scene
    with pytest.raises(ValueError, match="no body 'left' in the scene"):
        with_body_materials(scene, {"left": {"E": 1e5}})
    with pytest.raises(ValueError, match=r"bodies\[bubble\]: G is not a material value"):
        with_body_materials(scene, {"bubble": {"G": 1e5}})
    with pytest.raises(SceneError, match=r"bodies\[bubble\].K: must be a positive number"):
        with_body_materials(scene, {"bubble": {"K": -1.0}})
