"""``hydrosoft-stack bench tracker``: accuracy of the AprilTag tracker on rendered images with known truth.

A 5 cm cube with a 36h11 tag (black square ``TAG_SIZE_M``) on each face but the bottom rests on a table. For each
setting (camera distance to the cube's centre, view angle from the vertical: 0 = looking straight down) and each
sample, the cube's yaw, the camera's azimuth and its aim point (up to ``AIM_JITTER`` of the distance off the cube,
so the cube is not always at the image centre) are drawn at random from a seeded generator; ``drivers.camera.render``
renders the image (1280 x 720, fx = fy = 900 px, mild barrel distortion, Gaussian noise and blur) and
``services.tag_detection`` estimates the cube's pose in the base frame from it.

Each row (one setting): ``images``; ``detection_rate``, the fraction of images that gave a pose;
``tags_per_pose``, the mean number of tags fitted; position error (mm, Euclidean) and orientation error (deg, angle
of the relative rotation) of the poses against the rendered truth as ``median``, ``p95`` and ``max`` (``null``
when no image gave a pose); ``pos_err_mm_mean_base`` and ``pos_err_mm_mean_camera``: the mean signed position error
``[x, y, z]`` (mm) in the base frame and in the camera's (z along the line of sight: a tag seen too small or too
large shows there as a bias, which the random azimuths average out of the base frame's); ``rejections``: reason
counts for the images without a pose (reasons cut at the first colon); ``render_ms`` and ``track_ms``: median wall
times of rendering and of detection plus pose;
``track_cpu_ms_mean`` and ``track_cpu_ms_p95``: the tracker's CPU time per image (detection, corner refinement and
pose: ``time.process_time``, all threads of the process, so OpenCV's worker threads count too).
``track_cpu_ms`` sums up the CPU time per image over all rows (``mean``, ``p95``, ``images``).

Sequences: the tracker as the service runs it (``TagTracker.track``, one image after the other) on a camera that
stays put while the cube slides ``SEQUENCE_SPEED_M_S`` across the table and turns ``SEQUENCE_YAW_RATE_RAD_S``, one
sequence of ``sequence_images`` images at ``SEQUENCE_FPS`` per distance, seen from ``SEQUENCE_ANGLE_DEG``. Each image
goes to two trackers, in turns first: one searching around the cube's last tags (region of interest, the whole image
every ``full_frame_every`` images as the service does) and one searching every whole image. Each sequence row:
``distance_m``, ``view_angle_deg``, ``images``, ``poses`` (images with a pose, region tracker),
``full_frame_searches`` and ``region_searches`` of the region tracker (a fallback from the region to the whole image
counts in both), ``roi_cpu_ms_mean`` and ``full_frame_cpu_ms_mean`` (CPU per image), ``pose_mismatches`` (images
where one tracker gave a pose and the other not) and ``max_pose_diff_mm``, ``max_pose_diff_deg`` between the two
trackers' poses (``null`` when none). ``sequence_cpu_ms`` sums up all sequences: ``roi`` and ``full_frame``
(``mean``, ``p95``), ``roi_to_full_frame`` (ratio of the means) and ``images``.

Pieces (``pieces``): the tracker's time per image split into its steps, on deploy/sim.toml's tag camera (640 x 480,
the sim's noise and blur: what the stack's tracker sees) while the scene's object (the pushing cube) slides ``SEQUENCE_SPEED_M_S``
and turns: ``receive`` (decoding the ``CameraImage`` message), ``grey`` (to grey: nothing to do for the sim
camera's grey images, BGR to grey for a colour camera's), ``detect`` (OpenCV's ArUco detector, in the region the
tracker searched or the whole image), ``corners`` (``subpixel_corners`` and ``refine_corners`` of each tag), ``pose``
(``solve_tag`` of each tag and ``object_pose_from_tags``) and ``track`` (``TagTracker.track`` itself, all but
``receive``): CPU ms per image, ``mean`` and ``p95``, over ``pieces_images`` images (each timed on its own, the steps
after the tracker's own ``track`` of the image).

``--json`` prints ``{"config": {...}, "rows": [...], "track_cpu_ms": {...}, "sequences": [...],
"sequence_cpu_ms": {...}, "pieces": {...}}``; otherwise a table, a line with ``track_cpu_ms``, lines with the
sequences' figures and one with the pieces.
Progress goes to stderr.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import sys
import time
from collections import Counter
from collections.abc import Iterator

import cv2
import numpy as np

from hydrosoft.drivers.camera.config import CameraCalibration, CameraIntrinsics
from hydrosoft.drivers.poses import compose, inverse, look_at, rotation_angle_rad
from hydrosoft.drivers.camera.render import Renderer, RenderOptions
from hydrosoft.drivers.camera.tags import box_layout
from hydrosoft.services.bus import messages as msg
from hydrosoft.services.bus.config import StackConfig, load_config
from hydrosoft.services.sim.render import tag_camera
from hydrosoft.services.tag_tracker import TAG_CAMERA, TagTracker, full_frame_every
from hydrosoft.services.tag_detection import (
    ObjectPose,
    Rejection,
    TagDetection,
    detect_markers,
    detect_tags,
    make_detector,
    object_pose_from_tags,
    refine_corners,
    solve_tag,
    subpixel_corners,
    to_grey_uint8,
)
from hydrosoft.tasks import make_task

CUBE_EDGE_M = 0.05
TAG_SIZE_M = 0.032
INTRINSICS = dict(width=1280, height=720, fx=900.0, fy=900.0, cx=639.5, cy=359.5,
                  distortion=[-0.08, 0.02, 0.0, 0.0, 0.0])
AIM_JITTER = 0.1  # aim point off the cube centre, as a fraction of the distance (about 6 deg off the optical axis)
FULL = {"distances_m": "0.3,0.5,0.75,1.0", "angles_deg": "0,20,40,60", "samples": 30, "sequence_images": 40,
        "pieces_images": 100}
QUICK = {"distances_m": "0.3,1.0", "angles_deg": "0,60", "samples": 3, "sequence_images": 12, "pieces_images": 12}
PIECES_CONFIG = "deploy/sim.toml"  # the stack config whose tag camera and pushing scene the pieces are timed on
PIECES = ("receive", "grey", "detect", "corners", "pose", "track")
SEQUENCE_FPS = 10.0  # images/s of the sequences: half deploy/sim.toml's tag camera rate, so twice its motion per
# image (the harder case for the region of interest)
SEQUENCE_ANGLE_DEG = 40.0  # view angle of the sequences: two or three faces in view
SEQUENCE_SPEED_M_S = 0.02  # the cube slides this fast (a slow push; the sim arm moves at most 0.05 m/s) ...
SEQUENCE_YAW_RATE_RAD_S = 0.2  # ... and turns this fast, so faces turn into and out of view over a sequence


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``hydrosoft-stack bench tracker``."""
    parser.add_argument("--json", action="store_true", help='print one JSON document {"config": ..., "rows": [...]}')
    parser.add_argument("--quick", action="store_true",
                        help=f"2 distances x 2 angles x {QUICK['samples']} images (a few seconds)")
    parser.add_argument("--distances", default=None,
                        help=f"comma list of camera distances in metres (default {FULL['distances_m']})")
    parser.add_argument("--angles", default=None,
                        help=f"comma list of view angles from the vertical in degrees (default {FULL['angles_deg']})")
    parser.add_argument("--samples", type=int, default=None, help=f"images per setting (default {FULL['samples']})")
    parser.add_argument("--noise", type=float, default=2.0, help="pixel noise std in grey levels (default 2)")
    parser.add_argument("--blur", type=float, default=0.6, help="Gaussian blur sigma in pixels (default 0.6)")
    parser.add_argument("--seed", type=int, default=0, help="seed of poses and noise (default 0)")
    parser.add_argument("--threads", type=int, default=None,
                        help="OpenCV's thread count for detection (cv2.setNumThreads; default: OpenCV's own)")


