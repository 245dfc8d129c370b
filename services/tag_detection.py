"""The tag tracker's pure functions: AprilTag detection, per-tag pose, and one object pose from all its tags.

``tag_tracker.py`` (the service) is a thin loop over these; they take images and calibration and return values or
a ``Rejection`` that says why no pose was produced, and never raise on a bad image's content.

Pipeline for one image and one object:

0. ``RegionOfInterest``: where to detect. Once the object's tags were found, only a crop around where they were
   last seen goes to the detector, whose cost grows with the pixels it scans (measured on one thread: a 1280 x 720
   image 4.4-6.6 ms, the 150 px crop around a cube 1 m away 0.3 ms, the 420 px one at 0.3 m 3.3 ms; deploy/sim.toml's
   640 x 480 image 1.7 ms, its crop 0.5 ms). The whole image is searched when the crop shows fewer of the object's
   tags than the last image, when no tag of the object was seen last, and every ``full_frame_every``-th image.
   The tags found are the same, corners bit for bit (``subpixel_corners``).
1. ``detect_tags``: OpenCV's 36h11 detector, sub-pixel corners (``subpixel_corners``), then ``refine_corners``: each
   corner is re-placed at the intersection of straight lines fitted to the sub-pixel edge points of the black
   square's sides. OpenCV's corner refinement pulls a convex corner inwards (measured on rendered tags: 0.25-0.35 px,
   which is a 1 % scale error, 4 mm of depth at 0.5 m, on a 57 px tag); the line fit removes that bias and averages
   the noise along the whole edge (rendered tags at 0.3-1 m: 0.03 px median, 0.2 px p95 corner error, against 0.3 px
   and 1.0 px before).
2. ``tag_pose`` (``solve_tag``, then ``reject_ambiguous``): ``cv2.solvePnPGeneric`` with ``SOLVEPNP_IPPE_SQUARE``
   gives the two poses that explain a square's image. A tag is rejected when it is too small (shortest side below
   ``MIN_TAG_SIDE_PX``), seen at a grazing angle (its normal more than ``MAX_VIEW_ANGLE_DEG`` from the line of sight:
   its corners are then poorly placed), or ambiguous: the two solutions differ by more than
   ``AMBIGUITY_MIN_ANGLE_DEG`` and the worse one fits too well to be ruled out: its RMS reprojection error is less
   than ``1 / AMBIGUITY_MAX_RATIO`` times the better one's (with the default 0.5: the image does not favour the
   better pose two to one) or less than ``AMBIGUITY_MIN_ALTERNATIVE_RMS_PX`` (within corner noise, where the ratio of
   two tiny errors means nothing: a small tag seen nearly head-on, whose tilt the image barely shows). Two solutions
   closer than that angle are the same pose for our purposes.
3. ``object_pose_from_tags``: one non-linear PnP (``cv2.solvePnPRefineLM``) on all corners of the object's usable
   tags, started from each tag's two IPPE solutions (``solve_tag``'s, passed in when the caller has them) mapped to
   the object frame, keeping the lowest reprojection error. One joint fit rather than an average of per-tag poses: it
   weights every corner by what it measures (a large, head-on tag counts for more than a small, oblique one without
   hand-made weights), and corners on two or three faces form a non-planar set, which resolves the flip ambiguity
   that a single tag has. The same ambiguity test as in step 2 is then applied to the distinct minima of the joint
   fit, and a tag whose corners disagree with the others (RMS residual above ``MAX_REPROJECTION_RMS_PX``) is dropped
   and the fit repeated.

Frames: camera frame is OpenCV's (x right, y down, z forward); poses are ``(7,)`` ``[x, y, z, qw, qx, qy, qz]`` in
metres; ``T_a_b`` is frame b's pose in frame a.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from hydrosoft.drivers.camera.config import CameraIntrinsics
from hydrosoft.drivers.poses import (
    check_pose,
    compose,
    inverse,
    pose_from_rvec_tvec,
    quat_to_matrix,
    rotation_angle_rad,
    rvec_tvec_from_pose,
)
from hydrosoft.drivers.camera.tags import MARKER_CELLS, TagLayout, tag_corners, tag_dictionary

MIN_TAG_SIDE_PX = 12.0  # shorter sides hold too few pixels for a pose (about 1.5 px per cell)
MAX_VIEW_ANGLE_DEG = 70.0  # tag normal vs line of sight; beyond it one pair of sides is under a third of its length
AMBIGUITY_MAX_RATIO = 0.5  # best / second-best RMS reprojection error above this (with distinct poses): ambiguous
AMBIGUITY_MIN_ANGLE_DEG = 2.0  # two solutions closer than this in rotation count as the same pose
# An alternative that fits within this RMS is within corner noise (refined corners of rendered tags are 0.05-0.2 px
# off), whatever the ratio: raise it for a noisier camera.
AMBIGUITY_MIN_ALTERNATIVE_RMS_PX = 0.1
MAX_REPROJECTION_RMS_PX = 2.0  # a joint fit worse than this has an inconsistent tag (or a wrong layout)
EDGE_PROFILE_MAX_PX = 4.0  # half-length of the intensity profile taken across an edge
EDGE_PROFILE_MIN_PX = 1.0  # narrower profiles cannot see both sides of a blurred edge: no line refinement
EDGE_PROFILE_STEP_PX = 0.25
EDGE_CELL_FRACTION = 0.8  # profile half-length in cells: the nearest same-sign edge is 2 cells inwards
EDGE_SPAN = (0.15, 0.85)  # the part of each side sampled, as fractions of its length (away from the corners)
EDGE_SAMPLES_RANGE = (8, 40)  # number of profiles per side: one per 2 px of side, within this range
EDGE_MAX_SHIFT_PX = 3.0  # a line-fit corner further than this from the detector's is a failed fit: keep the detector's
# Each profile's edge point is the centroid of its steps above this fraction of its largest step. Below it, the
# blurred edges one cell away (quiet zone to face outside, black border to a white data cell inside) overlap the
# edge's own tails and cut them unevenly: with all steps, rendered tags at deploy/sim.toml's blur came out 0.3 % small
# (their corners 0.05-0.2 px inwards), the cube 0.65 mm too far at 0.53 m; with this floor, 0.13 mm. The part above a
# fraction of the peak is symmetric about a symmetric edge's centre wherever the profile starts. A higher floor
# uses fewer samples: at 0.25 an isolated tag's noisy corners were up to 0.104 px off (0.094 at 0.23).
EDGE_STEP_FLOOR = 0.23
EDGE_REFINE_PASSES = 2  # the second pass takes its profiles across the lines of the first
# cv2.cornerSubPix of the detector's corners, as OpenCV's ArucoDetector runs it with CORNER_REFINE_SUBPIX: a window
# of 0.3 of a cell (its default relativeCornerRefinmentWinSize), at most 5 px, 50 iterations or a step under 0.01 px.
SUBPIX_WINDOW_CELLS = 0.3
SUBPIX_MAX_WINDOW_PX = 5
SUBPIX_MAX_ITERATIONS = 50
SUBPIX_MIN_STEP_PX = 0.01
# The region searched around the object's tags reaches this fraction of their extent (the larger side of their
# corners' bounding box) beyond it: the object's motion between images (a 5 cm cube may move 2.5 cm, 25 cm/s at
# 10 images/s; the sim arm pushes at most 5 cm/s), the change of view as it turns, and the quiet zone (1/8 of a side).
REGION_MARGIN_FRACTION = 0.5
# ... plus this many pixels: the detector's adaptive threshold reads up to 11 px around a pixel (windows up to 23 px),
# and it drops tags nearer than 3 px to the border of the image it is given.
REGION_MARGIN_PX = 16
# The detector's adaptive threshold windows (px), smallest and largest, 10 apart: two passes (3 and 13 px), not
# OpenCV's default three (3, 13, 23). On bench tracker's rendered images (8 per setting, 0.3-1 m) the two passes found
# the same poses as accurately or better, at 0.7 of the CPU per image; one pass (13 or 23 px alone) lost tags at 1 m.
THRESHOLD_WINDOWS_PX = (3, 13)
NEXT, PREVIOUS = [1, 2, 3, 0], [3, 0, 1, 2]  # index of each corner's (side's) neighbour, going clockwise and back


@dataclass(frozen=True, eq=False)
class TagDetection:
    """One detected tag: its 36h11 ``id`` and ``corners (4, 2)`` float64 pixels (top-left, top-right,
    bottom-right, bottom-left of the printed tag; pixel centres at integer coordinates)."""

    id: int
    corners: np.ndarray


@dataclass(frozen=True, eq=False)
class TagPose:
    """A tag's pose from its four corners.

    T_camera_tag: ``(7,)`` the better IPPE solution. reprojection_rms_px: its RMS corner error (px).
    alternative_T_camera_tag, alternative_rms_px: the other solution and its RMS error (px).
    ambiguity_ratio: ``reprojection_rms_px / alternative_rms_px`` in [0, 1] (0 when the alternative fits nothing).
    view_angle_deg: angle between the tag's normal and the line of sight from the tag to the camera.
    """

    T_camera_tag: np.ndarray
    reprojection_rms_px: float
    alternative_T_camera_tag: np.ndarray
    alternative_rms_px: float
    ambiguity_ratio: float
    view_angle_deg: float


@dataclass(frozen=True)
class Rejection:
    """No pose, and why: ``reason`` is one line for logs and counters; ``tag_rejections`` maps the object's tag
    ids that were seen but not used to their reasons."""

    reason: str
    tag_rejections: dict[int, str] = field(default_factory=dict)


@dataclass(frozen=True, eq=False)
class ObjectPose:
    """An object's pose from its tags.

    T_base_object, T_camera_object: ``(7,)`` poses (m, wxyz). tag_ids: the tags whose corners were fitted.
    reprojection_rms_px: RMS corner error of the fit (px). ambiguity_ratio: RMS error of the fit divided by that
    of the best distinct alternative fit (0 when there was none; accepted poses have at most
    ``AMBIGUITY_MAX_RATIO``). tag_rejections: the object's tags that were seen but not used, with reasons.
    """

    T_base_object: np.ndarray
    T_camera_object: np.ndarray
    tag_ids: tuple[int, ...]
    reprojection_rms_px: float
    ambiguity_ratio: float
    tag_rejections: dict[int, str]


@dataclass(frozen=True)
class PixelBox:
    """A rectangle of image pixels: columns ``x0 <= x < x1`` and rows ``y0 <= y < y1`` (numpy slice bounds)."""

    x0: int
    y0: int
    x1: int
    y1: int


@dataclass(eq=False)
class RegionOfInterest:
    """Where to look for one object's tags in the next image: around where they were last seen, or everywhere.

    ``detect`` searches ``region`` (``detect_tags`` on a crop) and falls back to the whole image when the crop
    shows fewer of the object's tags than the previous image did; it searches the whole image outright when the
    previous image showed none of them (``region`` is ``None``) and on every ``full_frame_every``-th image, so that
    tags coming into view elsewhere (another face of the object turning into view, the object put down elsewhere)
    are found within that many images. Tags of other objects outside the region are found only in whole-image
    searches. After each image, ``region`` is the bounding box of the object's detected corners grown by
    ``REGION_MARGIN_FRACTION`` of its larger side plus ``REGION_MARGIN_PX`` on every side, cut at the image's border.

    tag_ids: the object's tag ids. full_frame_every: period of the whole-image search in images (1: every image,
    no region). region: ``PixelBox`` to search in the next image (``None``: the whole image). expected_tags: how many
    of the object's tags the previous image showed. images_since_full_frame: images since the last whole-image
    search. full_frame_searches, region_searches: how many searches of each kind were run (a fallback runs both).
    """

    tag_ids: frozenset[int]
    full_frame_every: int
    region: PixelBox | None = None
    expected_tags: int = 0
    images_since_full_frame: int = 0
    full_frame_searches: int = 0
    region_searches: int = 0

    def __post_init__(self) -> None:
        if self.full_frame_every < 1:
            raise ValueError(f"RegionOfInterest: full_frame_every must be at least 1, got {self.full_frame_every}")

    def detect(self, image: np.ndarray, detector: cv2.aruco.ArucoDetector,
               intrinsics: CameraIntrinsics | None = None) -> list[TagDetection]:
        """The tags in ``image`` (as ``detect_tags``; arguments alike): those in the region when it shows all the
        object's tags the previous image did, else all in the image. Updates the region for the next image."""
        if self.region is not None and self.images_since_full_frame + 1 < self.full_frame_every:
            detections = detect_tags(image, detector, intrinsics, self.region)
            self.region_searches += 1
            if self._object_tag_count(detections) >= self.expected_tags:
                self._remember(detections, image.shape[:2], self.images_since_full_frame + 1)
                return detections
        detections = detect_tags(image, detector, intrinsics)
        self.full_frame_searches += 1
        self._remember(detections, image.shape[:2], 0)
        return detections

    def _object_tag_count(self, detections: list[TagDetection]) -> int:
        """How many of ``detections`` are the object's tags."""
        return sum(detection.id in self.tag_ids for detection in detections)

    def _remember(self, detections: list[TagDetection], shape: tuple[int, int], images_since_full_frame: int) -> None:
        """Keep where the object's tags are in an image of ``shape`` ``(H, W)`` and how many were seen."""
        corners = [detection.corners for detection in detections if detection.id in self.tag_ids]
        self.expected_tags = len(corners)
        self.region = region_around(np.concatenate(corners), shape) if corners else None
        self.images_since_full_frame = images_since_full_frame


