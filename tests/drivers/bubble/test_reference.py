"""The reference membrane captured on request (``drivers.bubble.reference``): the median of noisy frames with
dropouts and outliers lies close to the nominal membrane, pixels that rarely return are NaN, the file round-trips
with its depth unit and capture time, and bad files are refused by name. The frames come from a ``DepthCamera``
that plays back a list of rendered uint16 images, and once through the real ``OpenCVDepthCamera`` on a 16-bit PNG
sequence."""

from __future__ import annotations

import asyncio
import time

import cv2
import numpy as np
import pytest

from hydrosoft.drivers.base import DepthFrame
from hydrosoft.drivers.bubble.opencv_depth import OpenCVDepthCamera, OpenCVDepthConfig
from hydrosoft.drivers.bubble.reference import (
    Reference,
    ReferenceFileError,
    capture_reference,
    load_reference,
    save_reference,
)
from hydrosoft.drivers.bubble.render import PinholeDepth, reference_depth, to_counts
from hydrosoft.drivers.errors import ProtocolError

TEST_TIMEOUT_S = 10.0
CAMERA = PinholeDepth(160, 120, 40.0, 40.0, 79.5, 59.5)
RADII = (0.06, 0.045, 0.03)
LOOK_DOWN = (0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0)
SCALE_M = 1e-4
NOISE_M = 2e-4  # sim's depth noise
NOMINAL = reference_depth(CAMERA, RADII, LOOK_DOWN)


class PlayedCamera:
    """A ``DepthCamera`` that hands out ``images`` (uint16) one per ``read``."""

    def __init__(self, images: list[np.ndarray], scales: list[float] | None = None) -> None:
        self.images = list(images)
        self.scales = scales or [SCALE_M] * len(images)
        self.reads = 0

    async def connect(self) -> None:
        pass

    async def read(self) -> DepthFrame:
        index, self.reads = self.reads, self.reads + 1
        return DepthFrame(self.images[index], self.scales[index], time.monotonic_ns(), None)

    async def close(self) -> None:
        pass


def noisy_frames(count: int, seed: int = 0) -> list[np.ndarray]:
    """``count`` frames of the nominal membrane with Gaussian noise, 5 % dropouts (0) and 1 % outliers (+-20 mm);
    pixel (3, 4) never returns, pixel (5, 6) returns in a third of the frames."""
    rng = np.random.default_rng(seed)
    frames = []
    for index in range(count):
        depth = NOMINAL + rng.normal(0.0, NOISE_M, NOMINAL.shape)
        outliers = rng.random(NOMINAL.shape) < 0.01
        depth[outliers] += rng.choice([-0.02, 0.02], outliers.sum())
        counts = to_counts(depth, SCALE_M)
        counts[rng.random(NOMINAL.shape) < 0.05] = 0
        counts[3, 4] = 0
        if index % 3:
            counts[5, 6] = 0
        frames.append(counts)
    return frames


def run(coroutine):
    return asyncio.run(asyncio.wait_for(coroutine, TEST_TIMEOUT_S))


def test_the_median_of_noisy_frames_lies_close_to_the_nominal_membrane():
    frames = noisy_frames(15)
    camera = PlayedCamera(frames)
    reference = run(capture_reference(camera, frames=15))
    assert camera.reads == 15
    assert reference.shape == (120, 160) and reference.dtype == np.float32
    assert np.isnan(reference[3, 4]) and np.isnan(reference[5, 6]) and np.isnan(reference).sum() == 2
    error_m = np.abs(reference - NOMINAL)[np.isfinite(reference)]
    assert error_m.max() < 3 * NOISE_M  # no outlier survives the median
    assert np.median(error_m) < 0.5 * NOISE_M  # the median of 15 frames is ~3x less noisy than one frame
    single_m = np.abs(frames[0] * SCALE_M - NOMINAL)[frames[0] > 0]
    assert error_m.mean() < 0.5 * single_m.mean()


def test_frames_that_change_size_or_unit_and_a_bad_count_are_refused():
    frames = noisy_frames(2)
    with pytest.raises(ProtocolError, match="frame 1"):
        run(capture_reference(PlayedCamera([frames[0], frames[1][:60]]), frames=2))
    with pytest.raises(ProtocolError, match="units of 0.001 m"):
        run(capture_reference(PlayedCamera(frames, [SCALE_M, 1e-3]), frames=2))
    with pytest.raises(ValueError, match="positive integer"):
        run(capture_reference(PlayedCamera(frames), frames=0))


def test_the_file_round_trips_with_its_unit_and_capture_time(tmp_path):
    reference_m = NOMINAL.copy()
    reference_m[0, 0] = np.nan
    captured_unix_ns = time.time_ns() - 60_000_000_000  # a minute ago
    path = save_reference(tmp_path / "bubble_reference", Reference(reference_m, SCALE_M, 30, captured_unix_ns))
    assert path == tmp_path / "bubble_reference.npz"
    loaded = load_reference(path)
    np.testing.assert_array_equal(loaded.reference_m, reference_m)  # NaN where it was NaN
    assert (loaded.depth_scale_m, loaded.frames, loaded.captured_unix_ns) == (SCALE_M, 30, captured_unix_ns)
    age_s = (time.monotonic_ns() - loaded.stamp_ns()) / 1e9
    assert age_s == pytest.approx(60.0, abs=1.0)


def test_bad_files_are_refused_by_name(tmp_path):
    with pytest.raises(ReferenceFileError, match="no such reference file"):
        load_reference(tmp_path / "absent.npz")
    np.save(tmp_path / "bare.npy", NOMINAL)
    with pytest.raises(ReferenceFileError, match="bare .npy array"):
        load_reference(tmp_path / "bare.npy")
    np.savez(tmp_path / "partial.npz", reference_m=NOMINAL, depth_scale_m=SCALE_M)
    with pytest.raises(ReferenceFileError, match="missing key frames"):
        load_reference(tmp_path / "partial.npz")
    np.savez(tmp_path / "flat.npz", reference_m=NOMINAL.ravel(), depth_scale_m=SCALE_M, frames=1, captured_unix_ns=0)
    with pytest.raises(ReferenceFileError, match=r"reference_m must be an \(H, W\) float"):
        load_reference(tmp_path / "flat.npz")
    (tmp_path / "text.npz").write_text("not numpy")
    with pytest.raises(ReferenceFileError, match="text.npz: not a NumPy"):
        load_reference(tmp_path / "text.npz")


def test_capture_through_the_opencv_driver_on_a_png_sequence(tmp_path):
    for index, frame in enumerate(noisy_frames(9, seed=1)):
        assert cv2.imwrite(str(tmp_path / f"frame_{index:04d}.png"), frame)
    camera = OpenCVDepthCamera(OpenCVDepthConfig(source=str(tmp_path / "frame_%04d.png"), width=160, height=120,
                                                 fps=100.0, depth_scale_m=SCALE_M))

    async def scenario():
        await camera.connect()
        try:
            return await capture_reference(camera, frames=9)
        finally:
            await camera.close()

    reference = run(scenario())
    finite = np.isfinite(reference)
    assert np.isnan(reference[3, 4]) and np.isnan(reference[5, 6])
    assert finite.mean() > 0.999  # else only pixels that by chance dropped out in 5 of the 9 frames
    assert np.abs(reference - NOMINAL)[finite].max() < 3 * NOISE_M