def run(args: argparse.Namespace) -> int:
    """Run the benchmark described by ``args`` (see ``add_arguments``); returns the exit status."""
    grid = QUICK if args.quick else FULL
    try:
        distances = _floats(args.distances or grid["distances_m"], "--distances")
        angles = _floats(args.angles or grid["angles_deg"], "--angles")
    except ValueError as error:
        print(f"bench tracker: {error}", file=sys.stderr)
        return 2
    samples = args.samples or grid["samples"]
    if samples < 1 or any(d <= CUBE_EDGE_M for d in distances) or any(not 0 <= a < 90 for a in angles):
        print("bench tracker: need --samples >= 1, distances above the cube's size and angles in [0, 90)",
              file=sys.stderr)
        return 2
    if args.threads is not None:
        if args.threads < 1:
            print("bench tracker: --threads must be at least 1", file=sys.stderr)
            return 2
        cv2.setNumThreads(args.threads)
    intrinsics = CameraIntrinsics(**INTRINSICS)
    options = RenderOptions(noise_std=args.noise, blur_sigma_px=args.blur)
    renderer = Renderer(intrinsics, options)
    rng = np.random.default_rng(args.seed)
    rows, cpu_ms = [], []
    for distance in distances:
        for angle in angles:
            print(f"bench tracker: distance {distance} m, view angle {angle} deg", file=sys.stderr)
            rows.append(measure_setting(renderer, distance, angle, samples, rng, cpu_ms))
    track_cpu_ms = {"mean": float(np.mean(cpu_ms)), "p95": float(np.percentile(cpu_ms, 95)), "images": len(cpu_ms)}
    sequences, roi_cpu_ms, full_frame_cpu_ms = [], [], []
    for distance in distances:
        print(f"bench tracker: sequence at distance {distance} m", file=sys.stderr)
        sequences.append(measure_sequence(renderer, distance, grid["sequence_images"], rng, roi_cpu_ms,
                                          full_frame_cpu_ms))
    sequence_cpu_ms = {"roi": _cpu_summary(roi_cpu_ms), "full_frame": _cpu_summary(full_frame_cpu_ms),
                       "roi_to_full_frame": float(np.mean(roi_cpu_ms) / np.mean(full_frame_cpu_ms)),
                       "images": len(roi_cpu_ms)}
    print("bench tracker: the tracker's pieces on the sim stack's tag camera", file=sys.stderr)
    pieces = measure_pieces(load_config(PIECES_CONFIG), grid["pieces_images"])
    config = {"cube_edge_m": CUBE_EDGE_M, "tag_size_m": TAG_SIZE_M, "intrinsics": INTRINSICS,
              "noise_std": args.noise, "blur_sigma_px": args.blur, "samples": samples, "seed": args.seed,
              "aim_jitter": AIM_JITTER, "opencv_threads": cv2.getNumThreads(),
              "sequence": {"images": grid["sequence_images"], "fps": SEQUENCE_FPS, "view_angle_deg": SEQUENCE_ANGLE_DEG,
                           "speed_m_s": SEQUENCE_SPEED_M_S, "yaw_rate_rad_s": SEQUENCE_YAW_RATE_RAD_S,
                           "full_frame_every": full_frame_every(SEQUENCE_FPS)},
              "pieces": {"config": PIECES_CONFIG, "images": grid["pieces_images"]}}
    if args.json:
        print(json.dumps({"config": config, "rows": rows, "track_cpu_ms": track_cpu_ms, "sequences": sequences,
                          "sequence_cpu_ms": sequence_cpu_ms, "pieces": pieces}))
    else:
        _print_table(rows)
        print(f"tracker CPU per image ({track_cpu_ms['images']} images, {intrinsics.width} x {intrinsics.height}): "
              f"mean {track_cpu_ms['mean']:.1f} ms, p95 {track_cpu_ms['p95']:.1f} ms")
        _print_sequences(sequences, sequence_cpu_ms)
        print(f"tracker pieces on {PIECES_CONFIG}'s tag camera, CPU ms per image (mean / p95): "
              + ", ".join(f"{name} {pieces[name]['mean']:.2f} / {pieces[name]['p95']:.2f}" for name in PIECES))
    return 0


