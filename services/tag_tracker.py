"""The tag tracker service: the object's pose in the robot base frame from the AprilTags in the tag camera's images.

Camera: in sim mode ``sim.devices.BusCamera`` on sim_world's ``image/tag_camera``; in the lab ``OpenCVCamera`` on
``camera.device``. Calibration (``camera_calibration``): the ``camera.calibration`` file when set (intrinsics and
``T_base_camera``), otherwise the numbers of ``[camera]`` (``pose`` = ``T_base_camera``).

For each image, ``TagTracker.track`` runs ``tag_detection``: ``RegionOfInterest.detect`` (``detect_tags`` around
where the object's tags were last seen, the whole image every ``FULL_FRAME_PERIOD_S`` or when that finds fewer of
them), ``solve_tag`` per tag and ``object_pose_from_tags`` with the object's layout (``object_layout``: the one
sim_world renders, so sim and tracker agree on where every tag sits) and those solutions. The service publishes,
stamped ``hw_stamp_ns`` = the image's exposure stamp:

- ``tags/tag_camera`` (``TagDetections``) for every image: the tags found whose own pose was accepted (tags of other
  objects away from the object only in whole-image searches, at least every ``FULL_FRAME_PERIOD_S``);
- ``object_pose/object`` (``ObjectPose``) only when the object's pose was accepted; a rejection is counted in the
  service's errors under ``rejection_kind(reason)`` with the reason as its text.

The service is ``ready`` while it produces poses. When every image for ``BLIND_AFTER_S`` gave no pose (rejected or
not an image), or the camera fails, it reports ``degraded``; the status note says why (``PoseWatch``), e.g. that
every tag is seen at a grazing angle. The first accepted pose makes it ``ready`` again.

The pure parts (``object_layout``, ``camera_calibration``, ``TagTracker``, ``PoseWatch``, ``full_frame_every``,
``detections_message``, ``pose_message``, ``pose_quality``, ``rejection_kind``) are tested without sockets; ``serve``
is the thin loop.
"""

from __future__ import annotations

import argparse
import asyncio
import math
import time
from dataclasses import dataclass, field

import cv2
import msgspec
import numpy as np

from hydrosoft.drivers.base import Camera
from hydrosoft.drivers.camera.config import CameraCalibration, CameraIntrinsics, load_calibration
from hydrosoft.drivers.camera.tags import (
    BOX_FACE_NORMALS,
    MARKER_CELLS,
    QUIET_ZONE_CELLS,
    Tag,
    TagLayout,
    box_layout,
    cylinder_layout,
)
from hydrosoft.drivers.errors import DriverError
from hydrosoft.drivers.poses import check_pose, compose, inverse
from hydrosoft.scene_spec import ObjectSpec, task_scene_parts
from hydrosoft.services.bus import messages as msg
from hydrosoft.services.bus import service_cli
from hydrosoft.services.bus.config import ConfigError, StackConfig
from hydrosoft.services.bus.runtime import Service
from hydrosoft.services.sim.devices import BusCamera, image_topic
from hydrosoft.services.tag_detection import (
    MAX_REPROJECTION_RMS_PX,
    ObjectPose,
    RegionOfInterest,
    Rejection,
    TagDetection,
    TagPose,
    make_detector,
    object_pose_from_tags,
    reject_ambiguous,
    solve_tag,
)

SERVICE = "tag_tracker"
TAG_CAMERA = "tag_camera"  # the camera's name: CameraImage.camera and the instance of image/, tags/ topics
OBJECT = "object"  # the tracked object's name: ObjectPose.object, EvalObjectPose.object, topic object_pose/object
BOX_TAG_FACES = ("+z", "+x", "-x", "+y", "-y")  # tag id = index here; the bottom rests on the table, untagged
CYLINDER_TAG_CAPS = ("+z", "-z")  # tag id = index here
TAG_SIZE_STEP_M = 0.0005  # a tag shrunk to fit a cylinder's cap is rounded down to this (printable) step
STALE_FRAME_PERIODS = 5.0  # the bus camera raises Stale after this many frame periods without a new image
CAMERA_RETRY_S = 0.1  # pause after a camera error, so a camera that fails at once is not polled in a tight loop
# The whole image is searched for tags at least this often (s): a tag coming into view away from the object's last
# tags is found within it. In between only a crop around them is (deploy/sim.toml: the detector's 1.7 ms -> 0.5 ms).
FULL_FRAME_PERIOD_S = 1.0
# Every image for this long (s) without a pose: the service reports degraded. Longer than a brief loss of the tags
# (a hand or the arm passing in front of them), shorter than a user's wait for a goal to start.
BLIND_AFTER_S = 2.0

