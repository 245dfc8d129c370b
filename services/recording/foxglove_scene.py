"""What a person wants to see of the stack, in Foxglove's well-known schemas: pure conversions of bus messages.

Frames (``FrameTransforms`` on ``/tf``): ``world`` is the robot base frame; each arm's TCP frame is named as the arm
(the bubble's frame: ``ArmState.tcp_pose``); ``object`` is the tracked object (``ObjectPose``), ``object_true`` the
simulated truth (``eval/object_pose``); ``tag_camera`` (``camera.pose``) and ``depth_ARM`` (the bubble's depth
camera, ``DepthConfig.camera_in_bubble``) are static.

Scene channels (``SceneUpdate``): ``/scene/bubbles`` (each bubble's membrane as its ellipsoid, in its arm's frame),
``/scene/object`` (the object's convex hull in ``object`` and, translucent, in ``object_true``), ``/scene/goal``
(the hull at the goal pose of the planner's running or last goal, from its ``StatusReply``), ``/scene/plan`` (the
plan's predicted object path), ``/scene/forces/predicted`` (the plan's per-point forces after its first step, at
the planner's surface points on the predicted object pose) and ``/scene/forces/true`` (sim only: the plant's
per-point forces at its own points on the true pose). A force is an arrow from its point along the force,
``FORCE_ARROW_M_PER_N`` long per newton; forces under ``MIN_ARROW_FORCE_N`` are left out.

Images: ``/image/CAMERA`` (``CompressedImage``, the JPEG the recording stores, or ``RawImage`` ``bgr8`` or
``mono8`` where it keeps camera images raw), ``/depth/ARM``
(``CompressedImage``, a 16-bit PNG of the counts of ``depth_scale_m``), ``/deformation/ARM`` (``RawImage``
``32FC1``, m, NaN = no return). Each image is the same bytes as the raw channel's, so the file's compression stores
it once (``mcap_format``).

Every stamp is ``stamp_ns`` (or the hardware stamp of an image) plus the recording's epoch offset (see
``mcap_format``). ``SceneGeometry.from_config`` compiles the task scene as the planner does (it imports torch);
everything else is numpy.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from foxglove.messages import (
    ArrowPrimitive,
    Color,
    CompressedImage,
    FrameTransform,
    FrameTransforms,
    LinePrimitive,
    LinePrimitiveLineType,
    Point3,
    Pose,
    Quaternion,
    RawImage,
    SceneEntity,
    SceneUpdate,
    SpherePrimitive,
    Timestamp,
    TriangleListPrimitive,
    Vector3,
)

from hydrosoft.drivers.poses import transform_points
from hydrosoft.services.bus import messages as msg
from hydrosoft.services.bus.config import StackConfig
from hydrosoft.services.recording.image_codec import EncodedImage
from hydrosoft.services.recording.mcap_format import JPEG, RawFormat, encoded_images

WORLD = "world"
OBJECT_FRAME = "object"
TRUE_OBJECT_FRAME = "object_true"
CAMERA_FRAME = "tag_camera"
TF_TOPIC = "/tf"
BUBBLES_TOPIC = "/scene/bubbles"
OBJECT_TOPIC = "/scene/object"
GOAL_TOPIC = "/scene/goal"
PLAN_TOPIC = "/scene/plan"
PREDICTED_FORCES_TOPIC = "/scene/forces/predicted"
TRUE_FORCES_TOPIC = "/scene/forces/true"
#: Length of a force arrow per newton of force, m/N (a 1 N contact force is drawn 2 cm long).
FORCE_ARROW_M_PER_N = 0.02
#: Forces weaker than this are not drawn, N.
MIN_ARROW_FORCE_N = 0.01
#: Spacing of the surface points whose convex hull draws the object, m.
HULL_SPACING_M = 0.005

_BUBBLE_COLOR = Color(r=0.3, g=0.6, b=1.0, a=0.35)
_OBJECT_COLOR = Color(r=0.9, g=0.6, b=0.2, a=1.0)
_TRUE_OBJECT_COLOR = Color(r=0.6, g=0.6, b=0.6, a=0.3)
_GOAL_COLOR = Color(r=0.2, g=0.9, b=0.3, a=0.35)
_PLAN_COLOR = Color(r=0.9, g=0.2, b=0.9, a=1.0)
_FORCE_COLORS = (Color(r=1.0, g=0.2, b=0.2, a=1.0), Color(r=0.2, g=0.4, b=1.0, a=1.0),
                 Color(r=1.0, g=0.8, b=0.1, a=1.0), Color(r=0.1, g=0.8, b=0.8, a=1.0))

class SceneError(ValueError):
    """A message that does not fit the scene's geometry (a plan for another scene); the text says why."""