def measure_setting(renderer: Renderer, distance_m: float, angle_deg: float, samples: int,
                    rng: np.random.Generator, cpu_ms: list[float]) -> dict:
    """Render ``samples`` images at one setting, track each, and summarise the errors (one row); appends each
    image's tracker CPU time (ms) to ``cpu_ms``."""
    layout = box_layout((CUBE_EDGE_M,) * 3, TAG_SIZE_M)
    detector = make_detector()
    intrinsics = renderer.intrinsics
    position_mm, rotation_deg, tags, render_ms, track_ms, track_cpu_ms = [], [], [], [], [], []
    signed_base_mm, signed_camera_mm = [], []
    rejections: Counter[str] = Counter()
    T_base_table = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
    for _ in range(samples):
        yaw = rng.uniform(0.0, 2 * math.pi)
        T_base_object = np.array([0.0, 0.0, CUBE_EDGE_M / 2, math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])
        T_base_camera = camera_pose(distance_m, angle_deg, rng.uniform(0.0, 2 * math.pi),
                                    T_base_object[:3] + rng.uniform(-AIM_JITTER, AIM_JITTER, 3) * distance_m)
        T_camera_base = inverse(T_base_camera)
        start = time.perf_counter()
        T_camera_table = compose(T_camera_base, T_base_table)
        image = renderer.render(compose(T_camera_base, T_base_object), layout, rng, T_camera_table)
        render_ms.append(1e3 * (time.perf_counter() - start))
        start, start_cpu = time.perf_counter(), time.process_time()
        result = object_pose_from_tags(detect_tags(image, detector, intrinsics), layout, intrinsics, T_base_camera)
        track_cpu_ms.append(1e3 * (time.process_time() - start_cpu))
        track_ms.append(1e3 * (time.perf_counter() - start))
        if isinstance(result, ObjectPose):
            position_mm.append(1e3 * float(np.linalg.norm(result.T_base_object[:3] - T_base_object[:3])))
            signed_base_mm.append(1e3 * (result.T_base_object[:3] - T_base_object[:3]))
            signed_camera_mm.append(1e3 * (result.T_camera_object[:3] - compose(T_camera_base, T_base_object)[:3]))
            rotation_deg.append(math.degrees(rotation_angle_rad(result.T_base_object[3:], T_base_object[3:])))
            tags.append(len(result.tag_ids))
        else:
            rejections[result.reason.split(":")[0]] += 1
    row = {"distance_m": distance_m, "view_angle_deg": angle_deg, "images": samples,
           "detection_rate": len(position_mm) / samples,
           "tags_per_pose": float(np.mean(tags)) if tags else None}
    row.update(_summary("pos_err_mm", position_mm))
    row.update(_summary("rot_err_deg", rotation_deg))
    row.update({f"pos_err_mm_mean_{frame}": np.mean(signed, axis=0).tolist() if signed else None
                for frame, signed in (("base", signed_base_mm), ("camera", signed_camera_mm))})
    row.update({"rejections": dict(rejections), "render_ms": float(np.median(render_ms)),
                "track_ms": float(np.median(track_ms)), "track_cpu_ms_mean": float(np.mean(track_cpu_ms)),
                "track_cpu_ms_p95": float(np.percentile(track_cpu_ms, 95))})
    cpu_ms.extend(track_cpu_ms)
    return row