def region_around(corners: np.ndarray, shape: tuple[int, int]) -> PixelBox:
    """The ``PixelBox`` around ``corners (N, 2)`` (px): their bounding box grown on every side by
    ``REGION_MARGIN_FRACTION`` of its larger side plus ``REGION_MARGIN_PX``, cut at the border of an image of
    ``shape`` ``(H, W)``."""
    low, high = corners.min(axis=0), corners.max(axis=0)
    margin_px = REGION_MARGIN_FRACTION * float(np.max(high - low)) + REGION_MARGIN_PX
    (x0, y0), (x1, y1) = np.floor(low - margin_px).astype(int), np.ceil(high + margin_px).astype(int) + 1
    height, width = shape
    return PixelBox(int(max(x0, 0)), int(max(y0, 0)), int(min(x1, width)), int(min(y1, height)))


def make_detector() -> cv2.aruco.ArucoDetector:
    """OpenCV's 36h11 detector, its corners left on whole pixels (the corners of the contour's polygon):
    ``detect_tags`` refines them on the whole image (``subpixel_corners``, then ``refine_corners``). Its adaptive
    threshold runs two passes, windows of ``THRESHOLD_WINDOWS_PX`` (3 and 13 px, OpenCV's step of 10 apart)."""
    parameters = cv2.aruco.DetectorParameters()
    parameters.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_NONE
    low, high = THRESHOLD_WINDOWS_PX
    parameters.adaptiveThreshWinSizeMin, parameters.adaptiveThreshWinSizeMax = low, high
    return cv2.aruco.ArucoDetector(tag_dictionary(), parameters)