SceneOutput = tuple[str, object]
"""A scene channel's topic and the Foxglove message to log on it."""


@dataclass(frozen=True)
class SceneGeometry:
    """The shapes the scene draws, from the stack's config.

    bubbles: per arm, the membrane ellipsoid's semi-axes ``(a, b, c)`` (m) in the arm's TCP frame.
    object_triangles: ``(T, 3, 3)`` the object's convex hull, object frame (m).
    planner_points: ``(N, 3)`` the planner's object surface points (m, object frame): the N of
    ``Plan.predicted_forces``.
    planner_bodies: the planner model's body names, the M of ``Plan.predicted_forces``.
    static_frames: per static frame, its parent frame and its pose ``(7,)`` there (m, wxyz).
    """

    bubbles: Mapping[str, tuple[float, float, float]]
    object_triangles: np.ndarray
    planner_points: np.ndarray
    planner_bodies: tuple[str, ...]
    static_frames: Mapping[str, tuple[str, np.ndarray]]

    @classmethod
    def from_config(cls, config: StackConfig) -> SceneGeometry:
        """Compile ``config``'s task scene at the planner's spacing and contact model, as the planner does (imports
        torch; about a second)."""
        import msgspec
        import trimesh

        from hydrosoft.scene import build_surface, compile_scene
        from hydrosoft.tasks import make_task
        from hydrosoft.tasks.evaluation import with_contact

        task = make_task(config.scene.task)
        model, _, _ = compile_scene(with_contact(task.scene, config.planner.model, config.planner.spacing))
        bubbles = {arm.name: tuple(float(r) for r in model.bodies[model.body_names.index(arm.name)].radii)
                   for arm in config.arms if arm.name in model.body_names}
        hull_points = build_surface(msgspec.structs.replace(task.scene.object, spacing=HULL_SPACING_M)).points
        hull = trimesh.convex.convex_hull(hull_points.numpy())
        frames = {CAMERA_FRAME: (WORLD, np.asarray(config.camera.pose, dtype=np.float64))}
        for arm in config.arms:
            frames[depth_frame(arm.name)] = (arm.name, np.asarray(arm.depth.camera_in_bubble(), dtype=np.float64))
        return cls(bubbles=bubbles, object_triangles=np.asarray(hull.triangles, dtype=np.float64),
                   planner_points=model.points.double().numpy(), planner_bodies=tuple(model.body_names),
                   static_frames=frames)


def depth_frame(arm: str) -> str:
    """The frame of arm ``arm``'s depth camera."""
    return f"depth_{arm}"


def scene_topics(config: StackConfig, raw_format: RawFormat = RawFormat()) -> dict[str, type]:
    """Every scene channel of ``config``'s stack and the Foxglove message type it carries (camera images as
    ``raw_format`` stores them)."""
    topics: dict[str, type] = {TF_TOPIC: FrameTransforms}
    topics |= dict.fromkeys((BUBBLES_TOPIC, OBJECT_TOPIC, GOAL_TOPIC, PLAN_TOPIC, PREDICTED_FORCES_TOPIC,
                             TRUE_FORCES_TOPIC), SceneUpdate)
    camera_type = CompressedImage if raw_format.camera_format == JPEG else RawImage
    topics[f"/{msg.topic_for(msg.CameraImage, CAMERA_FRAME)}"] = camera_type
    for arm in config.arms:
        topics[f"/{msg.topic_for(msg.DepthFrame, arm.name)}"] = CompressedImage
        topics[f"/{msg.topic_for(msg.MembraneDeformation, arm.name)}"] = RawImage
    return topics