def measure_sequence(renderer: Renderer, distance_m: float, images: int, rng: np.random.Generator,
                     roi_cpu_ms: list[float], full_frame_cpu_ms: list[float]) -> dict:
    """Track a sequence of ``images`` images of the sliding, turning cube (module docstring, Sequences) with a
    region-of-interest tracker and a whole-image one; appends each image's tracker CPU times (ms) to ``roi_cpu_ms``
    and ``full_frame_cpu_ms``, and returns the sequence's row."""
    layout = box_layout((CUBE_EDGE_M,) * 3, TAG_SIZE_M)
    start = np.array([0.0, 0.0, CUBE_EDGE_M / 2])
    T_base_camera = camera_pose(distance_m, SEQUENCE_ANGLE_DEG, rng.uniform(0.0, 2 * math.pi),
                                start + rng.uniform(-AIM_JITTER, AIM_JITTER, 3) * distance_m)
    T_camera_base = inverse(T_base_camera)
    T_camera_table = compose(T_camera_base, np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]))
    heading, yaw = rng.uniform(0.0, 2 * math.pi, 2)
    velocity = SEQUENCE_SPEED_M_S * np.array([math.cos(heading), math.sin(heading), 0.0])
    calibration = CameraCalibration(renderer.intrinsics, T_base_camera)
    roi = TagTracker(layout, calibration, TAG_SIZE_M, full_frame_every=full_frame_every(SEQUENCE_FPS))
    full_frame = TagTracker(layout, calibration, TAG_SIZE_M)
    poses, mismatches, position_diff_mm, rotation_diff_deg = 0, 0, [], []
    for index in range(images):
        t_s = (index - (images - 1) / 2) / SEQUENCE_FPS  # the cube passes the aim point halfway
        angle = yaw + SEQUENCE_YAW_RATE_RAD_S * t_s
        T_base_object = np.array([*(start + velocity * t_s), math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2)])
        image = renderer.render(compose(T_camera_base, T_base_object), layout, rng, T_camera_table)
        if index % 2 == 0:
            found = _timed_track(roi, image, roi_cpu_ms)
            expected = _timed_track(full_frame, image, full_frame_cpu_ms)
        else:
            expected = _timed_track(full_frame, image, full_frame_cpu_ms)
            found = _timed_track(roi, image, roi_cpu_ms)
        poses += isinstance(found, ObjectPose)
        if isinstance(found, ObjectPose) != isinstance(expected, ObjectPose):
            mismatches += 1
        elif isinstance(found, ObjectPose):
            position_diff_mm.append(1e3 * float(np.linalg.norm(found.T_base_object[:3] - expected.T_base_object[:3])))
            rotation_diff_deg.append(math.degrees(rotation_angle_rad(found.T_base_object[3:],
                                                                     expected.T_base_object[3:])))
    return {"distance_m": distance_m, "view_angle_deg": SEQUENCE_ANGLE_DEG, "images": images, "poses": poses,
            "full_frame_searches": roi.region.full_frame_searches, "region_searches": roi.region.region_searches,
            "roi_cpu_ms_mean": float(np.mean(roi_cpu_ms[-images:])),
            "full_frame_cpu_ms_mean": float(np.mean(full_frame_cpu_ms[-images:])), "pose_mismatches": mismatches,
            "max_pose_diff_mm": max(position_diff_mm, default=None),
            "max_pose_diff_deg": max(rotation_diff_deg, default=None)}


