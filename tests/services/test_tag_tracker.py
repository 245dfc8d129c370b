"""The tag tracker: the object's tag layout, tracking rendered images (no sockets), the bus-fed camera, and the
service as a real process fed by a test publisher of rendered ``CameraImage``s.

The process gets a private run_dir and is stopped by its pid in teardown; every wait has a timeout.
"""

from __future__ import annotations

import asyncio
import math
import time
from pathlib import Path

import msgspec
import numpy as np
import torch
import pytest

from hydrosoft.drivers.errors import NotConnected, Stale
from hydrosoft.drivers.poses import rotation_angle_rad
from hydrosoft.geometry import se3
from hydrosoft.services.bus import messages as msg
from hydrosoft.services.bus.sockets import Bus, LatestSubscriber, Publisher, Stale as NoStatus
from hydrosoft.services.bus.config import load_config, parse_config
from hydrosoft.services.sim.devices import BusCamera, image_topic
from hydrosoft.services.sim.render import tag_camera
from hydrosoft.services.tag_detection import MAX_VIEW_ANGLE_DEG, Rejection, solve_tag
from hydrosoft.services.tag_tracker import (
    BLIND_AFTER_S,
    PoseWatch,
    TagTracker,
    detections_message,
    full_frame_every,
    largest_cap_tag_m,
    object_layout,
    pose_message,
    rejection_kind,
)
from hydrosoft.tasks import make_task
from service_process import ServiceProcess

READY_TIMEOUT_S = 60.0
SCENARIO_TIMEOUT_S = 60.0
CAMERA_PERIOD_S = 1.0 / 15.0
POSES_PER_IMAGE = 3  # tracked poses awaited per shown object pose
DEGRADED_WITHIN_S = 2.0  # s after BLIND_AFTER_S of blank images (and after a pose) the state changes within
CAMERA_POSE = np.array([0.35, -0.2, 0.35, 0.376141, -0.778837, -0.451977, 0.218283])  # a camera 45 deg down
POSE_A = np.array([0.0, 0.0, 0.024215, 1.0, 0.0, 0.0, 0.0])
POSE_B = np.array([0.03, -0.02, 0.024215, math.cos(0.25), 0.0, 0.0, math.sin(0.25)])  # moved and turned 29 deg
SIM_TOML = Path(__file__).parents[2] / "deploy" / "sim.toml"
SIM_TASKS = ("pushing", "rotation", "rolling")  # the tasks deploy/sim.toml serves with its one tag camera


def pushing_config():
    """The pushing scene seen by the camera at ``CAMERA_POSE`` (the search tests' poses were chosen for its view)."""
    pose = ", ".join(repr(float(v)) for v in CAMERA_POSE)
    return parse_config(f'[[arms]]\nname = "bubble"\n[scene]\ntask = "pushing"\n[camera]\npose = [{pose}]\n')


def render(config, pose: np.ndarray) -> np.ndarray:
    """What sim_world's tag camera shows of the object at ``pose`` (base frame), noise and blur included."""
    return tag_camera(config, lambda: pose).render(pose)


def assert_near(pose: np.ndarray, truth: np.ndarray, mm: float, deg: float) -> None:
    assert np.linalg.norm(pose[:3] - truth[:3]) < mm * 1e-3, (pose, truth)
    assert math.degrees(rotation_angle_rad(pose[3:], truth[3:])) < deg, (pose, truth)


def sim_config(task: str):
    """deploy/sim.toml with ``scene.task`` = ``task``."""
    config = load_config(SIM_TOML)
    return msgspec.structs.replace(config, scene=msgspec.structs.replace(config.scene, task=task))


def rolled(start: np.ndarray, distance_m: float, radius_m: float) -> np.ndarray:
    """``start (7,)`` rolled without slipping by ``distance_m`` along base x: moved by it and turned by
    ``distance_m / radius_m`` about base y through the object's centre, as ``rolling.sample_goal`` does."""
    delta = torch.zeros(6, dtype=torch.float64)
    delta[0], delta[4] = distance_m, distance_m / radius_m
    return se3.retract(torch.as_tensor(start, dtype=torch.float64), delta).numpy()


# --- layout and tracking, without sockets -------------------------------------------------------------------------