# --- numpy geometry ----------------------------------------------------------------------------------------------


def x_axis_to(directions: np.ndarray) -> np.ndarray:
    """Unit quaternions ``(K, 4)`` ``[w, x, y, z]`` turning the x axis onto each of the directions ``(K, 3)`` (any
    length > 0): the shortest rotation, and a half turn about z for a direction along -x."""
    d = np.asarray(directions, dtype=np.float64)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    q = np.stack([1.0 + d[:, 0], np.zeros(len(d)), -d[:, 2], d[:, 1]], axis=-1)
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    opposite = norm[:, 0] < 1e-9
    q[opposite] = (0.0, 0.0, 0.0, 1.0)
    norm[opposite] = 1.0
    return q / norm


# --- Foxglove values ---------------------------------------------------------------------------------------------


def timestamp(stamp_ns: int, epoch_offset_ns: int) -> Timestamp:
    """The Foxglove timestamp of a monotonic ``stamp_ns`` on the recording's clock."""
    sec, nsec = divmod(stamp_ns + epoch_offset_ns, 1_000_000_000)
    return Timestamp(sec, nsec)


def _translation_rotation(pose: np.ndarray) -> tuple[Vector3, Quaternion]:
    x, y, z, qw, qx, qy, qz = (float(v) for v in pose)
    return Vector3(x=x, y=y, z=z), Quaternion(x=qx, y=qy, z=qz, w=qw)


def pose_of(pose: np.ndarray) -> Pose:
    """A Foxglove pose of ``pose (7,)`` ``[x, y, z, qw, qx, qy, qz]``."""
    translation, rotation = _translation_rotation(pose)
    return Pose(position=translation, orientation=rotation)


def transform(parent: str, child: str, pose: np.ndarray, stamp: Timestamp) -> FrameTransform:
    """The transform placing ``child`` at ``pose (7,)`` in ``parent``."""
    translation, rotation = _translation_rotation(pose)
    return FrameTransform(timestamp=stamp, parent_frame_id=parent, child_frame_id=child, translation=translation,
                          rotation=rotation)


_IDENTITY = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])


def hull_entity(entity_id: str, frame: str, triangles: np.ndarray, color: Color, stamp: Timestamp,
                pose: np.ndarray = _IDENTITY) -> SceneEntity:
    """A triangle-list entity of ``triangles (T, 3, 3)`` placed at ``pose (7,)`` in ``frame``, following it."""
    points = [Point3(x=float(x), y=float(y), z=float(z)) for x, y, z in triangles.reshape(-1, 3)]
    return SceneEntity(timestamp=stamp, frame_id=frame, id=entity_id, frame_locked=True,
                       triangles=[TriangleListPrimitive(pose=pose_of(pose), points=points, color=color)])


def force_arrows(points: np.ndarray, forces: np.ndarray, color: Color) -> list[ArrowPrimitive]:
    """Arrows of the forces ``(N, 3)`` (N, world frame) applied at ``points (N, 3)`` (m, world frame): from each
    point along its force, ``FORCE_ARROW_M_PER_N`` per newton; forces weaker than ``MIN_ARROW_FORCE_N`` left
    out."""
    magnitude = np.linalg.norm(forces, axis=-1)
    keep = np.flatnonzero(magnitude >= MIN_ARROW_FORCE_N)
    if not keep.size:
        return []
    rotations = x_axis_to(forces[keep])
    arrows = []
    for index, (w, x, y, z) in zip(keep, rotations):
        length_m = float(magnitude[index]) * FORCE_ARROW_M_PER_N
        px, py, pz = (float(v) for v in points[index])
        arrows.append(ArrowPrimitive(
            pose=Pose(position=Vector3(x=px, y=py, z=pz), orientation=Quaternion(x=x, y=y, z=z, w=w)),
            shaft_length=0.7 * length_m, shaft_diameter=0.0015, head_length=0.3 * length_m, head_diameter=0.004,
            color=color))
    return arrows