def measure_pieces(config: StackConfig, images: int) -> dict:
    """The tracker's CPU time per image in pieces (module docstring, Pieces) on ``images`` images of ``config``'s tag
    camera, its scene's object sliding along x and turning as in the sequences: ``{piece: {mean, p95}}`` (ms)."""
    tracker = TagTracker.from_config(config)
    spec = make_task(config.scene.task).scene.object
    start = compose(np.asarray(config.scene.task_frame, dtype=np.float64), np.asarray(spec.pose, dtype=np.float64))
    pose = {"now": start}
    camera = tag_camera(config, lambda: pose["now"])
    intrinsics = tracker.calibration.intrinsics
    cpu_ms: dict[str, list[float]] = {name: [] for name in PIECES}
    for index in range(images):
        t_s = index / config.camera.fps
        angle = SEQUENCE_YAW_RATE_RAD_S * t_s
        pose["now"] = compose(start, np.array([SEQUENCE_SPEED_M_S * t_s, 0.0, 0.0, math.cos(angle / 2), 0.0, 0.0,
                                               math.sin(angle / 2)]))
        frames = msg.encode(msg.CameraImage.of(TAG_CAMERA, camera.render(pose["now"]), 0))
        with _cpu_time(cpu_ms["receive"]):
            image = msg.decode(frames)[1].frame
        region = tracker.region.region if tracker.region.images_since_full_frame + 1 < tracker.full_frame_every \
            else None
        with _cpu_time(cpu_ms["track"]):
            tracker.track(image)
        with _cpu_time(cpu_ms["grey"]):
            grey = to_grey_uint8(image)
        with _cpu_time(cpu_ms["detect"]):
            markers = detect_markers(grey, tracker.detector, region)
        with _cpu_time(cpu_ms["corners"]):
            detections = [(tag_id, refine_corners(grey, subpixel_corners(grey, polygon), intrinsics))
                          for tag_id, polygon in markers]
        with _cpu_time(cpu_ms["pose"]):
            solved = [solve_tag(corners, tracker.tag_size_m(tag_id), intrinsics) for tag_id, corners in detections]
            object_pose_from_tags([TagDetection(tag_id, corners) for tag_id, corners in detections], tracker.layout,
                                  intrinsics, tracker.calibration.T_base_camera, solved)
    return {name: _cpu_summary(values) for name, values in cpu_ms.items()}


@contextlib.contextmanager
def _cpu_time(values: list[float]) -> Iterator[None]:
    """Appends the CPU time (ms, ``time.process_time``) of the ``with`` block to ``values``."""
    start = time.process_time()
    yield
    values.append(1e3 * (time.process_time() - start))


def _timed_track(tracker: TagTracker, image: np.ndarray, cpu_ms: list[float]) -> ObjectPose | Rejection:
    """``tracker.track(image)``'s object pose or rejection; appends the CPU time it took (ms) to ``cpu_ms``."""
    start_cpu = time.process_time()
    result = tracker.track(image).result
    cpu_ms.append(1e3 * (time.process_time() - start_cpu))
    return result