def test_the_cube_carries_tags_on_the_faces_the_camera_sees_with_fixed_ids():
    layout = object_layout(make_task("pushing").scene.object, 0.032, CAMERA_POSE)
    assert layout.ids == (0, 1, 4)  # +z, +x, -y of BOX_TAG_FACES: the camera is at +x, -y and above
    assert all(tag.size_m == 0.032 for tag in layout.tags)
    behind = CAMERA_POSE.copy()
    behind[:2] = -behind[:2]  # a camera at -x, +y sees the top, -x and +y: the ids stay those of their faces
    assert object_layout(make_task("pushing").scene.object, 0.032, behind).ids == (0, 2, 3)


def test_a_cylinder_carries_the_largest_tag_that_fits_on_the_cap_facing_the_camera():
    spec = make_task("rolling").scene.object  # radius 25 mm, its axis along base -y: the +z cap faces -y
    assert largest_cap_tag_m(0.025) == pytest.approx(0.028)
    layout = object_layout(spec, 0.032, CAMERA_POSE)
    assert layout.ids == (0,) and layout.tags[0].size_m == pytest.approx(0.028)
    assert object_layout(spec, 0.02, CAMERA_POSE).tags[0].size_m == 0.02


def test_a_plate_carries_a_tag_only_where_one_fits_and_other_shapes_have_no_layout():
    plate = msgspec.structs.replace(make_task("pushing").scene.object, shape="plate",
                                    params={"length": 0.1, "width": 0.08, "thickness": 0.005})
    assert object_layout(plate, 0.032, CAMERA_POSE).ids == (0,)  # its 5 mm rims hold no tag
    prism = msgspec.structs.replace(plate, shape="triangle_prism", params={})
    with pytest.raises(ValueError, match="no AprilTag layout"):
        object_layout(prism, 0.032, CAMERA_POSE)


def test_the_tracker_finds_the_rendered_cube_within_a_millimetre_and_publishes_its_tags():
    config = pushing_config()
    tracker = TagTracker.from_config(config)
    tracked = tracker.track(render(config, POSE_B))
    assert_near(tracked.result.T_base_object, POSE_B, mm=1.5, deg=1.0)
    detections = detections_message(tracked, "tag_camera", 42)
    assert set(detections.ids) == set(tracked.result.tag_ids) and len(detections.ids) >= 2
    assert detections.poses.shape == (len(detections.ids), 7) and detections.hw_stamp_ns == 42
    pose = pose_message(tracked.result, 42)
    assert pose.object == "object" and 0.5 < pose.quality <= 1.0 and pose.tags_used == tracked.result.tag_ids
    msg.encode(detections, "tags/tag_camera")  # both pass the bus's checks
    msg.encode(pose, "object_pose/object")


def test_an_image_without_the_object_is_a_counted_rejection_and_a_non_image_an_error():
    tracker = TagTracker.from_config(pushing_config())
    tracked = tracker.track(np.full((480, 640, 3), 90, np.uint8))
    assert tracked.tags == () and rejection_kind(tracked.result.reason) == "rejected_no_object_tag"
    assert detections_message(tracked, "tag_camera", None).ids.shape == (0,)
    with pytest.raises(ValueError):
        tracker.track(np.zeros((4, 4, 2), np.uint8))


def test_searching_around_the_last_tags_tracks_as_the_whole_image_does():
    """The config's tracker (whole image every second: 15 images at the default 15 fps) against one searching every
    image whole, on the cube at rest, moved and turned, gone and back: the same tags and poses, bit for bit."""
    config = pushing_config()
    tracker = TagTracker.from_config(config)
    whole = TagTracker(tracker.layout, tracker.calibration, tracker.other_tag_size_m)
    assert tracker.full_frame_every == full_frame_every(config.camera.fps) == 15 and whole.full_frame_every == 1
    blank = np.full((480, 640, 3), 90, np.uint8)
    for image in [render(config, POSE_A)] * 3 + [render(config, POSE_B), blank, render(config, POSE_A)]:
        found, expected = tracker.track(image), whole.track(image)
        assert type(found.result) is type(expected.result)
        if isinstance(expected.result, Rejection):
            assert found.result.reason == expected.result.reason
        else:
            np.testing.assert_array_equal(found.result.T_base_object, expected.result.T_base_object)
        found_message, expected_message = (detections_message(t, "tag_camera", 1) for t in (found, expected))
        np.testing.assert_array_equal(found_message.ids, expected_message.ids)
        np.testing.assert_array_equal(found_message.corners_px, expected_message.corners_px)
        np.testing.assert_array_equal(found_message.poses, expected_message.poses)
    region = tracker.region  # A whole, A twice in the region, B in the region, blank: region then whole, A whole
    assert (region.full_frame_searches, region.region_searches) == (3, 4)



