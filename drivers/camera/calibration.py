"""Camera intrinsics from pictures of a ChArUco board, and ``hydrosoft-stack calibrate camera``.

A ChArUco board is a chessboard whose white squares hold ArUco markers: each inner chessboard corner is identified
by the markers around it, so partly visible boards still count. Per image, ``cv2.aruco.CharucoDetector`` finds the
corners; ``cv2.calibrateCamera`` then fits the pinhole model with OpenCV's five distortion coefficients to all of
them. The board's markers come from ``BOARD_DICTIONARY_ID`` (print the board with ``make_board(...).generateImage``
or any generator that uses the same dictionary, square counts and lengths).

Take 15-30 pictures: the board filling a good part of the image, tilted up to about 45 degrees in different
directions, and reaching the image corners, where distortion is largest.
"""

from __future__ import annotations

import argparse
import glob
import sys
from collections.abc import Iterable
from pathlib import Path

import cv2
import numpy as np

from hydrosoft.drivers.camera.config import CameraCalibration, CameraIntrinsics, save_calibration

BOARD_DICTIONARY_ID = cv2.aruco.DICT_5X5_100
MIN_CORNERS_PER_IMAGE = 6  # calibrateCamera needs at least 4 non-collinear points; a few more make a view useful
MIN_IMAGES = 3  # fewer views do not constrain focal length and distortion together
CALIBRATION_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-9)


class CalibrationError(ValueError):
    """The pictures cannot give a calibration; the message says what is missing."""


def make_board(squares: tuple[int, int] = (7, 5), square_m: float = 0.03, marker_m: float = 0.022
               ) -> cv2.aruco.CharucoBoard:
    """A ChArUco board of ``squares`` (columns, rows), square edge ``square_m`` and marker edge ``marker_m`` (m).

    Board frame (OpenCV's): origin at the board's top-left outer corner, x along the columns, y down the rows.

    Raises:
        ValueError: for fewer than 2 squares along an axis, or a marker not smaller than its square.
    """
    columns, rows = squares
    if columns < 2 or rows < 2:
        raise ValueError(f"make_board: need at least 2 x 2 squares, got {columns} x {rows}")
    if not 0 < marker_m < square_m:
        raise ValueError(f"make_board: marker_m {marker_m} must be positive and below square_m {square_m}")
    return cv2.aruco.CharucoBoard((columns, rows), square_m, marker_m,
                                  cv2.aruco.getPredefinedDictionary(BOARD_DICTIONARY_ID))


def calibrate_charuco(images: Iterable[np.ndarray], board: cv2.aruco.CharucoBoard) -> tuple[CameraIntrinsics, float]:
    """Intrinsics from pictures of ``board``.

    Args:
        images: ``(H, W)`` grey or ``(H, W, 3)`` BGR uint8 pictures, all the same size.
        board: the board in the pictures (``make_board``).

    Returns:
        ``(intrinsics, rms_px)``: the fitted camera and the RMS reprojection error of all corners (px). Under 0.5 px
        is a good calibration; above 1 px, check the board's dimensions and the pictures' sharpness.

    Raises:
        CalibrationError: when pictures differ in size or fewer than ``MIN_IMAGES`` show at least
            ``MIN_CORNERS_PER_IMAGE`` non-collinear corners.
    """
    detector = cv2.aruco.CharucoDetector(board)
    object_points, image_points = [], []
    size: tuple[int, int] | None = None
    count = 0
    for index, image in enumerate(images):
        count += 1
        grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        image_size = (grey.shape[1], grey.shape[0])
        if size is None:
            size = image_size
        elif image_size != size:
            raise CalibrationError(f"image {index} is {image_size[0]}x{image_size[1]}, the first was "
                                   f"{size[0]}x{size[1]}: all pictures must come from one camera mode")
        corners, ids, _, _ = detector.detectBoard(grey)
        if ids is None or len(ids) < MIN_CORNERS_PER_IMAGE or board.checkCharucoCornersCollinear(ids):
            continue
        points_object, points_image = board.matchImagePoints(corners, ids)
        object_points.append(points_object.astype(np.float32))
        image_points.append(points_image.astype(np.float32))
    if len(object_points) < MIN_IMAGES:
        raise CalibrationError(f"only {len(object_points)} of {count} pictures show at least {MIN_CORNERS_PER_IMAGE} "
                               f"non-collinear board corners; need {MIN_IMAGES} (check --squares, the dictionary "
                               f"and focus)")
    rms_px, matrix, distortion, _, _ = cv2.calibrateCamera(object_points, image_points, size, None, None,
                                                           criteria=CALIBRATION_CRITERIA)
    intrinsics = CameraIntrinsics(width=size[0], height=size[1], fx=matrix[0, 0], fy=matrix[1, 1], cx=matrix[0, 2],
                                  cy=matrix[1, 2], distortion=np.asarray(distortion, dtype=np.float64).ravel()[:5])
    return intrinsics, float(rms_px)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``hydrosoft-stack calibrate camera``."""
    parser.add_argument("--images", required=True, help="glob of the board pictures, e.g. 'calib/*.png' (quote it)")
    parser.add_argument("--out", required=True, help="calibration TOML file to write (intrinsics only)")
    parser.add_argument("--squares", default="7x5", help="board squares as COLUMNSxROWS (default 7x5)")
    parser.add_argument("--square-m", type=float, default=0.03, help="square edge in metres (default 0.03)")
    parser.add_argument("--marker-m", type=float, default=0.022, help="marker edge in metres (default 0.022)")


def run(args: argparse.Namespace) -> int:
    """Calibrate from ``args.images`` and write ``args.out``; returns the exit status (2 for bad input)."""
    paths = sorted(glob.glob(args.images))
    if not paths:
        print(f"calibrate camera: no file matches {args.images!r}", file=sys.stderr)
        return 2
    try:
        columns, rows = (int(value) for value in args.squares.lower().split("x"))
        board = make_board((columns, rows), args.square_m, args.marker_m)
    except ValueError as error:
        print(f"calibrate camera: --squares {args.squares!r} / --square-m / --marker-m: {error}", file=sys.stderr)
        return 2
    images = []
    for path in paths:
        image = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
        if image is None:
            print(f"calibrate camera: cannot read {path} as an image", file=sys.stderr)
            return 2
        images.append(image)
    try:
        intrinsics, rms_px = calibrate_charuco(images, board)
    except CalibrationError as error:
        print(f"calibrate camera: {error}", file=sys.stderr)
        return 2
    comment = (f"Written by hydrosoft-stack calibrate camera from {len(paths)} pictures matching {args.images}\n"
               f"board {columns}x{rows} squares of {args.square_m} m, markers {args.marker_m} m; "
               f"RMS reprojection error {rms_px:.3f} px\n"
               f"Add [extrinsics] T_base_camera = [x, y, z, qw, qx, qy, qz] once the camera's pose is measured.")
    save_calibration(Path(args.out), CameraCalibration(intrinsics), comment)
    print(f"fx {intrinsics.fx:.2f} fy {intrinsics.fy:.2f} cx {intrinsics.cx:.2f} cy {intrinsics.cy:.2f} px, "
          f"distortion {np.round(intrinsics.distortion, 5).tolist()}, RMS {rms_px:.3f} px -> {args.out}")
    return 0


if __name__ == "__main__":
    _parser = argparse.ArgumentParser(prog="python -m hydrosoft.drivers.camera.calibration",
                                      description="Camera intrinsics from ChArUco board pictures.")
    add_arguments(_parser)
    sys.exit(run(_parser.parse_args()))