def detect_tags(
    image: np.ndarray,
    detector: cv2.aruco.ArucoDetector,
    intrinsics: CameraIntrinsics | None = None,
    region: PixelBox | None = None,
) -> list[TagDetection]:
    """The 36h11 tags in an image, or in a region of it, corners refined by ``refine_corners``.

    Args:
        image: ``(H, W)`` grey or ``(H, W, 3)`` BGR / ``(H, W, 4)`` BGRA; uint8, uint16 (its high byte is used) or
            float on the 0-255 scale (non-finite pixels read as black).
        detector: from ``make_detector``.
        intrinsics: when given and the lens has distortion, edge points are undistorted before lines are fitted.
        region: when given, only this crop of the image (cut at the image's border) goes to the detector
            (``_detect_in_crop``); corners are full-image pixels either way, and are refined on the whole image.

    Returns:
        One ``TagDetection`` per tag found (an id may repeat when two tags share it); ``[]`` for an image with no
        tag, including empty, uniform or noise images.

    Raises:
        ValueError: when ``image`` is not an image at all (wrong number of axes or channels, unsupported dtype).
    """
    grey = to_grey_uint8(image)
    if grey.size == 0:
        return []
    detections = []
    for tag_id, polygon in detect_markers(grey, detector, region):
        quad = subpixel_corners(grey, polygon)
        if not np.all(np.isfinite(quad)) or not cv2.isContourConvex(quad.astype(np.float32)):
            continue
        detections.append(TagDetection(tag_id, refine_corners(grey, quad, intrinsics)))
    return detections


