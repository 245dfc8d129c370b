"""Synthetic ``collect wrench`` recordings with a known bubble material: what the fit's tests and its noise
benchmark fit to.

The plant is the NH model itself at a chosen material (E, K, mu), replayed at ``PLANT_SUBSTEPS`` steps per recorded
step (finer than the fit's replay) along press-and-shear trajectories (``wrench_scenes.press_and_shear``) on a clamped
benchmark object. Each recorded wrench is what ``collect wrench`` stores: the mean of ``FRAMES_PER_SAMPLE`` FT 300
frames, each the true wrench plus the FT 300's noise at ``noise_scale`` rounded to the frame's resolution: the
noise model the FT 300 simulator uses (``hydrosoft.drivers.robotiq_ft300.noise``). The file is written by the recording
writer (``wrench_recording.WrenchRecordingWriter``) with the TCP frame at the sensor's origin. With ``pose_noise``
the recorded object poses are what a tracker reports (``tracked_poses``): the plant pressed the true, clamped
object, but every sample's recorded pose carries Gaussian position and rotation noise, drawn from a generator of its
own so the wrench noise of a seed stays the same. With ``pose_offset_m`` every recorded object pose is moved by
the same constant offset, as a tracker with a constant error reports a still object.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from hydrosoft.bench.wrench_recording import RecordingInfo, WrenchRecordingWriter, WrenchSample
from hydrosoft.bench.wrench_replay import predict_tcp_wrenches
from hydrosoft.bench.wrench_scenes import bench_object, press_and_shear, sample_press_and_shear
from hydrosoft.contact import Material
from hydrosoft.drivers.robotiq_ft300.noise import frame_noise, quantized

FRAMES_PER_SAMPLE = 5  # collect wrench averages a sample over 0.05 s of frames at 100 Hz
PLANT_SUBSTEPS = 4
PLANT_SPACING_M = 0.00625  # the sim plant's object surface spacing with deploy/sim.toml
IDENTITY = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
POSE_NOISE_STREAM = 0x7AC  # first word of the tracker noise generator's seed


def tracked_poses(poses: np.ndarray, rng: np.random.Generator, position_m: float, rotation_rad: float) -> np.ndarray:
    """Poses ``(..., 7)`` (m, wxyz) as a tracker reports them: each position plus Gaussian noise of ``position_m``
    per axis, each orientation turned by a rotation vector with Gaussian noise of ``rotation_rad`` per axis (in the
    world frame)."""
    from scipy.spatial.transform import Rotation

    flat = poses.reshape(-1, 7)
    position = flat[:, :3] + rng.normal(size=(len(flat), 3)) * position_m
    turn = Rotation.from_rotvec(rng.normal(size=(len(flat), 3)) * rotation_rad)
    quaternion = (turn * Rotation.from_quat(flat[:, 3:], scalar_first=True)).as_quat(scalar_first=True)
    quaternion *= np.where(np.sum(quaternion * flat[:, 3:], axis=1, keepdims=True) < 0, -1.0, 1.0)
    return np.concatenate([position, quaternion], axis=1).reshape(poses.shape)


def measured_wrenches(truth: np.ndarray, rng: np.random.Generator | None, noise_scale: float = 1.0) -> np.ndarray:
    """What the recording stores for true wrenches ``truth (..., 6)`` (N, N m): the mean of ``FRAMES_PER_SAMPLE``
    frames, each with the FT 300's noise at ``noise_scale`` (``noise.frame_noise``; none without ``rng``) and
    quantised (``noise.quantized``), as the simulated FT 300 sends them."""
    if rng is None:
        return quantized(truth)
    return np.mean(quantized(truth[None] + frame_noise(rng, (FRAMES_PER_SAMPLE, *truth.shape), noise_scale)), axis=0)


def synthetic_trajectories(object_name: str, material: dict[str, float], kinds: Sequence[str], steps: int,
                           seed: int, noise_scale: float = 0.0, contact: str = "nh",
                           plant_substeps: int = PLANT_SUBSTEPS):
    """``(params, bubbles, objects, measured)``: ``len(kinds)`` press-and-shear trajectories of ``steps`` steps on
    ``object_name`` with the plant at ``material`` (E, K in Pa/m, mu): their ``PressAndShear`` parameters, bubble
    and object poses ``(B, steps + 1, 7)`` (base frame, m, wxyz; row 0 out of contact) and measured TCP-frame
    wrenches ``(B, steps + 1, 6)`` (N, N m). ``kinds``: each trajectory's second phase (``wrench_scenes.KINDS``, or
    ``"press"`` for pressing only); ``seed``: of the trajectories and the noise; ``noise_scale``: the FT 300's
    noise level (0: resolution only); ``plant_substeps``: the plant's steps per recorded step."""
    obj = bench_object(object_name)
    rng = np.random.default_rng(seed)
    params = [sample_press_and_shear(rng, steps, "shear" if kind == "press" else kind) for kind in kinds]
    params = [p if kind != "press" else replace(p, shear_m=0.0, twist_rad=0.0, press_steps=steps, shear_steps=0)
              for p, kind in zip(params, kinds)]
    bubbles = np.stack([press_and_shear(obj, p) for p in params])
    objects = np.broadcast_to(obj.pose(), bubbles.shape).copy()
    plant = Material(*(torch.tensor([float(material[name])], dtype=torch.float64) for name in ("E", "K", "mu")))
    truth = predict_tcp_wrenches(object_name, objects, bubbles, contact, PLANT_SPACING_M, plant_substeps, plant)
    measured = measured_wrenches(truth, rng if noise_scale > 0 else None, noise_scale)
    return params, bubbles, objects, measured