def forces_update(bodies: tuple[str, ...], points_world: np.ndarray, forces: np.ndarray, stamp: Timestamp,
                  prefix: str) -> SceneUpdate:
    """One entity ``PREFIX/BODY`` per body with its force arrows (``forces (M, N, 3)`` at ``points_world
    (N, 3)``, world frame); a body without forces gets an empty entity, which clears its old arrows."""
    entities = []
    for index, body in enumerate(bodies):
        arrows = force_arrows(points_world, np.asarray(forces[index], dtype=np.float64),
                              _FORCE_COLORS[index % len(_FORCE_COLORS)])
        entities.append(SceneEntity(timestamp=stamp, frame_id=WORLD, id=f"{prefix}/{body}", arrows=arrows))
    return SceneUpdate(entities=entities)


def raw_image(image: np.ndarray, encoding: str, frame: str, stamp: Timestamp) -> RawImage:
    """A Foxglove raw image of ``image (H, W[, C])`` (C-ordered) in ``encoding`` (``bgr8``, ``mono8``, ``32FC1``)."""
    array = np.ascontiguousarray(image)
    height, width = array.shape[:2]
    return RawImage(timestamp=stamp, frame_id=frame, width=width, height=height, encoding=encoding,
                    step=array.strides[0], data=array.tobytes())


def compressed_image(image: EncodedImage, frame: str, stamp: Timestamp) -> CompressedImage:
    """A Foxglove compressed image of the PNG or JPEG ``image``."""
    return CompressedImage(timestamp=stamp, frame_id=frame, data=image.data, format=image.format)


# --- the builder -------------------------------------------------------------------------------------------------