def subpixel_corners(grey: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """``cv2.cornerSubPix`` of a tag's corners ``polygon (4, 2)`` (px) in ``grey`` ``(H, W)`` uint8, with the window
    OpenCV's ``ArucoDetector`` gives it for ``CORNER_REFINE_SUBPIX``: ``SUBPIX_WINDOW_CELLS`` of the mean cell size,
    rounded, 1 to ``SUBPIX_MAX_WINDOW_PX`` px (computed in float32 as OpenCV does: the corners are bit for bit the
    detector's own). Returns ``(4, 2)`` float64 px.

    The detector itself leaves its corners on whole pixels (``make_detector``): run here on the whole image, the
    corners of a tag found in a crop are those found in the whole image, bit for bit. (Run on the crop, its float32
    steps round differently, and for 2-4 % of the tags in rendered images, oblique ones, it stopped up to 0.9 px
    elsewhere: up to 0.6 px after ``refine_corners``.)
    """
    quad = np.ascontiguousarray(polygon, dtype=np.float32).reshape(4, 2)
    sides = quad - np.roll(quad, -1, axis=0)
    perimeter_px = np.float32(0.0)
    for side_px in np.sqrt(sides[:, 0] * sides[:, 0] + sides[:, 1] * sides[:, 1]):
        perimeter_px += side_px
    cell_px = perimeter_px / np.float32(4 * MARKER_CELLS)
    window_px = min(SUBPIX_MAX_WINDOW_PX, max(1, int(np.rint(np.float32(SUBPIX_WINDOW_CELLS) * cell_px))))
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, SUBPIX_MAX_ITERATIONS, SUBPIX_MIN_STEP_PX)
    return cv2.cornerSubPix(grey, quad, (window_px, window_px), (-1, -1), criteria).astype(np.float64)


def detect_markers(grey: np.ndarray, detector: cv2.aruco.ArucoDetector,
                   region: PixelBox | None = None) -> list[tuple[int, np.ndarray]]:
    """The detector's ``(id, corners (4, 2) float32 px)`` of the tags in ``grey`` ``(H, W)`` uint8, or in its crop
    ``region`` (``_detect_in_crop``): corners on whole pixels, in the whole image's pixels."""
    return _detect_markers(grey, detector) if region is None else _detect_in_crop(grey, detector, region)


def _detect_markers(grey: np.ndarray, detector: cv2.aruco.ArucoDetector) -> list[tuple[int, np.ndarray]]:
    """The detector's ``(id, corners (4, 2) float32 px)`` of the tags in ``grey`` ``(H, W)`` uint8."""
    corners, ids, _ = detector.detectMarkers(grey)
    if ids is None:
        return []
    return [(int(tag_id), quad.reshape(4, 2)) for quad, tag_id in zip(corners, ids.ravel())]


def _detect_in_crop(grey: np.ndarray, detector: cv2.aruco.ArucoDetector,
                    region: PixelBox) -> list[tuple[int, np.ndarray]]:
    """``_detect_markers`` of the crop ``region`` of ``grey`` (cut at its border), corners shifted back to
    full-image pixels.

    The detector's perimeter limits are fractions of the larger side of the image it is given: for the crop they
    are scaled so that they are the same number of pixels as for the whole image (and put back afterwards), so the
    crop accepts the tags the whole image would. A tag whose corners lie at least ``REGION_MARGIN_PX`` inside the
    crop has the same corners (whole pixels) as in the whole image: the detector's adaptive threshold reads only
    pixels nearer than that.
    """
    height, width = grey.shape
    x0, y0, x1, y1 = max(region.x0, 0), max(region.y0, 0), min(region.x1, width), min(region.y1, height)
    if x1 <= x0 or y1 <= y0:
        return []
    crop = grey[y0:y1, x0:x1]
    whole_image = detector.getDetectorParameters()
    cropped = detector.getDetectorParameters()
    scale = max(height, width) / max(crop.shape)
    cropped.minMarkerPerimeterRate = whole_image.minMarkerPerimeterRate * scale
    cropped.maxMarkerPerimeterRate = whole_image.maxMarkerPerimeterRate * scale
    detector.setDetectorParameters(cropped)
    try:
        markers = _detect_markers(crop, detector)
    finally:
        detector.setDetectorParameters(whole_image)
    return [(tag_id, quad + np.float32([x0, y0])) for tag_id, quad in markers]