def test_the_sim_cameras_grey_images_are_tracked_as_their_bgr_copies_bit_for_bit():
    """sim_world's tag camera gives grey images (a third of the bytes): the tracker reads the same grey levels from
    them as from the BGR image a colour camera of the same scene gives, so the same tags, corners and poses."""
    config = pushing_config()
    grey_tracker, bgr_tracker = TagTracker.from_config(config), TagTracker.from_config(config)
    camera = tag_camera(config, lambda: POSE_A)
    for pose in (POSE_A, POSE_B, POSE_A):
        grey = camera.render(pose)
        assert grey.shape == (480, 640) and grey.dtype == np.uint8
        found, expected = grey_tracker.track(grey), bgr_tracker.track(np.repeat(grey[:, :, None], 3, axis=2))
        np.testing.assert_array_equal(found.result.T_base_object, expected.result.T_base_object)
        assert found.result.reprojection_rms_px == expected.result.reprojection_rms_px
        found_message, expected_message = (detections_message(t, "tag_camera", 1) for t in (found, expected))
        np.testing.assert_array_equal(found_message.ids, expected_message.ids)
        np.testing.assert_array_equal(found_message.corners_px, expected_message.corners_px)
        assert_near(found.result.T_base_object, pose, mm=1.5, deg=1.0)

@pytest.mark.parametrize("task", SIM_TASKS)
def test_the_sim_camera_sees_every_tag_of_each_task_object_within_the_trackers_limits(task):
    """deploy/sim.toml's one tag camera, rendering each task's scene at its start pose: every tag of the object's
    layout is found and used, seen within ``MAX_VIEW_ANGLE_DEG`` of head-on, and the pose is within 1.5 mm."""
    config = sim_config(task)
    tracker = TagTracker.from_config(config)
    start = np.asarray(make_task(task).scene.object.pose, dtype=np.float64)
    image = render(config, start)
    intrinsics = tracker.calibration.intrinsics
    for detection in tracker.region.detect(image, tracker.detector, intrinsics):
        seen = solve_tag(detection.corners, tracker.layout.tag(detection.id).size_m, intrinsics)
        assert not isinstance(seen, Rejection), (detection.id, seen)
        assert seen.view_angle_deg <= MAX_VIEW_ANGLE_DEG
    result = tracker.track(image).result
    assert not isinstance(result, Rejection), result.reason
    assert result.tag_ids == tracker.layout.ids and not result.tag_rejections
    assert_near(result.T_base_object, start, mm=1.5, deg=1.0)


def test_the_sim_camera_tracks_the_rolling_cylinder_over_its_goal_range():
    """The cylinder rolled by up to the rolling task's 4 cm either way stays in deploy/sim.toml's view, its cap's
    tag within the tracker's limits: a pose within 3 mm and 1 deg in every image."""
    config = sim_config("rolling")
    tracker = TagTracker.from_config(config)
    spec = make_task("rolling").scene.object
    start = np.asarray(spec.pose, dtype=np.float64)
    for distance_m in (-0.04, -0.02, 0.02, 0.04):
        pose = rolled(start, distance_m, float(spec.params["radius"]))
        result = tracker.track(render(config, pose)).result
        assert not isinstance(result, Rejection), (distance_m, result.reason)
        assert_near(result.T_base_object, pose, mm=3.0, deg=1.0)


