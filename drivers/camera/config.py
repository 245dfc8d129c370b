"""Camera facts: intrinsics and extrinsics (read from a TOML calibration file) and the drivers' settings.

The calibration file format is written out in ``drivers/camera/README.md``; ``save_calibration`` writes it and
``load_calibration`` reads it back, raising ``CalibrationFileError`` that names the bad key.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hydrosoft.drivers.poses import check_pose

DISTORTION_SIZE = 5  # OpenCV's plumb-bob model: k1, k2, p1, p2, k3


class CalibrationFileError(ValueError):
    """A calibration file that cannot be used; the message names the file and the bad key."""


@dataclass(frozen=True, eq=False)
class CameraIntrinsics:
    """A pinhole camera with OpenCV's plumb-bob distortion.

    width, height: image size in pixels. fx, fy: focal lengths in pixels. cx, cy: principal point in pixels, with
    OpenCV's convention that pixel ``(u, v)``'s centre is at the integer coordinates ``(u, v)``.
    distortion: ``(5,)`` ``[k1, k2, p1, p2, k3]`` (dimensionless, on normalised image coordinates).
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: np.ndarray = field(default_factory=lambda: np.zeros(DISTORTION_SIZE))

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0:
                raise ValueError(f"CameraIntrinsics.{name}: expected a positive integer (pixels), got {value!r}")
        for name in ("fx", "fy"):
            value = getattr(self, name)
            if not _is_number(value) or not value > 0:
                raise ValueError(f"CameraIntrinsics.{name}: expected a positive focal length in pixels, got {value!r}")
        for name in ("cx", "cy"):
            if not _is_number(getattr(self, name)):
                raise ValueError(f"CameraIntrinsics.{name}: expected a finite number of pixels, got "
                                 f"{getattr(self, name)!r}")
        distortion = np.asarray(self.distortion, dtype=np.float64).reshape(-1)
        if distortion.shape != (DISTORTION_SIZE,) or not np.all(np.isfinite(distortion)):
            raise ValueError(f"CameraIntrinsics.distortion: expected {DISTORTION_SIZE} finite numbers "
                             f"[k1, k2, p1, p2, k3], got {np.asarray(self.distortion).tolist()}")
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        for name in ("fx", "fy", "cx", "cy"):
            object.__setattr__(self, name, float(getattr(self, name)))
        object.__setattr__(self, "distortion", distortion)

    @property
    def camera_matrix(self) -> np.ndarray:
        """OpenCV's camera matrix ``K (3, 3)`` in pixels."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def size(self) -> tuple[int, int]:
        """``(width, height)`` in pixels, the order OpenCV's functions take."""
        return self.width, self.height

    @property
    def has_distortion(self) -> bool:
        """Whether any distortion coefficient is non-zero."""
        return bool(np.any(self.distortion != 0.0))


@dataclass(frozen=True, eq=False)
class CameraCalibration:
    """One camera's calibration: its intrinsics and, once known, ``T_base_camera (7,)``, the camera's pose in the
    arm's base frame (m, wxyz; camera frame x right, y down, z forward). ``None`` until the extrinsics are measured
    (``hydrosoft-stack calibrate camera`` writes the intrinsics only)."""

    intrinsics: CameraIntrinsics
    T_base_camera: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.T_base_camera is not None:
            object.__setattr__(self, "T_base_camera", check_pose(self.T_base_camera, "T_base_camera"))