def refine_corners(grey: np.ndarray, corners: np.ndarray, intrinsics: CameraIntrinsics | None = None) -> np.ndarray:
    """Corners ``(4, 2)`` re-placed at the intersections of lines fitted to the edges of the tag's black square.

    For each side, intensity profiles are sampled across the edge (bilinear) over its middle ``EDGE_SPAN``; each
    profile's edge point is the centroid of its intensity step (the mean position of the gradient of the dominant
    sign above ``EDGE_STEP_FLOOR`` of its peak: unbiased by a symmetric blur, and much less biased than the whole
    gradient by the tails of the neighbouring edges one cell away); a least-squares line is fitted through
    them, in undistorted pixel coordinates when ``intrinsics`` has distortion. Two passes. Returns the input
    corners unchanged when they are not finite, the tag is too small for profiles of ``EDGE_PROFILE_MIN_PX``, or a
    corner would move further than ``EDGE_MAX_SHIFT_PX`` (a failed fit).

    Args:
        grey: ``(H, W)`` uint8 image. corners: ``(4, 2)`` pixels in the detector's order.
        intrinsics: the camera, used only to straighten distorted edges.
    """
    corners = np.asarray(corners, dtype=np.float64)
    if not np.all(np.isfinite(corners)):
        return corners.copy()
    undistort = intrinsics is not None and intrinsics.has_distortion
    sides = np.linalg.norm(corners[NEXT] - corners, axis=1)
    across_cell = np.minimum(sides[NEXT], sides[PREVIOUS]) / MARKER_CELLS
    half_px = np.minimum(EDGE_CELL_FRACTION * across_cell, EDGE_PROFILE_MAX_PX)
    if np.any(half_px < EDGE_PROFILE_MIN_PX):
        return corners.copy()
    offsets = [np.arange(-half, half + 1e-9, EDGE_PROFILE_STEP_PX) for half in half_px]
    refined = corners
    for _ in range(EDGE_REFINE_PASSES):
        sides_points = _edge_points(grey, refined, offsets)
        if sides_points is None or min(len(points) for points in sides_points) < 2:
            return corners.copy()
        if undistort:
            ends = np.cumsum([len(points) for points in sides_points])
            ideal_points = _undistort(np.concatenate(sides_points), intrinsics)
            sides_points = [ideal_points[end - len(points):end] for points, end in zip(sides_points, ends)]
        lines = [_fit_line(points) for points in sides_points]
        centres, directions = np.array([c for c, _ in lines]), np.array([d for _, d in lines])
        ideal = _intersect(centres[PREVIOUS], directions[PREVIOUS], centres, directions)
        refined = _distort(ideal, intrinsics) if undistort else ideal
        if not np.all(np.isfinite(refined)):
            return corners.copy()
    if np.max(np.linalg.norm(refined - corners, axis=1)) > EDGE_MAX_SHIFT_PX:
        return corners.copy()
    return refined


def tag_pose(corners: np.ndarray, size_m: float, intrinsics: CameraIntrinsics) -> TagPose | Rejection:
    """Pose of one tag in the camera frame from its corners, or why not (module docstring, step 2).

    Args:
        corners: ``(4, 2)`` pixels in the detector's order. size_m: the black square's edge (m).
        intrinsics: the camera.

    Returns:
        ``TagPose`` with both IPPE solutions' RMS reprojection errors, or a ``Rejection`` for a tag that is too small,
        seen at a grazing angle, ambiguous, or whose pose is not finite or not in front of the camera.
    """
    return reject_ambiguous(solve_tag(corners, size_m, intrinsics))


def reject_ambiguous(solved: TagPose | Rejection) -> TagPose | Rejection:
    """``solve_tag``'s result, or a ``Rejection`` when its two solutions are distinct and the image does not rule
    out the worse one (module docstring, step 2)."""
    if isinstance(solved, Rejection):
        return solved
    if _is_distinct(solved.T_camera_tag, solved.alternative_T_camera_tag) and _fits_too_well(
            solved.reprojection_rms_px, solved.alternative_rms_px):
        angle = math.degrees(rotation_angle_rad(solved.T_camera_tag[3:], solved.alternative_T_camera_tag[3:]))
        return Rejection(f"ambiguous: two poses {angle:.1f} deg apart fit with RMS {solved.reprojection_rms_px:.3f} "
                         f"and {solved.alternative_rms_px:.3f} px (need the second at least "
                         f"{1 / AMBIGUITY_MAX_RATIO:.0f}x the first and {AMBIGUITY_MIN_ALTERNATIVE_RMS_PX} px)")
    return solved