def test_the_pose_watch_names_the_reason_once_every_image_was_rejected_for_a_while():
    watch = PoseWatch(after_s=2.0)
    assert watch.update(10.0, "no usable tag: 0: grazing view") == ""  # the first rejection starts the clock
    assert watch.update(11.9, "no usable tag: 0: grazing view") == ""
    note = watch.update(12.0, "no usable tag: 0: grazing view: tag normal 72 deg")
    assert note == "no object pose for 2.0 s: every image rejected, the newest: no usable tag: 0: grazing view: " \
                   "tag normal 72 deg"
    assert watch.update(12.1, None) == ""  # a pose clears it at once
    assert watch.update(13.0, "no tag of the object seen") == ""  # and the clock starts again
    assert watch.update(15.0, "no tag of the object seen").startswith("no object pose for 2.0 s")
    assert PoseWatch().after_s == BLIND_AFTER_S


def test_the_whole_image_is_searched_about_once_a_second():
    assert [full_frame_every(fps) for fps in (10.0, 30.0, 2.5, 0.5)] == [10, 30, 2, 1]


@pytest.mark.parametrize("reason, kind", [
    ("no tag of the object seen (its ids: [0, 1])", "rejected_no_object_tag"),
    ("no usable tag: 0: too small", "rejected_no_usable_tag"),
    ("ambiguous: a pose more than 2 deg away fits", "rejected_ambiguous_pose"),
    ("joint fit failed: no finite pose in front of the camera", "rejected_fit_failed"),
    ("tag 3 fits with RMS 2.50 px > 2.0 px", "rejected_inconsistent_tag"),
    ("something new", "rejected_other"),
])
def test_rejection_reasons_map_to_short_kinds(reason, kind):
    assert rejection_kind(reason) == kind


# --- the bus-fed camera -------------------------------------------------------------------------------------------


def test_bus_camera_returns_the_newest_new_image_once_then_goes_stale(tmp_path):
    endpoint = f"ipc://{tmp_path}/sim_world.data"
    bgr = np.arange(4 * 5 * 3, dtype=np.uint8).reshape(4, 5, 3)

    async def scenario() -> None:
        with Bus() as bus:
            out = Publisher(bus, endpoint, source="test")
            subscriber = LatestSubscriber(bus, endpoint, [image_topic("cam")])
            camera = BusCamera(subscriber, "cam", timeout_s=0.3)
            with pytest.raises(NotConnected):
                await camera.read()
            await camera.connect()
            while True:  # until the subscription is up
                await out.send(msg.CameraImage.of("cam", np.zeros((4, 5), np.uint8), 1), image_topic("cam"))
                try:
                    await camera.read()
                    break
                except Stale:
                    pass
            with pytest.raises(Stale):
                while True:  # the warm-up images still queued, then nothing new
                    await camera.read()
            received = subscriber.received[image_topic("cam")]
            await out.send(msg.CameraImage.of("cam", np.zeros_like(bgr), 10), image_topic("cam"))
            await out.send(msg.CameraImage.of("cam", bgr, 20), image_topic("cam"))
            while subscriber.received[image_topic("cam")] < received + 2:  # both in before the read
                assert await subscriber.wait(1.0), "the two images never arrived"
            frame = await camera.read()
            assert frame.hw_stamp_ns == 20 and frame.stamp_ns <= time.monotonic_ns()
            np.testing.assert_array_equal(frame.image, bgr)
            tic_s = time.monotonic()
            with pytest.raises(Stale, match="no new image"):
                await camera.read()  # the newest image was returned already: never handed out twice
            assert time.monotonic() - tic_s >= 0.29
            await out.send(msg.CameraImage.of("cam", bgr[..., 0].copy(), 30), image_topic("cam"))
            assert (await camera.read()).image.shape == (4, 5)
            await camera.close()
            with pytest.raises(NotConnected):
                await camera.read()

    asyncio.run(asyncio.wait_for(scenario(), 20.0))


# --- the service as a process -------------------------------------------------------------------------------------


