"""The scene the recorder and the live view show (``services/recording/foxglove_scene.py``): numpy geometry, force arrows and the
conversion of each bus message, without sockets. (``tests/test_scene.py`` tests the model library's scenes.)"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from foxglove.messages import Color, CompressedImage, FrameTransforms, RawImage, SceneUpdate

from hydrosoft.drivers.poses import transform_points
from hydrosoft.geometry import se3
from hydrosoft.services.bus import messages as msg
from hydrosoft.services.bus.config import parse_config
from hydrosoft.services.recording.foxglove_scene import (
    PREDICTED_FORCES_TOPIC,
    TRUE_FORCES_TOPIC,
    SceneBuilder,
    SceneError,
    SceneGeometry,
    force_arrows,
    timestamp,
    x_axis_to,
)

POSE = np.array([0.1, -0.05, 0.02, math.cos(0.3), 0.1, 0.0, math.sin(0.3)])
POSE[3:] /= np.linalg.norm(POSE[3:])


def rotate(quaternion: np.ndarray, vector: np.ndarray) -> np.ndarray:
    return transform_points(np.concatenate([[0.0, 0.0, 0.0], quaternion]), vector)


def geometry() -> SceneGeometry:
    return SceneGeometry(bubbles={"bubble": (0.06, 0.045, 0.03)},
                         object_triangles=np.zeros((2, 3, 3)), planner_points=np.eye(3) * 0.01,
                         planner_bodies=("bubble", "table"), static_frames={"tag_camera": ("world", POSE)})


def test_points_move_as_the_model_library_moves_them_and_arrows_point_along_their_force():
    points = np.random.default_rng(0).normal(size=(5, 3))
    expected = se3.transform_points(torch.as_tensor(POSE), torch.as_tensor(points)).numpy()
    np.testing.assert_allclose(transform_points(POSE, points), expected, atol=1e-12)
    directions = np.array([[1.0, 0, 0], [-2.0, 0, 0], [0, 3.0, 0], [0.3, -0.2, 0.9], [0, 0, -1e-3]])
    for quaternion, direction in zip(x_axis_to(directions), directions):
        assert np.isclose(np.linalg.norm(quaternion), 1.0)
        np.testing.assert_allclose(rotate(quaternion, np.array([1.0, 0, 0])), direction / np.linalg.norm(direction),
                                   atol=1e-12)
    forces = np.array([[0.0, 0.0, 2.0], [0.0, 0.005, 0.0], [1.0, 0.0, 0.0]])
    arrows = force_arrows(np.zeros((3, 3)), forces, Color(r=1.0, a=1.0))
    assert len(arrows) == 2  # the 5 mN force is left out


def test_each_message_becomes_its_scene_update():
    builder = SceneBuilder(geometry(), epoch_offset_ns=1_000_000_000)
    assert timestamp(1_500_000_000, 1_000_000_000).sec == 2 and timestamp(1_500_000_000, 0).nsec == 500_000_000
    static = dict(builder.static(0))
    assert isinstance(static["/tf"], FrameTransforms) and set(static) == {"/tf", "/scene/bubbles", "/scene/object"}
    arm = msg.ArmState(arm="bubble", tcp_pose=POSE, tcp_speed=np.zeros(6), running=True, protective_stop=False,
                       emergency_stop=False, servo_active=True, stamp_ns=5)
    assert [t for t, _ in builder.convert("arm_state/bubble", arm)] == ["/tf"]
    forces = msg.EvalContactForces(bodies=("bubble", "table"), points=np.zeros((3, 3)), forces=np.ones((2, 3, 3)))
    assert builder.convert("eval/contact_forces", forces) == []  # no true pose yet: nowhere to draw them
    builder.convert("eval/object_pose", msg.EvalObjectPose(object="object", pose=POSE))
    (topic, update), = builder.convert("eval/contact_forces", forces)
    assert topic == TRUE_FORCES_TOPIC and isinstance(update, SceneUpdate)
    plan = msg.Plan(task="pushing", actions=np.zeros((2, 2, 6)), predicted_object_poses=np.tile(POSE, (2, 1)),
                    predicted_forces=np.ones((2, 3, 3)), cost=0.0, solve_ms=1.0)
    assert [t for t, _ in builder.convert("plan/pushing", plan)] == ["/scene/plan", PREDICTED_FORCES_TOPIC]
    wrong = msg.Plan(task="pushing", actions=np.zeros((2, 2, 6)), predicted_object_poses=np.tile(POSE, (2, 1)),
                     predicted_forces=np.ones((2, 4, 3)), cost=0.0, solve_ms=1.0)
    with pytest.raises(SceneError, match=r"\(M, N\) = \(2, 4\)"):
        builder.convert("plan/pushing", wrong)
    goal = msg.Goal(task="pushing", target_pose=POSE, tolerance_mm=5.0, timeout_s=10.0)
    assert [t for t, _ in builder.convert("reply/status", msg.StatusReply(ok=True, goal=goal))] == ["/scene/goal"]
    assert builder.convert("reply/status", msg.StatusReply(ok=True)) == []
    image = msg.CameraImage.of("tag_camera", np.zeros((4, 6), dtype=np.uint8), hw_stamp_ns=3)
    (topic, compressed), = builder.convert("image/tag_camera", image)
    assert topic == "/image/tag_camera" and isinstance(compressed, CompressedImage)
    assert b"jpeg" in compressed.encode() and b"\xff\xd8" in compressed.encode()  # format, JPEG's start marker
    (topic, raw), = builder.convert("image/tag_camera", image, images={})  # a recorder keeping camera images raw
    assert topic == "/image/tag_camera" and isinstance(raw, RawImage) and b"mono8" in raw.encode()
    depth = msg.DepthFrame(bubble="bubble", depth=np.zeros((4, 6), np.uint16), depth_scale_m=1e-4, fx_px=1.0,
                           fy_px=1.0, cx_px=1.0, cy_px=1.0)
    (topic, compressed), = builder.convert("depth/bubble", depth)
    assert topic == "/depth/bubble" and isinstance(compressed, CompressedImage)
    assert b"png" in compressed.encode() and b"\x89PNG" in compressed.encode()
    deformation = msg.MembraneDeformation(bubble="bubble", deformation=np.ones((4, 6), np.float32),
                                          reference_stamp_ns=1)
    (topic, raw), = builder.convert("deformation/bubble", deformation)
    assert topic == "/deformation/bubble" and isinstance(raw, RawImage) and b"32FC1" in raw.encode()
    assert builder.convert("wrench/bubble", msg.Wrench(sensor="b", wrench=np.zeros(6), tared=True)) == []


def test_the_geometry_of_the_sim_config_is_the_planners_scene():
    config = parse_config('[[arms]]\nname = "bubble"\n[scene]\ntask = "pushing"\n')
    scene = SceneGeometry.from_config(config)
    assert scene.bubbles == {"bubble": (0.06, 0.045, 0.03)}
    assert scene.planner_bodies == ("bubble", "table") and scene.planner_points.shape == (64, 3)
    corners = scene.object_triangles.reshape(-1, 3)
    assert np.all(np.abs(corners) <= 0.025 + 1e-9) and np.abs(corners).max() > 0.02  # the 5 cm cube's hull
    assert set(scene.static_frames) == {"tag_camera", "depth_bubble"}