def object_pose_from_tags(
    detections: list[TagDetection],
    layout: TagLayout,
    intrinsics: CameraIntrinsics,
    T_base_camera: np.ndarray,
    solved: list[TagPose | Rejection] | None = None,
) -> ObjectPose | Rejection:
    """One pose of the object in the base frame from all its visible tags (module docstring, step 3).

    Args:
        detections: every tag in the image; tags not in ``layout`` (other objects) are ignored.
        layout: the object's tags. intrinsics: the camera. T_base_camera: ``(7,)`` the camera's pose in the base frame.
        solved: ``solve_tag`` of each detection (same order; the object's tags at their ``layout`` size) when the
            caller has them already; ``None``: the object's tags are solved here.

    Returns:
        ``ObjectPose``, or a ``Rejection`` when none of the object's tags was seen, none is usable (each tag's reason
        in ``tag_rejections``), the fit is ambiguous or inconsistent, or its result is not finite or not in front of
        the camera.

    Raises:
        ValueError: when ``T_base_camera`` is not a pose (configuration error, not image content).
    """
    T_base_camera = check_pose(T_base_camera, "T_base_camera")
    rejections: dict[int, str] = {}
    seen: dict[int, list[int]] = {}  # tag id -> indices in detections
    for index, detection in enumerate(detections):
        if layout.tag(detection.id) is not None:
            seen.setdefault(detection.id, []).append(index)
    if not seen:
        return Rejection(f"no tag of the object seen (its ids: {list(layout.ids)})")
    usable: dict[int, np.ndarray] = {}
    starts: list[np.ndarray] = []
    for tag_id, indices in sorted(seen.items()):
        if len(indices) > 1:
            rejections[tag_id] = f"seen {len(indices)} times in one image: cannot tell which is on the object"
            continue
        tag, corners = layout.tag(tag_id), detections[indices[0]].corners
        tag_solved = solved[indices[0]] if solved is not None else solve_tag(corners, tag.size_m, intrinsics)
        if isinstance(tag_solved, Rejection):
            rejections[tag_id] = tag_solved.reason
            continue
        usable[tag_id] = corners
        T_tag_object = inverse(tag.T_object_tag)
        starts += [compose(tag_solved.T_camera_tag, T_tag_object),
                   compose(tag_solved.alternative_T_camera_tag, T_tag_object)]
    while usable:
        fit = _fit_object(usable, starts, layout, intrinsics)
        if fit is None:
            return Rejection("joint fit failed: no finite pose in front of the camera", rejections)
        T_camera_object, rms_px, alternative_rms_px, residuals = fit
        ratio = rms_px / alternative_rms_px if alternative_rms_px > 0 else 1.0
        if rms_px > MAX_REPROJECTION_RMS_PX:
            if len(usable) == 1:
                return Rejection(f"tag {next(iter(usable))} fits with RMS {rms_px:.2f} px > "
                                 f"{MAX_REPROJECTION_RMS_PX} px", rejections)
            worst = max(residuals, key=residuals.get)
            rejections[worst] = (f"inconsistent with the other tags: RMS residual {residuals[worst]:.2f} px in the "
                                 f"joint fit")
            del usable[worst]
            continue
        if _fits_too_well(rms_px, alternative_rms_px):
            return Rejection(f"ambiguous: a pose more than {AMBIGUITY_MIN_ANGLE_DEG} deg away fits tags "
                             f"{sorted(usable)} with RMS {alternative_rms_px:.3f} px against {rms_px:.3f} px",
                             rejections)
        return ObjectPose(compose(T_base_camera, T_camera_object), T_camera_object, tuple(sorted(usable)), rms_px,
                          ratio, rejections)
    return Rejection("no usable tag: " + "; ".join(f"{i}: {r}" for i, r in sorted(rejections.items())), rejections)


def solve_tag(corners: np.ndarray, size_m: float, intrinsics: CameraIntrinsics) -> TagPose | Rejection:
    """Both IPPE solutions of one tag (arguments as ``tag_pose``), with the size and view-angle checks but not the
    ambiguity check (``reject_ambiguous``): a tag ambiguous on its own still helps the object's joint fit."""
    corners = np.asarray(corners, dtype=np.float64).reshape(4, 2)
    if not np.all(np.isfinite(corners)):
        return Rejection("corners are not finite")
    shortest_px = float(np.min(np.linalg.norm(np.roll(corners, -1, axis=0) - corners, axis=1)))
    if shortest_px < MIN_TAG_SIDE_PX:
        return Rejection(f"too small: shortest side {shortest_px:.1f} px < {MIN_TAG_SIDE_PX} px")
    if not cv2.isContourConvex(corners.astype(np.float32)):
        return Rejection("corners do not form a convex quadrilateral")
    object_points = tag_corners(size_m)
    try:
        count, rvecs, tvecs, _ = cv2.solvePnPGeneric(object_points, corners, intrinsics.camera_matrix,
                                                     intrinsics.distortion, flags=cv2.SOLVEPNP_IPPE_SQUARE)
    except cv2.error as error:
        return Rejection(f"pose solver failed: {error.err}")
    solutions = []
    for rvec, tvec in zip(rvecs[:count], tvecs[:count]):
        if np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec)) and float(tvec[2, 0]) > 0:
            pose = pose_from_rvec_tvec(rvec, tvec)
            solutions.append((_rms_px(object_points, corners, pose, intrinsics), pose))
    if not solutions:
        return Rejection("no finite pose in front of the camera")
    solutions.sort(key=lambda solution: solution[0])
    best_rms, best = solutions[0]
    alternative_rms, alternative = solutions[-1] if len(solutions) > 1 else (math.inf, best)
    normal = quat_to_matrix(best[3:])[:, 2]
    cosine = float(-normal @ best[:3]) / float(np.linalg.norm(best[:3]))
    view_angle_deg = math.degrees(math.acos(max(-1.0, min(1.0, cosine))))
    if view_angle_deg > MAX_VIEW_ANGLE_DEG:
        return Rejection(f"grazing view: tag normal {view_angle_deg:.0f} deg from the line of sight > "
                         f"{MAX_VIEW_ANGLE_DEG:.0f} deg")
    ratio = best_rms / alternative_rms if alternative_rms > 0 else 1.0
    return TagPose(best, best_rms, alternative, alternative_rms, ratio, view_angle_deg)