def test_the_tracker_process_follows_rendered_images_counts_rejections_and_says_when_it_sees_nothing(tmp_path):
    """Poses of the cube at two places; then blank images: each is a counted rejection, and after BLIND_AFTER_S
    the status is degraded, its note naming the reason; the cube again: ready."""
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    config_path = tmp_path / "sim.toml"
    config_path.write_text(f'run_dir = "{run_dir}"\nmode = "sim"\n[scene]\ntask = "pushing"\n'
                           '[[arms]]\nname = "bubble"\n')
    config = load_config(config_path)
    images = {"A": render(config, POSE_A), "B": render(config, POSE_B), "blank": np.full((480, 640, 3), 90, np.uint8)}

    async def scenario(process: ServiceProcess) -> dict[str, list[msg.ObjectPose]]:
        poses: dict[str, list[msg.ObjectPose]] = {"A": [], "B": []}
        stamps: dict[int, str] = {}
        with Bus() as bus:
            camera = Publisher(bus, config.endpoint("sim_world"), source="test")
            tracked = LatestSubscriber(bus, config.endpoint("tag_tracker"), ["object_pose/object"])
            status = LatestSubscriber(bus, config.endpoint("tag_tracker", "status"), ["status/tag_tracker"])

            async def show(name: str) -> None:
                """Publish one image, and keep the pose the tracker found in any image shown so far."""
                image = msg.CameraImage.of("tag_camera", images[name], time.monotonic_ns())
                stamps[image.hw_stamp_ns] = name
                await camera.send(image, image_topic("tag_camera"))
                if await tracked.wait(CAMERA_PERIOD_S):
                    pose = tracked.latest("object_pose/object", 1.0, msg.ObjectPose).value
                    poses[stamps[pose.hw_stamp_ns]].append(pose)

            def newest_status() -> msg.ServiceStatus | None:
                try:
                    return status.latest("status/tag_tracker", 3.0, msg.ServiceStatus).value
                except NoStatus:
                    return None

            async def show_until(name: str, state: str, within_s: float) -> tuple[msg.ServiceStatus, float]:
                """Show image ``name`` until the status reads ``state`` (published at each change); it and the s
                that took."""
                tic = time.monotonic()
                while time.monotonic() - tic < within_s:
                    await show(name)
                    now = newest_status()
                    if now is not None and now.state == state:
                        return now, time.monotonic() - tic
                raise AssertionError(f"{name} images for {within_s} s: the tracker's state is not {state}")

            for name in ("A", "B"):
                while len(poses[name]) < POSES_PER_IMAGE:
                    await show(name)
            await show_until("B", "ready", DEGRADED_WITHIN_S)  # the status comes every second
            blank, blind_s = await show_until("blank", "degraded", BLIND_AFTER_S + DEGRADED_WITHIN_S)
            assert blind_s >= BLIND_AFTER_S and blank.errors.get("rejected_no_object_tag", 0) > 0
            assert blank.note.startswith("no object pose for") and "no tag of the object seen" in blank.note
            seen, _ = await show_until("A", "ready", DEGRADED_WITHIN_S)
            assert seen.note == ""
            return poses

    process = ServiceProcess("tag_tracker", "tag_tracker", config_path, tmp_path / "tag_tracker.log")
    try:
        process.wait_ready(READY_TIMEOUT_S)
        poses = asyncio.run(asyncio.wait_for(scenario(process), SCENARIO_TIMEOUT_S))
    finally:
        rc = process.stop()
    assert rc == 0, process.log()
    for name, truth in (("A", POSE_A), ("B", POSE_B)):
        for pose in poses[name]:
            assert_near(pose.pose, truth, mm=3.0, deg=1.5)
            assert pose.source == "tag_tracker" and pose.tags_used


def test_a_scene_moved_and_turned_by_its_task_frame_keeps_its_tags_facing_the_camera():
    """The camera and the scene moved together (``scene.task_frame``): the same faces carry tags, the table is drawn
    at the frame's height, and the tracker finds the cube in the base frame as precisely as at the origin."""
    from hydrosoft.services.arm.task_frame import TaskFrame

    frame = [0.4, -0.1, -0.05, math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5)]
    to_base = TaskFrame.from_pose(frame).to_base
    camera = to_base(torch.tensor(CAMERA_POSE)).tolist()
    config = parse_config(f'[[arms]]\nname = "bubble"\n[scene]\ntask = "pushing"\ntask_frame = {frame}\n'
                          f'[camera]\npose = {camera}\n')
    tracker = TagTracker.from_config(config)
    assert tracker.layout.ids == (0, 1, 4)  # as at the origin: +z, +x, -y of the cube face the camera
    pose = to_base(torch.tensor(POSE_B)).numpy()
    tracked = tracker.track(render(config, pose))
    assert_near(tracked.result.T_base_object, pose, mm=1.5, deg=1.0)
    assert len(tracked.result.tag_ids) >= 2
