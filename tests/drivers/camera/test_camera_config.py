"""Calibration files round-trip exactly, and a bad file is refused with the bad key named."""

import numpy as np
import pytest

from hydrosoft.drivers.camera.config import (
    CalibrationFileError,
    CameraCalibration,
    CameraIntrinsics,
    OpenCVCameraConfig,
    SimCameraConfig,
    load_calibration,
    save_calibration,
)

GOOD = """[intrinsics]
width = 1280
height = 720
fx = 901.25
fy = 899.5
cx = 641.0
cy = 358.75
distortion = [-0.08, 0.02, 0.0001, -0.0002, 0.0]

[extrinsics]
T_base_camera = [0.5, 0.0, 0.8, 0.0, 1.0, 0.0, 0.0]
"""


def test_round_trip_is_exact(tmp_path):
    intrinsics = CameraIntrinsics(1280, 720, 901.123456789012, 899.1, 640.3, 359.7,
                                  np.array([-0.0812345678901, 0.021, 1e-5, -2e-5, 0.003]))
    T = np.array([0.4, -0.1, 0.9, 0.1, 0.9, 0.3, 0.2])
    T[3:] /= np.linalg.norm(T[3:])
    path = tmp_path / "cam.toml"
    save_calibration(path, CameraCalibration(intrinsics, T), comment="made by a test\nsecond line")
    loaded = load_calibration(path)
    for name in ("width", "height", "fx", "fy", "cx", "cy"):
        assert getattr(loaded.intrinsics, name) == getattr(intrinsics, name)
    np.testing.assert_array_equal(loaded.intrinsics.distortion, intrinsics.distortion)
    np.testing.assert_array_equal(loaded.T_base_camera, T)
    assert path.read_text().startswith("# made by a test\n# second line\n")


def test_intrinsics_only_file_loads_when_extrinsics_are_not_required(tmp_path):
    path = tmp_path / "cam.toml"
    save_calibration(path, CameraCalibration(CameraIntrinsics(640, 480, 500.0, 500.0, 319.5, 239.5)))
    assert load_calibration(path, require_extrinsics=False).T_base_camera is None
    with pytest.raises(CalibrationFileError, match=r"extrinsics\.T_base_camera"):
        load_calibration(path)


@pytest.mark.parametrize("edit, key", [
    (("fx = 901.25", "fx = -3.0"), "intrinsics.fx"),
    (("fy = 899.5", 'fy = "900"'), "intrinsics.fy"),
    (("width = 1280", "width = 12.5"), "intrinsics.width"),
    (("cy = 358.75\n", ""), "intrinsics.cy"),
    (("cy = 358.75", "cy = 358.75\nskew = 0.0"), "intrinsics.skew"),
    (("distortion = [-0.08, 0.02, 0.0001, -0.0002, 0.0]", "distortion = [-0.08, 0.02]"), "intrinsics.distortion"),
    (("distortion = [-0.08, 0.02, 0.0001, -0.0002, 0.0]", "distortion = [-0.08, 0.02, 0.0, 0.0, nan]"),
     "intrinsics.distortion"),
    (("T_base_camera = [0.5, 0.0, 0.8, 0.0, 1.0, 0.0, 0.0]", "T_base_camera = [0.5, 0.0, 0.8]"),
     "extrinsics.T_base_camera"),
    (("T_base_camera = [0.5, 0.0, 0.8, 0.0, 1.0, 0.0, 0.0]", "T_base_camera = [0.5, 0.0, 0.8, 0.0, 2.0, 0.0, 0.0]"),
     "extrinsics.T_base_camera"),
    (("T_base_camera", "T_camera_base"), "extrinsics.T_base_camera"),
    (("[intrinsics]", "[intrinsic]"), "[intrinsics]"),
])
def test_bad_key_is_named(tmp_path, edit, key):
    path = tmp_path / "cam.toml"
    path.write_text(GOOD.replace(*edit))
    with pytest.raises(CalibrationFileError) as error:
        load_calibration(path)
    assert key in str(error.value)
    assert str(path) in str(error.value)


def test_missing_and_malformed_files_are_named(tmp_path):
    with pytest.raises(CalibrationFileError, match="no such calibration file"):
        load_calibration(tmp_path / "absent.toml")
    path = tmp_path / "broken.toml"
    path.write_text("[intrinsics\nfx = 1")
    with pytest.raises(CalibrationFileError, match="not valid TOML"):
        load_calibration(path)


def test_the_good_example_loads(tmp_path):
    path = tmp_path / "cam.toml"
    path.write_text(GOOD)
    calibration = load_calibration(path)
    assert calibration.intrinsics.camera_matrix[0, 2] == 641.0
    np.testing.assert_array_equal(calibration.T_base_camera, [0.5, 0.0, 0.8, 0.0, 1.0, 0.0, 0.0])


@pytest.mark.parametrize("kwargs, field", [
    (dict(width=0), "width"), (dict(fx=0.0), "fx"), (dict(cy=float("inf")), "cy"),
    (dict(distortion=np.zeros(4)), "distortion"),
])
def test_intrinsics_refuse_bad_values(kwargs, field):
    values = dict(width=640, height=480, fx=500.0, fy=500.0, cx=319.5, cy=239.5) | kwargs
    with pytest.raises(ValueError, match=f"CameraIntrinsics.{field}"):
        CameraIntrinsics(**values)


def test_driver_configs_check_how_limits_relate():
    with pytest.raises(ValueError, match="max_age_ms"):
        OpenCVCameraConfig(source=0, fps=10.0, max_age_ms=150.0)  # two periods are 200 ms
    with pytest.raises(ValueError, match="source"):
        OpenCVCameraConfig(source="")
    with pytest.raises(ValueError, match="fps"):
        SimCameraConfig(fps=0.0)
    assert OpenCVCameraConfig(source="video.avi", fps=10.0, max_age_ms=200.0).max_age_ms == 200.0