def _fit_object(
    usable: dict[int, np.ndarray], starts: list[np.ndarray], layout: TagLayout, intrinsics: CameraIntrinsics
) -> tuple[np.ndarray, float, float, dict[int, float]] | None:
    """Joint LM fit of ``T_camera_object`` to the corners of ``usable`` tags from each start.

    Returns the best pose, its RMS (px), the lowest RMS (px) of a distinct pose among the refined results and the
    starts themselves (``inf`` when there is none), and each tag's RMS residual at the best pose (px). The starts
    count as alternatives because LM from both IPPE solutions of a lone, nearly head-on tag can slide into one
    minimum, hiding the other solution that fits just as well.
    """
    ids = sorted(usable)
    object_points = np.concatenate([layout.tag(i).corners_object for i in ids])
    image_points = np.concatenate([usable[i] for i in ids])
    candidates = []
    for start in starts:
        rvec, tvec = rvec_tvec_from_pose(start)
        try:
            rvec, tvec = cv2.solvePnPRefineLM(object_points, image_points, intrinsics.camera_matrix,
                                              intrinsics.distortion, rvec, tvec)
        except cv2.error:
            rvec = tvec = np.full((3, 1), np.nan)  # a failed refinement only loses this candidate
        if np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec)):
            candidates.append(pose_from_rvec_tvec(rvec, tvec))
        candidates.append(start)
    scored = []
    for pose in candidates:
        points_camera = object_points @ quat_to_matrix(pose[3:]).T + pose[:3]
        if np.all(points_camera[:, 2] > 0):
            squared_px = _squared_errors_px(object_points, image_points, pose, intrinsics)
            scored.append((float(np.sqrt(np.mean(squared_px))), pose, squared_px))
    if not scored:
        return None
    scored.sort(key=lambda candidate: candidate[0])
    best_rms, best, squared_px = scored[0]
    distinct = [rms for rms, pose, _ in scored[1:] if _is_distinct(best, pose)]
    ends = np.cumsum([len(usable[i]) for i in ids])
    residuals = {i: float(np.sqrt(np.mean(squared_px[end - len(usable[i]):end]))) for i, end in zip(ids, ends)}
    return best, best_rms, distinct[0] if distinct else math.inf, residuals


def _is_distinct(T_a: np.ndarray, T_b: np.ndarray) -> bool:
    """Whether two poses differ in rotation by more than ``AMBIGUITY_MIN_ANGLE_DEG``."""
    return math.degrees(rotation_angle_rad(T_a[3:], T_b[3:])) > AMBIGUITY_MIN_ANGLE_DEG


def _fits_too_well(best_rms_px: float, alternative_rms_px: float) -> bool:
    """Whether a distinct alternative pose with RMS ``alternative_rms_px`` cannot be ruled out against the best."""
    return (alternative_rms_px * AMBIGUITY_MAX_RATIO < best_rms_px
            or alternative_rms_px < AMBIGUITY_MIN_ALTERNATIVE_RMS_PX)


def _rms_px(object_points: np.ndarray, image_points: np.ndarray, pose: np.ndarray,
            intrinsics: CameraIntrinsics) -> float:
    """RMS distance (px) between ``image_points (N, 2)`` and ``object_points (N, 3)`` projected at ``pose``."""
    return float(np.sqrt(np.mean(_squared_errors_px(object_points, image_points, pose, intrinsics))))


def _squared_errors_px(object_points: np.ndarray, image_points: np.ndarray, pose: np.ndarray,
                       intrinsics: CameraIntrinsics) -> np.ndarray:
    """Squared distances ``(N,)`` (px^2) between ``image_points (N, 2)`` and ``object_points (N, 3)`` projected at
    ``pose``; each point's is the same whichever other points are projected with it."""
    rvec, tvec = rvec_tvec_from_pose(pose)
    projected, _ = cv2.projectPoints(object_points, rvec, tvec, intrinsics.camera_matrix, intrinsics.distortion)
    return np.sum((projected.reshape(-1, 2) - image_points) ** 2, axis=1)


def to_grey_uint8(image: np.ndarray) -> np.ndarray:
    """``(H, W)`` uint8 grey view of an image (see ``detect_tags``), or ``ValueError`` naming what is wrong."""
    array = np.asarray(image)
    if array.ndim == 3 and array.shape[2] == 1:
        array = array[:, :, 0]
    if array.ndim not in (2, 3) or (array.ndim == 3 and array.shape[2] not in (3, 4)):
        raise ValueError(f"detect_tags: expected an image (H, W), (H, W, 3) or (H, W, 4), got shape {array.shape}")
    if array.dtype == np.uint16:
        array = (array >> 8).astype(np.uint8)
    elif np.issubdtype(array.dtype, np.floating):
        array = np.clip(np.nan_to_num(array, nan=0.0, posinf=0.0, neginf=0.0), 0, 255).astype(np.uint8)
    elif array.dtype != np.uint8:
        raise ValueError(f"detect_tags: expected a uint8, uint16 or float image, got dtype {array.dtype}")
    if array.size == 0:
        return np.zeros((0, 0), dtype=np.uint8)
    if array.ndim == 3:
        code = cv2.COLOR_BGR2GRAY if array.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        array = cv2.cvtColor(np.ascontiguousarray(array), code)
    return np.ascontiguousarray(array)


