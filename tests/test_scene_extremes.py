"""Nonsense scene parameters are refused with a SceneError that names the field (issue 34, answer 3 and the list of
unclear errors), before any model is built or stepped."""

import math

import msgspec
import pytest

from hydrosoft.scene import SceneError, compile_scene
from hydrosoft.tasks.scenes import task_scene

replace = msgspec.structs.replace


def pushing(**fields):
    return replace(task_scene("pushing"), **fields)


def pushing_object(**fields):
    scene = task_scene("pushing")
    return replace(scene, object=replace(scene.object, **fields))


def in_hand_bubbles(**params):
    scene = task_scene("in_hand")
    return replace(scene, bodies=[replace(b, params=params) if b.sdf == "ellipsoid" else b for b in scene.bodies])


REFUSED = {
    "snh beta nan": (lambda: pushing(contact="snh", contact_params={"beta": math.nan}), "contact_params.beta"),
    "snh beta negative": (lambda: pushing(contact="snh", contact_params={"beta": -1e4}), "contact_params.beta"),
    "snh beta zero": (lambda: pushing(contact="snh", contact_params={"beta": 0.0}), "contact_params.beta"),
    "pf slip_tolerance negative": (lambda: pushing(contact="pf", contact_params={"slip_tolerance": -1.0}),
                                   "contact_params.slip_tolerance"),
    "unknown contact parameter": (lambda: pushing(contact_params={"stiffness": 1.0}), "contact_params.stiffness"),
    "cube side negative": (lambda: pushing_object(params={"side": -0.05}), "object.params: side"),
    "cube side zero": (lambda: pushing_object(params={"side": 0.0}), "object.params: side"),
    "cube side nan": (lambda: pushing_object(params={"side": math.nan}), "object.params: side"),
    "cube side inf": (lambda: pushing_object(params={"side": math.inf}), "object.params: side"),
    "ellipsoid radii of 2": (lambda: in_hand_bubbles(radii=[0.06, 0.045]), "radii"),
    "ellipsoid radii of 4": (lambda: in_hand_bubbles(radii=[0.06, 0.045, 0.03, 0.03]), "radii"),
    "dt overflowing": (lambda: pushing(dt=1e300), "dt"),
    "gravity 1e300": (lambda: pushing(gravity=[0.0, 0.0, -1e300]), "gravity"),
    "max_substeps 1e12": (lambda: pushing(max_substeps=10**12), "max_substeps"),
    "planar without gravity": (lambda: pushing(gravity=[0.0, 0.0, 0.0]), "planar"),
}


@pytest.mark.parametrize("case", sorted(REFUSED))
def test_nonsense_parameters_are_a_scene_error_naming_the_field(case):
    build, field = REFUSED[case]
    with pytest.raises(SceneError, match=field.replace(".", r"\.").replace("[", r"\[")):
        compile_scene(build())


def test_box_sdf_half_extents_of_the_wrong_length_name_the_field():
    scene = task_scene("pushing")
    bodies = [replace(b, sdf="box", params={"half_extents": [0.1, 0.1]}) if b.actuated else b for b in scene.bodies]
    with pytest.raises(SceneError, match="half_extents"):
        compile_scene(replace(scene, bodies=bodies))


def test_a_tiny_spacing_is_refused_with_the_point_count_it_would_make():
    """A 5 cm cube at 10 um spacing would have 1.5e8 points: refused before any is made, naming the count."""
    with pytest.raises(SceneError, match=r"object\.spacing: .*1\.5e\+08 surface points"):
        compile_scene(pushing_object(spacing=1e-5))
