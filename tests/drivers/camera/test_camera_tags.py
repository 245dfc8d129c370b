"""Tag layouts put each tag on its face, facing out, and refuse tags that do not fit."""

import numpy as np
import pytest

from hydrosoft.drivers.poses import quat_to_matrix
from hydrosoft.drivers.camera.tags import Tag, TagLayout, box_layout, cylinder_layout, tag_corners


def test_box_tags_sit_on_their_faces_facing_out():
    size = (0.06, 0.05, 0.04)
    layout = box_layout(size, 0.025, first_id=10, faces=("+x", "-x", "+y", "-y", "+z", "-z"))
    assert layout.ids == (10, 11, 12, 13, 14, 15)
    for tag, normal in zip(layout.tags, np.eye(3).repeat(2, axis=0) * np.tile([1, -1], 3)[:, None]):
        axis = int(np.argmax(np.abs(normal)))
        R = quat_to_matrix(tag.T_object_tag[3:])
        np.testing.assert_allclose(R[:, 2], normal, atol=1e-12)  # tag z out of the face
        np.testing.assert_allclose(tag.T_object_tag[:3], normal * size[axis] / 2, atol=1e-12)
        corners = tag.corners_object
        np.testing.assert_allclose(corners[:, axis], normal[axis] * size[axis] / 2, atol=1e-12)
        assert np.all(np.abs(corners) <= np.array(size) / 2 + 1e-12)
    assert len(layout.faces) == 6
    for face in layout.faces:  # every face's vertex order gives an outward normal
        normal = np.cross(face[1] - face[0], face[2] - face[0])
        assert normal @ face.mean(axis=0) > 0


def test_side_tags_are_upright():
    layout = box_layout((0.05, 0.05, 0.05), 0.03, faces=("+x", "-y"))
    for tag in layout.tags:
        np.testing.assert_allclose(quat_to_matrix(tag.T_object_tag[3:])[:, 1], [0, 0, 1], atol=1e-12)


def test_cylinder_caps():
    layout = cylinder_layout(0.03, 0.08, 0.03, first_id=5)
    top, bottom = layout.tags
    np.testing.assert_allclose(top.T_object_tag[:3], [0, 0, 0.04])
    np.testing.assert_allclose(quat_to_matrix(bottom.T_object_tag[3:])[:, 2], [0, 0, -1], atol=1e-12)
    for face in layout.faces:
        normal = np.cross(face[1] - face[0], face[2] - face[0])
        assert normal @ face.mean(axis=0) > 0


def test_tags_that_do_not_fit_are_refused():
    with pytest.raises(ValueError, match="does not fit on face"):
        box_layout((0.05, 0.05, 0.05), 0.045)  # 0.045 * 10/8 = 0.056 m with its quiet zone
    with pytest.raises(ValueError, match="does not fit in a cap"):
        cylinder_layout(0.02, 0.05, 0.03)
    with pytest.raises(ValueError, match="unknown face"):
        box_layout((0.05, 0.05, 0.05), 0.03, faces=("top",))


def test_layout_checks_ids():
    pose = np.array([0, 0, 0, 1.0, 0, 0, 0])
    with pytest.raises(ValueError, match="unique"):
        TagLayout((Tag(1, 0.03, pose), Tag(1, 0.03, pose)))
    with pytest.raises(ValueError, match="36h11"):
        Tag(587, 0.03, pose)
    assert TagLayout((Tag(3, 0.03, pose),)).tag(4) is None


def test_corner_order_is_the_detectors():
    corners = tag_corners(2.0)  # top-left, top-right, bottom-right, bottom-left as printed (y up)
    np.testing.assert_array_equal(corners[:, :2], [[-1, 1], [1, 1], [1, -1], [-1, -1]])