class SceneBuilder:
    """Turns bus messages into scene messages (see the module docstring). It keeps the newest true object pose,
    which places the true contact forces; everything else is converted message by message.

    Args:
        geometry: the shapes to draw.
        epoch_offset_ns: added to monotonic stamps (see ``mcap_format``).
    """

    def __init__(self, geometry: SceneGeometry, epoch_offset_ns: int) -> None:
        self.geometry = geometry
        self.epoch_offset_ns = epoch_offset_ns
        self._true_pose: np.ndarray | None = None

    def static(self, now_ns: int) -> list[SceneOutput]:
        """What does not change: the static frames, the bubbles' ellipsoids and the object's hull in its frames
        (log it once a second, so a viewer that joins late gets it)."""
        stamp = timestamp(now_ns, self.epoch_offset_ns)
        frames = FrameTransforms(transforms=[transform(parent, child, pose, stamp)
                                             for child, (parent, pose) in self.geometry.static_frames.items()])
        bubbles = [SceneEntity(timestamp=stamp, frame_id=arm, id=f"bubble/{arm}", frame_locked=True,
                               spheres=[SpherePrimitive(pose=pose_of(_IDENTITY), color=_BUBBLE_COLOR,
                                                        size=Vector3(x=2 * a, y=2 * b, z=2 * c))])
                   for arm, (a, b, c) in self.geometry.bubbles.items()]
        objects = [hull_entity("object", OBJECT_FRAME, self.geometry.object_triangles, _OBJECT_COLOR, stamp),
                   hull_entity("object_true", TRUE_OBJECT_FRAME, self.geometry.object_triangles, _TRUE_OBJECT_COLOR,
                               stamp)]
        return [(TF_TOPIC, frames), (BUBBLES_TOPIC, SceneUpdate(entities=bubbles)),
                (OBJECT_TOPIC, SceneUpdate(entities=objects))]

    def convert(self, topic: str, message: msg.Message,
                images: dict[str, EncodedImage] | None = None) -> list[SceneOutput]:
        """The scene messages of one bus message (none for the kinds the scene does not show). ``images``: its
        compressed image fields as the recording stores them (default: ``recording.encoded_images``)."""
        stamp = timestamp(message.stamp_ns, self.epoch_offset_ns)
        match message:
            case msg.ArmState():
                return [(TF_TOPIC, FrameTransforms(transforms=[transform(WORLD, message.arm, message.tcp_pose,
                                                                         stamp)]))]
            case msg.ObjectPose():
                return [(TF_TOPIC, FrameTransforms(transforms=[transform(WORLD, OBJECT_FRAME, message.pose, stamp)]))]
            case msg.EvalObjectPose():
                self._true_pose = np.asarray(message.pose, dtype=np.float64)
                return [(TF_TOPIC, FrameTransforms(transforms=[transform(WORLD, TRUE_OBJECT_FRAME, message.pose,
                                                                         stamp)]))]
            case msg.EvalContactForces():
                if self._true_pose is None:
                    return []
                points = transform_points(self._true_pose, message.points)
                return [(TRUE_FORCES_TOPIC, forces_update(message.bodies, points, message.forces, stamp, "true"))]
            case msg.Plan():
                return self._plan(message, stamp)
            case msg.StatusReply() if message.goal is not None and message.goal.target_pose is not None:
                goal = hull_entity("goal", WORLD, self.geometry.object_triangles, _GOAL_COLOR, stamp,
                                   pose=message.goal.target_pose)
                return [(GOAL_TOPIC, SceneUpdate(entities=[goal]))]
            case msg.CameraImage():
                image = (encoded_images(message) if images is None else images).get("image")
                image_stamp = timestamp(message.hw_stamp_ns or message.stamp_ns, self.epoch_offset_ns)
                if image is None:  # kept raw
                    encoding = "bgr8" if message.image.shape[2] == 3 else "mono8"
                    return [(f"/{topic}", raw_image(message.image, encoding, message.camera, image_stamp))]
                return [(f"/{topic}", compressed_image(image, message.camera, image_stamp))]
            case msg.DepthFrame():
                image = (encoded_images(message) if images is None else images)["depth"]
                return [(f"/{topic}", compressed_image(image, depth_frame(message.bubble), stamp))]
            case msg.MembraneDeformation():
                return [(f"/{topic}", raw_image(message.deformation, "32FC1", depth_frame(message.bubble), stamp))]
        return []

    def _plan(self, plan: msg.Plan, stamp: Timestamp) -> list[SceneOutput]:
        poses = np.asarray(plan.predicted_object_poses, dtype=np.float64)
        path = [Point3(x=float(x), y=float(y), z=float(z)) for x, y, z in poses[:, :3]]
        line = LinePrimitive(type=LinePrimitiveLineType.LineStrip, pose=pose_of(_IDENTITY), thickness=0.002,
                             scale_invariant=False, points=path, color=_PLAN_COLOR)
        outputs: list[SceneOutput] = [
            (PLAN_TOPIC, SceneUpdate(entities=[SceneEntity(timestamp=stamp, frame_id=WORLD, id="plan", lines=[line])]))]
        forces = np.asarray(plan.predicted_forces, dtype=np.float64)
        expected = (len(self.geometry.planner_bodies), len(self.geometry.planner_points))
        if forces.shape[:2] != expected:
            raise SceneError(f"{plan.topic} forces are for (M, N) = {forces.shape[:2]} bodies and points, the "
                             f"planner's scene has {expected}: is the recorder's config the planner's?")
        points = transform_points(poses[0], self.geometry.planner_points)
        outputs.append((PREDICTED_FORCES_TOPIC, forces_update(self.geometry.planner_bodies, points, forces, stamp,
                                                              "predicted")))
        return outputs