_REJECTION_KINDS = (  # prefix of a tag_detection.Rejection reason -> short error kind
    ("no tag of the object seen", "no_object_tag"),
    ("no usable tag", "no_usable_tag"),
    ("ambiguous", "ambiguous_pose"),
    ("joint fit failed", "fit_failed"),
    ("tag ", "inconsistent_tag"),
)


# --- the object and the camera ----------------------------------------------------------------------------------


def object_layout(spec: ObjectSpec, tag_size_m: float, T_base_camera: np.ndarray) -> TagLayout:
    """The tags on the task's object, as sim_world renders them and the tracker expects them.

    A box (``cube`` side, ``plate`` length/width/thickness) carries one tag centred on each face of
    ``BOX_TAG_FACES`` that faces the camera (its outward normal points to the camera's side of the face's plane at
    the object's scene pose ``spec.pose``) and holds the tag with its quiet zone; a cylinder (``radius``,
    ``length``, axis along object z) one on each end cap that faces the camera (both when neither does). Tag ids are
    fixed per face (its index in ``BOX_TAG_FACES`` or ``CYLINDER_TAG_CAPS``), whatever the camera sees, so that
    printed tags never change id. A cylinder's tags shrink to the largest size that fits its caps (rounded down to
    ``TAG_SIZE_STEP_M``) when ``tag_size_m`` does not.

    Args:
        spec: the scene's object (``hydrosoft.scene.ObjectSpec``): shape, params (m) and pose (base frame).
        tag_size_m: black-square edge of each tag (m). T_base_camera: ``(7,)`` the camera's pose (m, wxyz).

    Raises:
        ValueError: for a shape with no tag layout, or a box none of whose camera-facing faces holds a tag.
    """
    camera_in_object = _camera_in_object(spec, T_base_camera)
    if spec.shape in ("cube", "plate"):
        return _box_tags(_box_size(spec), tag_size_m, camera_in_object)
    if spec.shape == "cylinder":
        return _cylinder_tags(float(spec.params["radius"]), float(spec.params["length"]), tag_size_m,
                              camera_in_object)
    raise ValueError(f"no AprilTag layout for a {spec.shape!r} object: the tag tracker knows cubes, plates and "
                     "cylinders")


def largest_cap_tag_m(radius_m: float) -> float:
    """The largest tag edge (m) whose square with its quiet zone fits in a cap of ``radius_m`` (m), rounded down to
    ``TAG_SIZE_STEP_M``."""
    largest = radius_m * math.sqrt(2.0) * MARKER_CELLS / (MARKER_CELLS + 2 * QUIET_ZONE_CELLS)
    return math.floor(largest / TAG_SIZE_STEP_M + 1e-9) * TAG_SIZE_STEP_M


def _box_size(spec: ObjectSpec) -> tuple[float, float, float]:
    if spec.shape == "cube":
        return (float(spec.params.get("side", 0.05)),) * 3
    p = spec.params
    return float(p.get("length", 0.10)), float(p.get("width", 0.10)), float(p.get("thickness", 0.005))


def _camera_in_object(spec: ObjectSpec, T_base_camera: np.ndarray) -> np.ndarray:
    """The camera's position ``(3,)`` (m) in the object frame at the object's scene pose."""
    T_object_camera = compose(inverse(check_pose(np.asarray(spec.pose), "object pose")),
                              check_pose(T_base_camera, "T_base_camera"))
    return T_object_camera[:3]


def _faces_point(normal: np.ndarray, centre: np.ndarray, point: np.ndarray) -> bool:
    return float(normal @ (point - centre)) > 0.0


