"""The reference membrane, captured on request: the real bubble's undeformed depth image, taken while nothing
touches it, and its file.

``capture_reference`` reads N frames from a connected ``DepthCamera`` and keeps, per pixel, the median depth of the
frames in which the pixel had a return (count > 0); a pixel without a return in at least half of them is NaN (no
return). The median rejects the camera's outliers (flying pixels, multipath) that a mean would smear in.

File (``save_reference`` / ``load_reference``): a NumPy ``.npz`` archive holding ``reference_m`` ``(H, W)`` float32
(m along the optical axis, NaN = no return), ``depth_scale_m`` (m per count of the frames it came from), ``frames``
(how many) and ``captured_unix_ns`` (wall-clock capture time, ns since the Unix epoch: a file outlives the process,
so its time is the wall clock's; ``Reference.stamp_ns`` maps it onto ``time.monotonic_ns``).
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hydrosoft.drivers.base import DepthCamera
from hydrosoft.drivers.errors import ProtocolError

#: A pixel needs a return in at least this fraction of the frames, else it is NaN in the reference.
MIN_RETURN_FRACTION = 0.5
#: The arrays and values of a reference file.
FILE_KEYS = ("reference_m", "depth_scale_m", "frames", "captured_unix_ns")


class ReferenceFileError(ValueError):
    """A reference file that cannot be used; the message names the file and the bad key."""


@dataclass(frozen=True, eq=False)
class Reference:
    """A captured reference. reference_m: ``(H, W)`` float32, m along the optical axis, NaN = no return.
    depth_scale_m: m per count of the frames it was taken from. frames: how many. captured_unix_ns: when
    (wall clock, ns since the Unix epoch)."""

    reference_m: np.ndarray
    depth_scale_m: float
    frames: int
    captured_unix_ns: int

    def stamp_ns(self) -> int:
        """The capture time on this host's ``time.monotonic_ns`` clock (negative if before this boot)."""
        return time.monotonic_ns() - (time.time_ns() - self.captured_unix_ns)


def median_depth_m(counts: np.ndarray, depth_scale_m: float) -> np.ndarray:
    """The per-pixel median depth ``(H, W)`` float32 (m) of ``counts (N, H, W)`` uint16 (0 = no return), over the
    frames with a return; NaN where fewer than ``MIN_RETURN_FRACTION`` of the frames have one."""
    depth = counts.astype(np.float32) * np.float32(depth_scale_m)
    returned = counts > 0
    depth[~returned] = np.nan
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN pixels: NaN is the answer
        median = np.nanmedian(depth, axis=0)
    median[returned.mean(axis=0) < MIN_RETURN_FRACTION] = np.nan
    return median.astype(np.float32)


async def capture_reference(camera: DepthCamera, frames: int = 30) -> np.ndarray:
    """The undeformed membrane's depth image ``(H, W)`` float32 (m, NaN = no return) from ``frames`` consecutive
    frames of the connected ``camera``, taken with nothing touching the membrane (module docstring).

    Raises:
        ValueError: ``frames`` is not a positive integer.
        ProtocolError: the frames change size or depth unit on the way.
        DriverError: whatever the camera's ``read`` raises (``Stale``, ``NotConnected``, ...).
    """
    if isinstance(frames, bool) or not isinstance(frames, int) or frames < 1:
        raise ValueError(f"capture_reference: frames must be a positive integer, got {frames!r}")
    first = await camera.read()
    stack = np.empty((frames, *first.depth.shape), np.uint16)
    stack[0] = first.depth
    for index in range(1, frames):
        frame = await camera.read()
        if frame.depth.shape != first.depth.shape or frame.depth_scale_m != first.depth_scale_m:
            raise ProtocolError(f"capture_reference: frame {index} is {frame.depth.shape} in units of "
                                f"{frame.depth_scale_m} m, the first was {first.depth.shape} in "
                                f"{first.depth_scale_m} m")
        stack[index] = frame.depth
    return median_depth_m(stack, first.depth_scale_m)


def save_reference(path: str | Path, reference: Reference) -> Path:
    """Write ``reference`` as a ``.npz`` file (module docstring); returns the path written (``.npz`` appended
    when missing, as NumPy does)."""
    path = Path(path)
    if path.suffix != ".npz":
        path = path.with_name(path.name + ".npz")
    np.savez(path, reference_m=np.asarray(reference.reference_m, np.float32),
             depth_scale_m=np.float64(reference.depth_scale_m), frames=np.int64(reference.frames),
             captured_unix_ns=np.int64(reference.captured_unix_ns))
    return path


def load_reference(path: str | Path) -> Reference:
    """Read a reference file written by ``save_reference``.

    Raises:
        ReferenceFileError: naming the file and the key when the file is missing, is not a ``.npz`` archive,
            lacks a key or holds a bad value (a reference that is not ``(H, W)`` float, a unit that is not a
            positive length).
    """
    path = Path(path)
    try:
        loaded = np.load(path, allow_pickle=False)
    except FileNotFoundError as error:
        raise ReferenceFileError(f"{path}: no such reference file") from error
    except (OSError, ValueError) as error:
        raise ReferenceFileError(f"{path}: not a NumPy .npz file: {error}") from error
    if not isinstance(loaded, np.lib.npyio.NpzFile):
        raise ReferenceFileError(f"{path}: a reference file is a .npz archive of {FILE_KEYS}, this is a bare .npy "
                                 f"array without its depth unit and capture time")
    with loaded:
        missing = [key for key in FILE_KEYS if key not in loaded.files]
        if missing:
            raise ReferenceFileError(f"{path}: missing key {missing[0]}")
        values = {key: loaded[key] for key in FILE_KEYS}
    reference = values["reference_m"]
    if reference.ndim != 2 or reference.dtype.kind != "f":
        raise ReferenceFileError(f"{path}: reference_m must be an (H, W) float depth image (m), got "
                                 f"{reference.shape} {reference.dtype}")
    scale = float(values["depth_scale_m"])
    if not (math.isfinite(scale) and scale > 0):
        raise ReferenceFileError(f"{path}: depth_scale_m must be a positive length (m per count), got {scale!r}")
    return Reference(reference.astype(np.float32), scale, int(values["frames"]), int(values["captured_unix_ns"]))
