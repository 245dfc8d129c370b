"""``hydrosoft-stack bench tracker``: accuracy of the AprilTag tracker on rendered images with known truth.

A 5 cm cube with a 36h11 tag (black square ``TAG_SIZE_M``) on each face but the bottom rests on a table. For each
setting (camera distance to the cube's centre, view angle from the vertical: 0 = looking straight down) and each
sample, the cube's yaw, the camera's azimuth and its aim point (up to ``AIM_JITTER`` of the distance off the cube,
so the cube is not always at the image centre) are drawn at random from a seeded generator; ``drivers.camera.render``
renders the image (1280 x 720, fx = fy = 900 px, mild barrel distortion, Gaussian noise and blur) and
``services.tag_tracking`` estimates the cube's pose in the base frame from it.

Each row (one setting): ``images``; ``detection_rate``, the fraction of images that gave a pose;
``tags_per_pose``, the mean number of tags fitted; position error (mm, Euclidean) and orientation error (deg, angle
of the relative rotation) of the poses against the rendered truth as ``median``, ``p95`` and ``max`` (``null``
when no image gave a pose); ``rejections``: reason counts for the images without a pose (reasons cut at the first
colon); ``render_ms`` and ``track_ms``: median wall times of rendering and of detection plus pose;
``track_cpu_ms_mean`` and ``track_cpu_ms_p95``: the tracker's CPU time per image (detection, corner refinement and
pose: ``time.process_time``, all threads of the process, so OpenCV's worker threads count too).
``track_cpu_ms`` sums up the CPU time per image over all rows (``mean``, ``p95``, ``images``).
``--json`` prints ``{"config": {...}, "rows": [...], "track_cpu_ms": {...}}``; otherwise a table and a line with
``track_cpu_ms``. Progress goes to stderr.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections import Counter

import cv2
import numpy as np

from hydrosoft.drivers.camera.config import CameraIntrinsics
from hydrosoft.drivers.poses import compose, inverse, look_at, rotation_angle_rad
from hydrosoft.drivers.camera.render import Renderer, RenderOptions
from hydrosoft.drivers.camera.tags import box_layout
from hydrosoft.services.tag_tracking import ObjectPose, detect_tags, make_detector, object_pose_from_tags

CUBE_EDGE_M = 0.05
TAG_SIZE_M = 0.032
INTRINSICS = dict(width=1280, height=720, fx=900.0, fy=900.0, cx=639.5, cy=359.5,
                  distortion=[-0.08, 0.02, 0.0, 0.0, 0.0])
AIM_JITTER = 0.1  # aim point off the cube centre, as a fraction of the distance (about 6 deg off the optical axis)
FULL = {"distances_m": "0.3,0.5,0.75,1.0", "angles_deg": "0,20,40,60", "samples": 30}
QUICK = {"distances_m": "0.3,1.0", "angles_deg": "0,60", "samples": 3}


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
    config = {"cube_edge_m": CUBE_EDGE_M, "tag_size_m": TAG_SIZE_M, "intrinsics": INTRINSICS,
              "noise_std": args.noise, "blur_sigma_px": args.blur, "samples": samples, "seed": args.seed,
              "aim_jitter": AIM_JITTER, "opencv_threads": cv2.getNumThreads()}
    if args.json:
        print(json.dumps({"config": config, "rows": rows, "track_cpu_ms": track_cpu_ms}))
    else:
        _print_table(rows)
        print(f"tracker CPU per image ({track_cpu_ms['images']} images, {intrinsics.width} x {intrinsics.height}): "
              f"mean {track_cpu_ms['mean']:.1f} ms, p95 {track_cpu_ms['p95']:.1f} ms")
    return 0


def measure_setting(renderer: Renderer, distance_m: float, angle_deg: float, samples: int,
                    rng: np.random.Generator, cpu_ms: list[float]) -> dict:
    """Render ``samples`` images at one setting, track each, and summarise the errors (one row); appends each
    image's tracker CPU time (ms) to ``cpu_ms``."""
    layout = box_layout((CUBE_EDGE_M,) * 3, TAG_SIZE_M)
    detector = make_detector()
    intrinsics = renderer.intrinsics
    position_mm, rotation_deg, tags, render_ms, track_ms, track_cpu_ms = [], [], [], [], [], []
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
            rotation_deg.append(math.degrees(rotation_angle_rad(result.T_base_object[3:], T_base_object[3:])))
            tags.append(len(result.tag_ids))
        else:
            rejections[result.reason.split(":")[0]] += 1
    row = {"distance_m": distance_m, "view_angle_deg": angle_deg, "images": samples,
           "detection_rate": len(position_mm) / samples,
           "tags_per_pose": float(np.mean(tags)) if tags else None}
    row.update(_summary("pos_err_mm", position_mm))
    row.update(_summary("rot_err_deg", rotation_deg))
    row.update({"rejections": dict(rejections), "render_ms": float(np.median(render_ms)),
                "track_ms": float(np.median(track_ms)), "track_cpu_ms_mean": float(np.mean(track_cpu_ms)),
                "track_cpu_ms_p95": float(np.percentile(track_cpu_ms, 95))})
    cpu_ms.extend(track_cpu_ms)
    return row


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


def _floats(text: str, option: str) -> list[float]:
    try:
        return [float(value) for value in text.split(",") if value.strip()]
    except ValueError as error:
        raise ValueError(f"{option}: expected a comma list of numbers, got {text!r}") from error


def _print_table(rows: list[dict]) -> None:
    def cell(value: float | None, digits: int) -> str:
        return "-" if value is None else f"{value:.{digits}f}"

    print(f"{'dist m':>6} {'angle':>5} {'found':>6} {'tags':>4} | {'pos mm: med':>11} {'p95':>6} {'max':>6} | "
          f"{'rot deg: med':>12} {'p95':>6} {'max':>6} | {'render ms':>9} {'track ms':>8} {'cpu ms':>6} "
          f"{'p95':>5}  rejections")
    for row in rows:
        print(f"{row['distance_m']:>6.2f} {row['view_angle_deg']:>5.0f} {row['detection_rate']:>6.0%} "
              f"{cell(row['tags_per_pose'], 1):>4} | {cell(row['pos_err_mm_median'], 2):>11} "
              f"{cell(row['pos_err_mm_p95'], 2):>6} {cell(row['pos_err_mm_max'], 2):>6} | "
              f"{cell(row['rot_err_deg_median'], 2):>12} {cell(row['rot_err_deg_p95'], 2):>6} "
              f"{cell(row['rot_err_deg_max'], 2):>6} | {row['render_ms']:>9.1f} {row['track_ms']:>8.1f} "
              f"{row['track_cpu_ms_mean']:>6.1f} {row['track_cpu_ms_p95']:>5.1f}  {row['rejections'] or ''}")


if __name__ == "__main__":
    _parser = argparse.ArgumentParser(prog="python -m hydrosoft.services.benchmarks.tracker",
                                      description=__doc__.splitlines()[0])
    add_arguments(_parser)
    sys.exit(run(_parser.parse_args()))