def _box_tags(size_m: tuple[float, float, float], tag_size_m: float, camera: np.ndarray) -> TagLayout:
    half = np.asarray(size_m) / 2.0
    tags: list[Tag] = []
    faces: tuple[np.ndarray, ...] = ()
    for tag_id, face in enumerate(BOX_TAG_FACES):
        normal = np.asarray(BOX_FACE_NORMALS[face], dtype=np.float64)
        if not _faces_point(normal, normal * half, camera):
            continue
        try:
            one = box_layout(size_m, tag_size_m, first_id=tag_id, faces=(face,))
        except ValueError:  # the face is too small for the tag (a plate's rim)
            continue
        tags += one.tags
        faces = one.faces
    if not tags:
        raise ValueError(f"no face of the {size_m} m box facing the camera holds a {tag_size_m} m tag")
    return TagLayout(tuple(tags), faces)


def _cylinder_tags(radius_m: float, length_m: float, tag_size_m: float, camera: np.ndarray) -> TagLayout:
    tag_size_m = min(tag_size_m, largest_cap_tag_m(radius_m))
    facing = [cap for cap in CYLINDER_TAG_CAPS
              if _faces_point(np.asarray(BOX_FACE_NORMALS[cap], dtype=np.float64),
                              np.asarray(BOX_FACE_NORMALS[cap], dtype=np.float64) * length_m / 2, camera)]
    tags: list[Tag] = []
    faces: tuple[np.ndarray, ...] = ()
    for tag_id, cap in enumerate(CYLINDER_TAG_CAPS):
        if cap in facing or not facing:
            one = cylinder_layout(radius_m, length_m, tag_size_m, first_id=tag_id, caps=(cap,))
            tags += one.tags
            faces = one.faces
    return TagLayout(tuple(tags), faces)


def camera_calibration(config: StackConfig) -> CameraCalibration:
    """The tag camera's intrinsics and ``T_base_camera``: the ``camera.calibration`` file when set (it must hold
    the extrinsics), else ``[camera]``'s numbers and pose. Raises ``CalibrationFileError`` naming the file and key."""
    camera = config.camera
    if camera.calibration:
        return load_calibration(camera.calibration, require_extrinsics=True)
    intrinsics = CameraIntrinsics(width=camera.width, height=camera.height, fx=camera.fx, fy=camera.fy,
                                  cx=camera.cx, cy=camera.cy)
    return CameraCalibration(intrinsics, np.asarray(camera.pose, dtype=np.float64))


def config_layout(config: StackConfig, T_base_camera: np.ndarray) -> TagLayout:
    """``object_layout`` of the object of the config's task at its scene pose carried into the base frame by
    ``scene.task_frame`` (so the tags go on the faces the camera sees wherever the scene lies), with
    ``scene.tag_size_m``."""
    spec = task_scene_parts(config.scene.task).object
    pose = compose(np.asarray(config.scene.task_frame, dtype=np.float64), np.asarray(spec.pose, dtype=np.float64))
    return object_layout(msgspec.structs.replace(spec, pose=pose.tolist()), config.scene.tag_size_m, T_base_camera)


# --- tracking one image -----------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Tracked:
    """What one image shows: ``tags``, each detected tag whose own pose was accepted with that pose (camera
    frame), and ``result``, the object's pose or the ``Rejection`` saying why there is none."""

    tags: tuple[tuple[TagDetection, TagPose], ...]
    result: ObjectPose | Rejection