def camera_pose(distance_m: float, angle_deg: float, azimuth_rad: float, target: np.ndarray) -> np.ndarray:
    """``T_base_camera (7,)`` of a camera ``distance_m`` from ``target (3,)``, ``angle_deg`` from the vertical above
    it, at ``azimuth_rad`` about the vertical; the image's top points away from the camera (up the view)."""
    tilt = math.radians(angle_deg)
    towards = -np.array([math.cos(azimuth_rad), math.sin(azimuth_rad), 0.0])  # horizontal, camera to target
    eye = target - distance_m * math.sin(tilt) * towards + np.array([0.0, 0.0, distance_m * math.cos(tilt)])
    up = math.cos(tilt) * towards + math.sin(tilt) * np.array([0.0, 0.0, 1.0])
    return look_at(eye, target, up)


def _summary(name: str, values: list[float]) -> dict:
    """``{name_median, name_p95, name_max}`` of ``values`` (``None`` each when empty)."""
    if not values:
        return {f"{name}_median": None, f"{name}_p95": None, f"{name}_max": None}
    return {f"{name}_median": float(np.median(values)), f"{name}_p95": float(np.percentile(values, 95)),
            f"{name}_max": float(np.max(values))}


def _cpu_summary(cpu_ms: list[float]) -> dict:
    """``{mean, p95}`` (ms) of per-image CPU times ``cpu_ms`` (ms)."""
    return {"mean": float(np.mean(cpu_ms)), "p95": float(np.percentile(cpu_ms, 95))}


def _floats(text: str, option: str) -> list[float]:
    try:
        return [float(value) for value in text.split(",") if value.strip()]
    except ValueError as error:
        raise ValueError(f"{option}: expected a comma list of numbers, got {text!r}") from error


def _print_table(rows: list[dict]) -> None:
    def cell(value: float | None, digits: int) -> str:
        return "-" if value is None else f"{value:.{digits}f}"

    def signed(values: list[float] | None) -> str:
        return "-" if values is None else ", ".join(f"{value:+.2f}" for value in values)

    print(f"{'dist m':>6} {'angle':>5} {'found':>6} {'tags':>4} | {'pos mm: med':>11} {'p95':>6} {'max':>6} | "
          f"{'rot deg: med':>12} {'p95':>6} {'max':>6} | {'mean mm: cam x, y, z':>20} | {'render ms':>9} "
          f"{'track ms':>8} {'cpu ms':>6} {'p95':>5}  rejections")
    for row in rows:
        print(f"{row['distance_m']:>6.2f} {row['view_angle_deg']:>5.0f} {row['detection_rate']:>6.0%} "
              f"{cell(row['tags_per_pose'], 1):>4} | {cell(row['pos_err_mm_median'], 2):>11} "
              f"{cell(row['pos_err_mm_p95'], 2):>6} {cell(row['pos_err_mm_max'], 2):>6} | "
              f"{cell(row['rot_err_deg_median'], 2):>12} {cell(row['rot_err_deg_p95'], 2):>6} "
              f"{cell(row['rot_err_deg_max'], 2):>6} | {signed(row['pos_err_mm_mean_camera']):>20} | "
              f"{row['render_ms']:>9.1f} {row['track_ms']:>8.1f} "
              f"{row['track_cpu_ms_mean']:>6.1f} {row['track_cpu_ms_p95']:>5.1f}  {row['rejections'] or ''}")


def _print_sequences(sequences: list[dict], cpu_ms: dict) -> None:
    def cell(value: float | None) -> str:
        return "-" if value is None else f"{value:.4f}"

    for row in sequences:
        print(f"sequence at {row['distance_m']:.2f} m: {row['poses']}/{row['images']} poses, "
              f"{row['full_frame_searches']} whole-image and {row['region_searches']} region searches, CPU per image "
              f"{row['roi_cpu_ms_mean']:.1f} ms (region) vs {row['full_frame_cpu_ms_mean']:.1f} ms (whole image), "
              f"pose mismatches {row['pose_mismatches']}, pose difference max {cell(row['max_pose_diff_mm'])} mm "
              f"{cell(row['max_pose_diff_deg'])} deg")
    print(f"tracker CPU per image over sequences ({cpu_ms['images']} images): region of interest mean "
          f"{cpu_ms['roi']['mean']:.1f} ms (p95 {cpu_ms['roi']['p95']:.1f}), whole image mean "
          f"{cpu_ms['full_frame']['mean']:.1f} ms (p95 {cpu_ms['full_frame']['p95']:.1f}): "
          f"ratio {cpu_ms['roi_to_full_frame']:.2f}")


if __name__ == "__main__":
    _parser = argparse.ArgumentParser(prog="python -m hydrosoft.services.benchmarks.tracker",
                                      description=__doc__.splitlines()[0])
    add_arguments(_parser)
    sys.exit(run(_parser.parse_args()))