def load_calibration(path: str | Path, require_extrinsics: bool = True) -> CameraCalibration:
    """Read a calibration TOML file (format in ``drivers/camera/README.md``).

    Args:
        path: the file.
        require_extrinsics: raise when the ``[extrinsics]`` table is missing (the tracker needs it).

    Raises:
        CalibrationFileError: naming the file and the key (``intrinsics.fx``, ``extrinsics.T_base_camera``, ...)
            when the file is missing, is not TOML, lacks a key or holds a bad value.
    """
    path = Path(path)
    try:
        document = tomllib.loads(path.read_text())
    except FileNotFoundError as error:
        raise CalibrationFileError(f"{path}: no such calibration file") from error
    except tomllib.TOMLDecodeError as error:
        raise CalibrationFileError(f"{path}: not valid TOML: {error}") from error
    table = _table(document, "intrinsics", path)
    values = {}
    for key in ("width", "height", "fx", "fy", "cx", "cy", "distortion"):
        if key not in table:
            raise CalibrationFileError(f"{path}: missing key intrinsics.{key}")
        values[key] = table[key]
    unknown = sorted(set(table) - set(values))
    if unknown:
        raise CalibrationFileError(f"{path}: unknown key intrinsics.{unknown[0]}")
    for key in ("width", "height"):
        if isinstance(values[key], bool) or not isinstance(values[key], int) or values[key] <= 0:
            raise CalibrationFileError(f"{path}: intrinsics.{key} must be a positive integer (pixels), "
                                       f"got {values[key]!r}")
    for key in ("fx", "fy", "cx", "cy"):
        if not _is_number(values[key]):
            raise CalibrationFileError(f"{path}: intrinsics.{key} must be a finite number (pixels), got "
                                       f"{values[key]!r}")
    for key in ("fx", "fy"):
        if values[key] <= 0:
            raise CalibrationFileError(f"{path}: intrinsics.{key} must be a positive focal length (pixels), got "
                                       f"{values[key]!r}")
    if not _is_number_list(values["distortion"], DISTORTION_SIZE):
        raise CalibrationFileError(f"{path}: intrinsics.distortion must be {DISTORTION_SIZE} finite numbers "
                                   f"[k1, k2, p1, p2, k3], got {values['distortion']!r}")
    intrinsics = CameraIntrinsics(**values)
    if "extrinsics" not in document:
        if require_extrinsics:
            raise CalibrationFileError(f"{path}: missing table [extrinsics] (key extrinsics.T_base_camera)")
        return CameraCalibration(intrinsics)
    extrinsics = _table(document, "extrinsics", path)
    if "T_base_camera" not in extrinsics:
        raise CalibrationFileError(f"{path}: missing key extrinsics.T_base_camera")
    unknown = sorted(set(extrinsics) - {"T_base_camera"})
    if unknown:
        raise CalibrationFileError(f"{path}: unknown key extrinsics.{unknown[0]}")
    pose = extrinsics["T_base_camera"]
    if not _is_number_list(pose, 7):
        raise CalibrationFileError(f"{path}: extrinsics.T_base_camera must be 7 finite numbers "
                                   f"[x, y, z, qw, qx, qy, qz], got {pose!r}")
    try:
        return CameraCalibration(intrinsics, check_pose(np.array(pose, dtype=np.float64), "T_base_camera"))
    except ValueError as error:
        raise CalibrationFileError(f"{path}: extrinsics.{error}") from error


def save_calibration(path: str | Path, calibration: CameraCalibration, comment: str = "") -> None:
    """Write ``calibration`` as a TOML file that ``load_calibration`` reads back exactly (floats as ``repr``).

    ``comment`` (any lines) is written at the top as TOML comments, e.g. how the file was made.
    """
    intrinsics = calibration.intrinsics
    lines = [f"# {line}" for line in comment.splitlines()]
    lines += [
        "[intrinsics]",
        f"width = {intrinsics.width}",
        f"height = {intrinsics.height}",
        f"fx = {intrinsics.fx!r}",
        f"fy = {intrinsics.fy!r}",
        f"cx = {intrinsics.cx!r}",
        f"cy = {intrinsics.cy!r}",
        f"distortion = [{', '.join(repr(float(v)) for v in intrinsics.distortion)}]",
    ]
    if calibration.T_base_camera is not None:
        lines += ["", "[extrinsics]",
                  f"T_base_camera = [{', '.join(repr(float(v)) for v in calibration.T_base_camera)}]"]
    Path(path).write_text("\n".join(lines) + "\n")