def write_synthetic_recording(path: str | Path, object_name: str, material: dict[str, float],
                              kinds: Sequence[str], steps: int, seed: int, noise_scale: float = 0.0,
                              contact: str = "nh", pose_noise: tuple[float, float] = (0.0, 0.0),
                              plant_substeps: int = PLANT_SUBSTEPS,
                              pose_offset_m: Sequence[float] = (0.0, 0.0, 0.0)) -> None:
    """Record ``synthetic_trajectories(object_name, material, kinds, steps, seed, noise_scale, contact,
    plant_substeps)`` to
    ``path`` in the ``collect wrench`` format. ``pose_noise``: ``(position m, rotation rad)`` per axis of the
    tracker noise on the recorded object poses (``tracked_poses``; none by default); ``pose_offset_m``: a constant
    offset (3 numbers, m, base frame) added to every recorded object position (none by default)."""
    params, bubbles, objects, measured = synthetic_trajectories(object_name, material, kinds, steps, seed,
                                                                noise_scale, contact, plant_substeps)
    if any(pose_noise):
        objects = tracked_poses(objects, np.random.default_rng((POSE_NOISE_STREAM, seed)), *pose_noise)
    objects[..., :3] += np.asarray(pose_offset_m, dtype=np.float64)
    info = RecordingInfo(object=object_name, config="synthetic", mode="sim", tcp_in_sensor=IDENTITY,
                         plant_spacing_m=PLANT_SPACING_M, seed=seed, epoch_offset_ns=0,
                         trajectories=[{"kind": kind, "material": dict(material)} for kind in kinds])
    with WrenchRecordingWriter(path, info) as writer:
        for i, p in enumerate(params):
            for k in range(steps + 1):
                phase = "start" if k == 0 else "press" if k <= p.press_steps else "shear"
                writer.add(WrenchSample(object=object_name, trajectory=i, step=k, phase=phase,
                                        stamp_ns=50_000_000 * k, bubble_pose=tuple(bubbles[i, k].tolist()),
                                        target_pose=tuple(bubbles[i, k].tolist()),
                                        object_pose=tuple(objects[i, k].tolist()),
                                        wrench=tuple(measured[i, k].tolist())))