def _edge_points(grey: np.ndarray, corners: np.ndarray, offsets: list[np.ndarray]) -> list[np.ndarray] | None:
    """Sub-pixel edge points ``(M_k, 2)`` along each side ``k`` of the quadrilateral ``corners (4, 2)``, from corner
    ``k`` to corner ``k + 1`` (see ``refine_corners``); ``None`` when a side is shorter than 1 px.

    ``offsets[k]`` are side ``k``'s sample positions across the edge (px, positive into the tag). The four sides'
    profiles are sampled together (``(4, S, P)``: sides with fewer profiles or narrower ones padded by repeating
    their last row and column, which are cut off again), with the same floating-point operations in the same order
    as for one side on its own, so each point is bit for bit what sampling that side alone gives.
    """
    start = corners
    delta = corners[NEXT] - start
    length = np.array([np.linalg.norm(side) for side in delta])
    if np.any(length < 1.0):
        return None
    along = delta / length[:, None]
    across = np.column_stack([-along[:, 1], along[:, 0]])  # into the tag: the detector's corners run clockwise
    low, high = EDGE_SAMPLES_RANGE
    count = np.clip(length / 2.0, low, high).astype(int)
    rows = np.minimum(np.arange(count.max()), count[:, None] - 1)  # (4, S)
    fractions = rows * ((EDGE_SPAN[1] - EDGE_SPAN[0]) / (count[:, None] - 1)) + EDGE_SPAN[0]  # np.linspace's sums
    fractions[rows == count[:, None] - 1] = EDGE_SPAN[1]
    positions = fractions * length[:, None]
    widths = [len(o) for o in offsets]
    across_px = np.array([np.concatenate([o, np.full(max(widths) - len(o), o[-1])]) for o in offsets])  # (4, P)
    samples = np.empty((2, 4, len(rows[0]), len(across_px[0])), dtype=np.float32)  # x and y of (4, S, P) samples
    for axis in range(2):
        np.add((start[:, axis, None] + positions * along[:, axis, None])[:, :, None],
               (across_px * across[:, axis, None])[:, None, :], out=samples[axis], casting="same_kind")
    profiles = _sample(grey, samples[0], samples[1]).astype(np.float64)
    steps = np.clip(-np.diff(profiles, axis=2), 0.0, None)  # white quiet zone to black square, going inwards
    steps = np.clip(steps - EDGE_STEP_FLOOR * steps.max(axis=2, keepdims=True), 0.0, None)  # the edge's own peak
    sides_points = []
    for k in range(4):
        side_steps = steps[k, :count[k], :widths[k] - 1]
        weight = side_steps.sum(axis=1)
        valid = weight > 0
        midpoints = (offsets[k][:-1] + offsets[k][1:]) / 2.0
        shift = (side_steps[valid] @ midpoints) / weight[valid]
        sides_points.append(start[k] + positions[k, :count[k]][valid, None] * along[k] + shift[:, None] * across[k])
    return sides_points


def _sample(grey: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear grey levels (float32) at the float32 pixels ``(x, y)`` (same shapes), border pixels replicated
    outwards, as ``cv2.remap`` of the whole image as float32 gives them.

    Only the pixels the samples reach are converted to float: their bounding box with a margin of 1 px (2 on the
    far side: bilinear reads the next pixel), cut at the image's border. That patch holds every pixel of the image
    a sample reads, and where it is cut its border is the image's, so replication gives the same values as from the
    whole image; the patch's offsets are integers, so the shifted float32 coordinates are exact. The samples go in
    as one row (at most 32766: OpenCV's limit; four sides of 40 profiles of 33 samples are 5280): OpenCV then
    interpolates in the calling thread, where a map of several rows wakes its thread pool, whose spinning costs
    more CPU than the interpolation.
    """
    height, width = grey.shape
    x0 = min(max(math.floor(float(x.min())) - 1, 0), width - 1)
    y0 = min(max(math.floor(float(y.min())) - 1, 0), height - 1)
    x1 = max(min(math.floor(float(x.max())) + 3, width), x0 + 1)
    y1 = max(min(math.floor(float(y.max())) + 3, height), y0 + 1)
    patch = grey[y0:y1, x0:x1].astype(np.float32)
    values = cv2.remap(patch, x.reshape(1, -1) - np.float32(x0), y.reshape(1, -1) - np.float32(y0), cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_REPLICATE)
    return values.reshape(x.shape)


def _fit_line(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Total-least-squares line through ``points (M, 2)``: a point on it and its unit direction."""
    centre = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centre)
    return centre, vt[0]


def _intersect(pa: np.ndarray, da: np.ndarray, pb: np.ndarray, db: np.ndarray) -> np.ndarray:
    """Intersections ``(K, 2)`` of the lines through points ``pa (K, 2)`` along directions ``da (K, 2)`` with those
    through ``pb`` along ``db``; non-finite where a pair is parallel."""
    matrices = np.stack([da, -db], axis=2)
    parallel = np.abs(np.linalg.det(matrices)) < 1e-12
    matrices[parallel] = np.eye(2)
    s = np.linalg.solve(matrices, (pb - pa)[:, :, None])[:, 0]
    return np.where(parallel[:, None], np.nan, pa + s * da)


def _undistort(points: np.ndarray, intrinsics: CameraIntrinsics) -> np.ndarray:
    """Distorted pixels ``(M, 2)`` to ideal (undistorted) pixels of the same camera matrix."""
    K = intrinsics.camera_matrix
    return cv2.undistortPoints(points.reshape(-1, 1, 2), K, intrinsics.distortion, P=K).reshape(-1, 2)


def _distort(points: np.ndarray, intrinsics: CameraIntrinsics) -> np.ndarray:
    """Ideal pixels ``(M, 2)`` to distorted pixels: the inverse of ``_undistort``."""
    normalised = (points - [intrinsics.cx, intrinsics.cy]) / [intrinsics.fx, intrinsics.fy]
    rays = np.column_stack([normalised, np.ones(len(points))])
    projected, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), intrinsics.camera_matrix, intrinsics.distortion)
    return projected.reshape(-1, 2)