@dataclass(frozen=True)
class OpenCVCameraConfig:
    """Settings of ``OpenCVCamera``.

    source: a device index (``0`` is ``/dev/video0``), or a string: a file, an image-sequence pattern such as
        ``frames/%04d.png``, or a stream URL (``rtsp://...``). Files and sequences are played back at ``fps``.
    width, height: requested resolution in pixels (``None`` keeps the device's default). fps: requested frame rate
        (Hz); also the playback rate of files.
    exposure: the device's ``CAP_PROP_EXPOSURE`` value (its own units, V4L2: 100 us steps), ``None`` for auto.
    max_age_ms: ``read`` raises ``Stale`` when no frame newer than the last one returned arrives within this time,
        or when the newest frame is older than this. Keep it above two frame periods.
    open_timeout_s: how long ``connect`` waits for the device to open and deliver a first frame.
    """

    source: int | str = 0
    width: int | None = None
    height: int | None = None
    fps: float = 30.0
    exposure: float | None = None
    max_age_ms: float = 500.0
    open_timeout_s: float = 5.0

    def __post_init__(self) -> None:
        if isinstance(self.source, bool) or not isinstance(self.source, (int, str)) or self.source == "":
            raise ValueError(f"OpenCVCameraConfig.source: expected a device index or a path/URL, got {self.source!r}")
        for name in ("width", "height"):
            value = getattr(self, name)
            if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value <= 0):
                raise ValueError(f"OpenCVCameraConfig.{name}: expected a positive integer or None, got {value!r}")
        if not _is_number(self.fps) or self.fps <= 0:
            raise ValueError(f"OpenCVCameraConfig.fps: expected a positive rate in Hz, got {self.fps!r}")
        if self.exposure is not None and not _is_number(self.exposure):
            raise ValueError(f"OpenCVCameraConfig.exposure: expected a number or None, got {self.exposure!r}")
        if not _is_number(self.max_age_ms) or self.max_age_ms < 2 * 1000.0 / self.fps:
            raise ValueError(f"OpenCVCameraConfig.max_age_ms: {self.max_age_ms!r} must be at least two frame "
                             f"periods ({2 * 1000.0 / self.fps:.1f} ms at {self.fps} Hz)")
        if not _is_number(self.open_timeout_s) or self.open_timeout_s <= 0:
            raise ValueError(f"OpenCVCameraConfig.open_timeout_s: expected a positive duration, got "
                             f"{self.open_timeout_s!r}")


@dataclass(frozen=True)
class SimCameraConfig:
    """Settings of ``SimCamera``: frame rate (Hz) and the render options of ``render.RenderOptions``'s fields.

    noise_std: Gaussian pixel noise, grey levels (0-255). blur_sigma_px: Gaussian blur, pixels (0 = none).
    seed: seed of the noise generator (the same seed and poses give the same images).
    table_height_m: height of the table top in the base frame (m; drawn as a grey plane), ``None`` for no table.
    grey: a monochrome camera: frames ``(H, W)`` uint8 grey instead of ``(H, W, 3)`` BGR (the same grey levels).
    """

    fps: float = 30.0
    noise_std: float = 2.0
    blur_sigma_px: float = 0.6
    seed: int = 0
    table_height_m: float | None = 0.0
    grey: bool = False

    def __post_init__(self) -> None:
        if not _is_number(self.fps) or self.fps <= 0:
            raise ValueError(f"SimCameraConfig.fps: expected a positive rate in Hz, got {self.fps!r}")
        for name in ("noise_std", "blur_sigma_px"):
            value = getattr(self, name)
            if not _is_number(value) or value < 0:
                raise ValueError(f"SimCameraConfig.{name}: expected a non-negative number, got {value!r}")
        if self.table_height_m is not None and not _is_number(self.table_height_m):
            raise ValueError(f"SimCameraConfig.table_height_m: expected metres or None, got {self.table_height_m!r}")


def _is_number(value: object) -> bool:
    """A finite int or float (not a bool)."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        return False
    return math.isfinite(value)


def _is_number_list(value: object, size: int) -> bool:
    """A list of ``size`` finite numbers."""
    return isinstance(value, list) and len(value) == size and all(_is_number(v) for v in value)


def _table(document: dict, key: str, path: Path) -> dict:
    """The TOML table ``[key]`` of ``document``, or a ``CalibrationFileError`` naming it."""
    if key not in document:
        raise CalibrationFileError(f"{path}: missing table [{key}]")
    if not isinstance(document[key], dict):
        raise CalibrationFileError(f"{path}: {key} must be a table [{key}], got {type(document[key]).__name__}")
    return document[key]