@dataclass(eq=False)
class TagTracker:
    """The tracker of one object seen by one camera, one image after the other.

    layout: the object's tags. calibration: the camera (intrinsics and ``T_base_camera``, required).
    other_tag_size_m: edge (m) assumed for tags not on the object when their own pose is solved.
    full_frame_every: the whole image is searched for tags at least on every this-many-th image, in between only
    around the object's last tags (``RegionOfInterest``); 1 searches every image whole.
    """

    layout: TagLayout
    calibration: CameraCalibration
    other_tag_size_m: float
    full_frame_every: int = 1
    detector: cv2.aruco.ArucoDetector = field(default_factory=make_detector)
    region: RegionOfInterest = field(init=False)

    def __post_init__(self) -> None:
        if self.calibration.T_base_camera is None:
            raise ValueError("TagTracker: the camera calibration has no T_base_camera (extrinsics)")
        self.region = RegionOfInterest(frozenset(self.layout.ids), self.full_frame_every)

    @classmethod
    def from_config(cls, config: StackConfig) -> TagTracker:
        """The tracker of the config's object and tag camera, searching the whole image every
        ``FULL_FRAME_PERIOD_S`` at the camera's ``fps``."""
        calibration = camera_calibration(config)
        return cls(config_layout(config, calibration.T_base_camera), calibration, config.scene.tag_size_m,
                   full_frame_every=full_frame_every(config.camera.fps))

    def track(self, image: np.ndarray) -> Tracked:
        """Tags and object pose in ``image`` (``(H, W, 3)`` BGR or ``(H, W)`` grey uint8), the next image of the
        camera. Raises ValueError when ``image`` is not an image (``detect_tags``); an image without the object
        gives a ``Rejection``."""
        intrinsics = self.calibration.intrinsics
        detections = self.region.detect(image, self.detector, intrinsics)
        solved = [solve_tag(detection.corners, self.tag_size_m(detection.id), intrinsics)
                  for detection in detections]
        tags = tuple((detection, pose) for detection, pose in zip(detections, map(reject_ambiguous, solved))
                     if isinstance(pose, TagPose))
        result = object_pose_from_tags(detections, self.layout, intrinsics, self.calibration.T_base_camera, solved)
        return Tracked(tags, result)

    def tag_size_m(self, tag_id: int) -> float:
        """Edge (m) of tag ``tag_id``: the object's tag's, else ``other_tag_size_m``."""
        tag = self.layout.tag(tag_id)
        return tag.size_m if tag is not None else self.other_tag_size_m


def full_frame_every(fps: float) -> int:
    """``TagTracker.full_frame_every`` for a camera of ``fps`` images/s: the images in ``FULL_FRAME_PERIOD_S``."""
    return max(1, round(FULL_FRAME_PERIOD_S * fps))


def detections_message(tracked: Tracked, camera: str, hw_stamp_ns: int | None) -> msg.TagDetections:
    """The ``TagDetections`` of ``tracked``'s accepted tags (``T`` may be 0)."""
    tags = tracked.tags
    return msg.TagDetections(
        camera=camera,
        ids=np.array([d.id for d, _ in tags], dtype=np.int32),
        corners_px=np.array([d.corners for d, _ in tags], dtype=np.float64).reshape(-1, 4, 2),
        poses=np.array([p.T_camera_tag for _, p in tags], dtype=np.float64).reshape(-1, 7),
        reprojection_error_px=np.array([p.reprojection_rms_px for _, p in tags], dtype=np.float64),
        ambiguity=np.array([p.ambiguity_ratio for _, p in tags], dtype=np.float64),
        hw_stamp_ns=hw_stamp_ns,
    )


def pose_quality(pose: ObjectPose) -> float:
    """Confidence in [0, 1]: ``(1 - rms / MAX_REPROJECTION_RMS_PX) (1 - ambiguity_ratio)``, 1 for a perfect,
    unambiguous fit, 0 at the tracker's limit of fit error."""
    fit = max(0.0, 1.0 - pose.reprojection_rms_px / MAX_REPROJECTION_RMS_PX)
    return float(min(1.0, fit * (1.0 - min(max(pose.ambiguity_ratio, 0.0), 1.0))))


def pose_message(pose: ObjectPose, hw_stamp_ns: int | None) -> msg.ObjectPose:
    """The ``ObjectPose`` message of an accepted pose (base frame)."""
    return msg.ObjectPose(object=OBJECT, pose=pose.T_base_object, tags_used=pose.tag_ids, quality=pose_quality(pose),
                          hw_stamp_ns=hw_stamp_ns)


def rejection_kind(reason: str) -> str:
    """The error-counter kind of a ``Rejection`` reason (``rejected_ambiguous_pose``, ...; ``rejected_other`` for
    a reason this table does not know)."""
    for prefix, kind in _REJECTION_KINDS:
        if reason.startswith(prefix):
            return f"rejected_{kind}"
    return "rejected_other"


@dataclass
class PoseWatch:
    """Whether the tracker still produces poses: a note saying why not once no image gave one for ``after_s``.

    after_s: how long (s) images may give no pose before ``update`` returns a note. since_s: monotonic time (s) of
    the first image without a pose since the last pose (``None`` after a pose, and before the first image).
    """

    after_s: float = BLIND_AFTER_S
    since_s: float | None = None

    def update(self, now_s: float, rejection: str | None) -> str:
        """Record one image at monotonic ``now_s`` (s): ``rejection`` is why it gave no pose, ``None`` when it gave
        one. Returns ``""`` while poses come, else (after ``after_s`` without one) a line naming the newest reason."""
        if rejection is None:
            self.since_s = None
            return ""
        if self.since_s is None:
            self.since_s = now_s
        blind_s = now_s - self.since_s
        if blind_s < self.after_s:
            return ""
        return f"no object pose for {blind_s:.1f} s: every image rejected, the newest: {rejection}"


