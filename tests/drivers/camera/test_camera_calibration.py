"""ChArUco calibration recovers known intrinsics from rendered board pictures; the command writes a loadable file."""

import argparse
import math

import cv2
import numpy as np
import pytest

from hydrosoft.drivers.camera.calibration import CalibrationError, add_arguments, calibrate_charuco, make_board, run
from hydrosoft.drivers.camera.config import CameraIntrinsics, load_calibration
from hydrosoft.drivers.poses import compose
from hydrosoft.drivers.camera.render import Renderer, RenderOptions

TRUTH = CameraIntrinsics(1280, 720, 910.0, 905.0, 652.0, 350.0, np.array([-0.12, 0.06, 0.0, 0.0, 0.0]))
SQUARES, SQUARE_M, MARKER_M = (7, 5), 0.03, 0.022
PX_PER_SQUARE = 80


def rotation(axis, degrees):
    half = math.radians(degrees) / 2
    return np.concatenate([[0, 0, 0, math.cos(half)], math.sin(half) * np.asarray(axis, dtype=float)])


def board_pictures(count: int) -> list[np.ndarray]:
    """``count`` pictures of the board, tilted up to 35 deg about varied axes, 0.35-0.5 m away, spread over the
    image (with noise and blur)."""
    board = make_board(SQUARES, SQUARE_M, MARKER_M)
    texture = board.generateImage((SQUARES[0] * PX_PER_SQUARE, SQUARES[1] * PX_PER_SQUARE), marginSize=0,
                                  borderBits=1)
    size_m = (SQUARES[0] * SQUARE_M, SQUARES[1] * SQUARE_M)
    centre_to_origin = np.array([-size_m[0] / 2, -size_m[1] / 2, 0.0, 1.0, 0.0, 0.0, 0.0])
    renderer = Renderer(TRUTH, RenderOptions(background=200.0, noise_std=1.5, blur_sigma_px=0.5))
    rng = np.random.default_rng(11)
    pictures = []
    for index in range(count):
        angle = 2 * math.pi * index / count
        axis = [math.cos(angle), math.sin(angle), 0.0]
        centre = [0.15 * math.cos(angle + 1.0), 0.09 * math.sin(angle + 1.0), 0.35 + 0.15 * (index % 3) / 2]
        T_camera_centre = compose(np.array([*centre, 1.0, 0.0, 0.0, 0.0]), rotation(axis, 20 + 15 * (index % 2)))
        pictures.append(renderer.render_plane(texture, compose(T_camera_centre, centre_to_origin), size_m, rng))
    return pictures


@pytest.fixture(scope="module")
def pictures():
    return board_pictures(8)


def test_recovers_known_intrinsics_within_one_percent(pictures):
    intrinsics, rms_px = calibrate_charuco(pictures, make_board(SQUARES, SQUARE_M, MARKER_M))
    for name in ("fx", "fy", "cx", "cy"):
        assert getattr(intrinsics, name) == pytest.approx(getattr(TRUTH, name), rel=0.01), name
    assert (intrinsics.width, intrinsics.height) == (1280, 720)
    assert intrinsics.distortion[0] == pytest.approx(TRUTH.distortion[0], abs=0.03)
    assert rms_px < 0.5


def test_too_few_usable_pictures_are_refused(pictures):
    blank = np.full((720, 1280), 128, np.uint8)
    with pytest.raises(CalibrationError, match="only 2 of 4 pictures"):
        calibrate_charuco([pictures[0], blank, pictures[1], blank], make_board(SQUARES, SQUARE_M, MARKER_M))
    with pytest.raises(CalibrationError, match="image 1 is 640x360"):
        calibrate_charuco([pictures[0], cv2.resize(pictures[1], (640, 360))], make_board(SQUARES, SQUARE_M, MARKER_M))


def parse(argv):
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    return parser.parse_args(argv)


def test_command_writes_a_calibration_file(tmp_path, pictures, capsys):
    for index, picture in enumerate(pictures):
        cv2.imwrite(str(tmp_path / f"board_{index}.png"), picture)
    out = tmp_path / "camera.toml"
    assert run(parse(["--images", str(tmp_path / "board_*.png"), "--out", str(out), "--squares", "7x5"])) == 0
    assert "RMS" in capsys.readouterr().out
    calibration = load_calibration(out, require_extrinsics=False)
    assert calibration.T_base_camera is None
    assert calibration.intrinsics.fx == pytest.approx(TRUTH.fx, rel=0.01)
    assert "RMS reprojection error" in out.read_text()


def test_command_reports_bad_input(tmp_path, capsys):
    assert run(parse(["--images", str(tmp_path / "none_*.png"), "--out", str(tmp_path / "c.toml")])) == 2
    assert "no file matches" in capsys.readouterr().err
    (tmp_path / "x.png").write_text("not an image")
    assert run(parse(["--images", str(tmp_path / "x.png"), "--out", str(tmp_path / "c.toml")])) == 2
    assert "cannot read" in capsys.readouterr().err
    bad_squares = ["--images", str(tmp_path / "x.png"), "--out", str(tmp_path / "c.toml"), "--squares", "7by5"]
    assert run(parse(bad_squares)) == 2
    assert "--squares" in capsys.readouterr().err
