"""Scene loading, validation messages and compilation."""

import msgspec
import pytest
import torch

from hydrosoft.dynamics import substeps_for
from hydrosoft.geometry import se3
from hydrosoft.scene import SceneError, compile_scene, load_scene, parse_scene
from hydrosoft.tasks.scenes import TASK_SCENES, task_scene

MINIMAL = """
contact = "nh"
dt = 0.05
epsilon = 10.0
[object]
shape = "cube"
params = { side = 0.04 }
mass = 0.1
pose = [0.0, 0.0, 0.0195, 1.0, 0.0, 0.0, 0.0]
[[bodies]]
name = "table"
sdf = "halfspace"
E = 1e6
K = 1e5
mu = 0.3
actuated = false
"""


def test_minimal_scene_compiles(tmp_path):
    path = tmp_path / "scene.toml"
    path.write_text(MINIMAL)
    model, state, report = compile_scene(load_scene(path))
    assert model.body_names == ("table",)
    assert state.forces.shape == (1, 1, model.n_points, 3)
    # the press-in state carries the cube's weight share at 0.5 mm depth: E A d = 1e6 * 0.0016 * 5e-4
    assert state.forces[..., 2].sum().item() == pytest.approx(0.8, rel=1e-6)


@pytest.mark.parametrize(
    "edit,message",
    [
        (("mass = 0.1", "mass = -1.0"), "object.mass"),
        (("E = 1e6", 'E = "stiff"'), r"Expected `float`, got `str` - at `\$.bodies\[0\].E`"),
        (("mu = 0.3", "mu = -0.3"), r"bodies\[table\].mu"),
        (('contact = "nh"', 'contact = "magic"'), "known: nh, snh, pf, pff"),
        (('shape = "cube"', 'shape = "donut"'), "unknown shape 'donut'"),
        (("pose = [0.0, 0.0, 0.0195, 1.0, 0.0, 0.0, 0.0]", "pose = [0.0, 0.0, 0.0195, 2.0, 0.0, 0.0, 0.0]"), "not unit"),
        (("pose = [0.0, 0.0, 0.0195, 1.0, 0.0, 0.0, 0.0]", "pose = [0.0, 0.0, nan, 1.0, 0.0, 0.0, 0.0]"), "finite"),
        (("dt = 0.05", "dt = 0.0"), "dt: must be a positive"),
        (("mass = 0.1", "mass = 0.1\ncolour = 'red'"), "unknown field `colour`"),
        (("[object]", "[objet]\n[object]"), "objet"),
    ],
)
def test_invalid_scenes_name_the_field(edit, message):
    with pytest.raises(SceneError, match=message):
        parse_scene(MINIMAL.replace(*edit))


def test_broken_toml_and_missing_file_are_clear(tmp_path):
    with pytest.raises(SceneError, match="not valid TOML"):
        parse_scene("contact = ")
    with pytest.raises(SceneError, match="does not exist"):
        load_scene(tmp_path / "missing.toml")


def test_bad_shape_parameters_are_reported():
    with pytest.raises(SceneError, match="object.params"):
        compile_scene(parse_scene(MINIMAL.replace("side = 0.04", "radius = 0.04")))


def test_no_body_within_reach_is_an_error():
    scene = parse_scene(MINIMAL.replace("pose = [0.0, 0.0, 0.0195,", "pose = [0.0, 0.0, 1.0,"))
    with pytest.raises(SceneError, match="no compliant body can reach"):
        compile_scene(scene)


def test_planar_scene_must_be_upright():
    scene = parse_scene(MINIMAL.replace("pose = [0.0, 0.0, 0.0195, 1.0, 0.0, 0.0, 0.0]",
                                        "pose = [0.0, 0.0, 0.0195, 0.7071067811865476, 0.7071067811865476, 0.0, 0.0]"))
    with pytest.raises(SceneError, match="upright"):
        compile_scene(msgspec.structs.replace(scene, planar=True))


@pytest.mark.parametrize("task", TASK_SCENES)
def test_task_scenes_compile_in_both_precisions(task):
    for dtype in (torch.float32, torch.float64):
        model, state, report = compile_scene(task_scene(task), dtype=dtype)
        assert model.dtype == dtype and state.forces.dtype == dtype
        assert torch.isfinite(state.forces).all()
        assert report.points_kept <= report.points_total


def test_pruning_drops_points_and_bodies_it_reports():
    _, _, report = compile_scene(task_scene("in_hand"))
    _, _, full = compile_scene(task_scene("in_hand"), prune=False)
    assert report.bodies_dropped == ("table",) and full.bodies_dropped == ()
    assert report.points_kept < full.points_kept


def test_a_planar_table_counts_only_its_contact_patch_in_the_stability_bound():
    """The planar cube's side points near the table can never reach it (height held), so their horizontal
    normals must not add the table's E to the bound: counting every point within stability_margin, as for a
    body that moves, would need 3 sub-steps instead of 2 in the rotation scene (5 instead of 3 in pushing)."""
    scene = task_scene("rotation")
    model, state, report = compile_scene(scene, prune=False)
    world = se3.transform_points(state.object_pose[0], model.points)
    within_margin = torch.stack([
        sdf(se3.transform_points(se3.inverse(state.body_poses[0, m]), world)) <= scene.stability_margin
        for m, sdf in enumerate(model.bodies)])
    assert report.substeps == 2
    assert substeps_for(model, 64, within_margin) == 3