# --- the service ------------------------------------------------------------------------------------------------


def open_camera(service: Service, config: StackConfig) -> Camera:
    """The tag camera: sim_world's images over the bus in sim mode, ``OpenCVCamera(camera.device)`` in the lab.
    Raises ConfigError for a lab config without ``camera.device``."""
    camera = config.camera
    if config.mode == "sim":
        subscriber = service.subscriber(config.endpoint("sim_world"), [image_topic(TAG_CAMERA)])
        return BusCamera(subscriber, TAG_CAMERA, timeout_s=STALE_FRAME_PERIODS / camera.fps)
    if not camera.device:
        raise ConfigError("camera.device: the lab's tag camera needs an OpenCV device index or URL")
    from hydrosoft.drivers.camera.config import OpenCVCameraConfig
    from hydrosoft.drivers.camera.opencv import OpenCVCamera

    source: int | str = int(camera.device) if camera.device.isdigit() else camera.device
    return OpenCVCamera(OpenCVCameraConfig(source=source, width=camera.width, height=camera.height, fps=camera.fps))


async def serve(service: Service, config: StackConfig) -> None:
    """Track every image of the tag camera until cancelled (see the module docstring)."""
    loop = asyncio.get_running_loop()
    cv2.setNumThreads(config.camera.detector_threads)
    tracker = await loop.run_in_executor(None, TagTracker.from_config, config)
    service.log.info("tracking tags %s of the %s object", list(tracker.layout.ids), config.scene.task)
    camera = open_camera(service, config)
    await camera.connect()
    service.on_shutdown(camera.close)
    out = service.publisher(config.endpoint(service.name, "data"))
    tags_topic, pose_topic = msg.topic_for(msg.TagDetections, TAG_CAMERA), msg.topic_for(msg.ObjectPose, OBJECT)
    watch = PoseWatch()
    await service.ready()
    while True:
        try:
            frame = await camera.read()
        except DriverError as error:
            service.count_error("camera", f"{camera}: {error}")
            await report_health(service, f"camera: {error}")
            await asyncio.sleep(CAMERA_RETRY_S)
            continue
        stamp_ns = frame.hw_stamp_ns if frame.hw_stamp_ns is not None else frame.stamp_ns
        try:
            tracked = await loop.run_in_executor(None, tracker.track, frame.image)
        except ValueError as error:
            service.count_error("bad_image", str(error))
            await report_health(service, watch.update(time.monotonic(), f"not an image: {error}"))
            continue
        result = tracked.result
        try:
            await out.send(detections_message(tracked, TAG_CAMERA, stamp_ns), tags_topic)
            if isinstance(result, ObjectPose):
                await out.send(pose_message(result, stamp_ns), pose_topic)
            else:
                service.count_error(rejection_kind(result.reason), result.reason)
        except msg.MessageError as error:
            service.count_error(error.kind, f"cannot publish: {error}")
        rejection = None if isinstance(result, ObjectPose) else result.reason
        await report_health(service, watch.update(time.monotonic(), rejection))


async def report_health(service: Service, note: str) -> None:
    """``degraded`` with ``note`` as the status note when there is one (why no pose or image comes), else ``ready``
    with no note; a change of state is logged and published at once."""
    service.note = note
    state = "degraded" if note else "ready"
    if service.state != service.effective_state(state):
        if note:
            service.log.warning("%s", note)
        await service.set_state(state)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments: CONFIG [--name tag_tracker] (``service_cli``)."""
    service_cli.add_arguments(parser, SERVICE)


def run(args: argparse.Namespace) -> int:
    """Run the tag tracker until SIGINT/SIGTERM; the exit code (2 for a config that cannot be used)."""
    return service_cli.run(args, serve)


def main(argv: list[str] | None = None) -> int:
    return service_cli.main(SERVICE, __doc__, argv, add_arguments, run)


if __name__ == "__main__":
    service_cli.exit_process(main())
