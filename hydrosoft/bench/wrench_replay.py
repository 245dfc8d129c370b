"""Replay of ``collect wrench`` recordings through a contact model, shared by ``bench wrench`` and ``fit``.

A recorded trajectory is replayed in its benchmark object's scene (``wrench_scenes.wrench_scene``): from the recorded
tare pose (out of contact, no force) the bubble and the object are moved kinematically to each recorded pose
(``dynamics.advance_forces``) and the model's wrench on the bubble is read about its frame's origin, in its frame
(``dynamics.body_wrenches``, as sim_world's FT 300 reports it). The measurement it is compared with is the recorded
wrench minus the trajectory's tare sample, moved from the sensor's frame to the TCP frame
(``RecordingInfo.tcp_in_sensor``). Errors are RMSEs over a trajectory's steps, the tare sample excluded.

``replay_tcp_wrenches`` is differentiable in the bubble's material (``contact.Material``): ``fit`` minimises the
wrench error over E, K and mu through it.
"""

from __future__ import annotations

import statistics
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from hydrosoft.drivers.poses import quat_to_matrix

DEFAULT_SUBSTEPS = 1  # on sim recordings 1, 4 and 8 agree within 1e-4 N: the arm's path between samples is straight


# --- frames and errors (numpy) --------------------------------------------------------------------------------------


def sensor_to_tcp(wrenches: np.ndarray, tcp_in_sensor: Sequence[float]) -> np.ndarray:
    """Wrenches ``(..., 6)`` [N, N m] about the sensor's origin in its frame, moved to about the TCP's origin in the TCP
    frame; ``tcp_in_sensor (7,)`` is the TCP frame's pose in the sensor frame (m, wxyz)."""
    pose = np.asarray(tcp_in_sensor, dtype=np.float64)
    R, p = quat_to_matrix(pose[3:]), pose[:3]
    force, torque = wrenches[..., :3], wrenches[..., 3:]
    return np.concatenate([force @ R, (torque - np.cross(p, force)) @ R], axis=-1)


def measured_tcp_wrenches(wrenches: np.ndarray, tcp_in_sensor: Sequence[float], pretared: bool = False
                          ) -> np.ndarray:
    """Measured wrenches ``(K + 1, 6)`` (sensor frame) minus the tare row 0 (as they are when ``pretared``: tared
    before the trajectory), in the TCP frame about its origin."""
    return sensor_to_tcp(wrenches if pretared else wrenches - wrenches[0], tcp_in_sensor)


def rmse(errors: np.ndarray) -> float:
    """Root mean square over rows of the row norms of ``errors (K, d)``."""
    return float(np.sqrt(np.mean(np.sum(np.square(errors), axis=-1))))


def trajectory_errors(predicted: np.ndarray, measured: np.ndarray) -> dict[str, float]:
    """RMSEs of one trajectory over its rows 1..K (row 0 is the tare), wrenches ``(K + 1, 6)`` in the TCP frame:
    ``force_n`` (3-vector), ``torque_nm`` (3-vector), ``shear_n`` (the TCP-frame x, y force)."""
    error = predicted[1:] - measured[1:]
    return {"force_n": rmse(error[:, :3]), "torque_nm": rmse(error[:, 3:]), "shear_n": rmse(error[:, :2])}


def mean_and_std(values: Sequence[float]) -> tuple[float, float]:
    """Mean and sample standard deviation (0 for one value)."""
    return statistics.fmean(values), statistics.stdev(values) if len(values) > 1 else 0.0


# --- recordings -----------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ObjectRecordings:
    """Every complete trajectory of one benchmark object: ``info`` of its first recording, the trajectories
    (``wrench_recording.RecordedTrajectory``) and their measured TCP-frame wrenches ``(K + 1, 6)`` each
    (``measured_tcp_wrenches``), in the same order; ``spacing_m``: the surface spacing to replay them at (m);
    ``modes``: the recording modes of its files (``sim``, ``lab``)."""

    object: str
    info: object
    trajectories: list
    measured: list[np.ndarray]
    spacing_m: float
    modes: tuple[str, ...]


def recording_files(paths: Sequence[Path]) -> list[Path]:
    """The recording files named by ``paths`` (files, or folders of ``wrench-*.mcap``); ValueError naming a path
    that is neither or a folder without recordings."""
    files = []
    for path in paths:
        path = Path(path)
        if path.is_dir():
            found = sorted(path.glob("wrench-*.mcap"))
            if not found:
                raise ValueError(f"{path}: no wrench-*.mcap recording in this folder")
            files += found
        elif path.is_file():
            files.append(path)
        else:
            raise ValueError(f"{path}: no such recording")
    return files


def load_recordings(files: Sequence[Path], spacing: float | None = None, read=None) -> list[ObjectRecordings]:
    """The trajectories of ``files`` per benchmark object, in ``BENCH_OBJECTS`` order (read only). ``spacing``: the
    replay's surface spacing (m); None takes the sim plant's, recorded in the file, or ``SPACING_M`` for lab files.
    ``read``: path -> ``(RecordingInfo, [RecordedTrajectory])`` (default ``read_wrench_recording``). ValueError when
    no file holds a complete trajectory."""
    from hydrosoft.bench.wrench_recording import read_wrench_recording
    from hydrosoft.bench.wrench_scenes import BENCH_OBJECTS, SPACING_M

    read = read or read_wrench_recording
    by_object: dict[str, list] = {}
    infos, modes = {}, {}
    for path in files:
        info, trajectories = read(path)
        by_object.setdefault(info.object, []).extend(trajectories)
        infos.setdefault(info.object, info)
        modes.setdefault(info.object, set()).add(info.mode)
    names = [n for n in BENCH_OBJECTS if by_object.get(n)]
    if not names:
        raise ValueError(f"no complete trajectory in {', '.join(str(p) for p in files)}")
    groups = []
    for name in names:
        info = infos[name]
        groups.append(ObjectRecordings(
            object=name, info=info, trajectories=by_object[name],
            measured=[measured_tcp_wrenches(t.wrenches, info.tcp_in_sensor, t.pretared) for t in by_object[name]],
            spacing_m=spacing if spacing is not None else (info.plant_spacing_m or SPACING_M),
            modes=tuple(sorted(modes[name]))))
    return groups


# --- the replay (torch) -------------------------------------------------------------------------------------------


def replay_tcp_wrenches(object_name: str, object_poses, bubble_poses, contact: str, spacing: float,
                        substeps: int = DEFAULT_SUBSTEPS, material=None):
    """Replay a batch of trajectories of one object through contact model ``contact``, differentiably.

    Args:
        object_name: a ``wrench_scenes.BENCH_OBJECTS`` key.
        object_poses, bubble_poses: ``(B, K + 1, 7)`` world poses per trajectory and step (m, wxyz), arrays or
            tensors (gradients flow to them); row 0 must be out of contact (the replay starts there without force).
        contact: a ``hydrosoft.contact.MODELS`` name.
        spacing: the object's surface spacing (m).
        substeps: ``dynamics.advance_forces`` calls per recorded step, at equally spaced poses between the two
            recorded ones (straight line, shortest rotation).
        material: the bubble's ``contact.Material`` (E, K, mu each ``(1,)`` float64 tensors; gradients flow to
            them), or None for the scene's (``wrench_scenes.BUBBLE_E``, ``BUBBLE_K``, ``BUBBLE_MU``).

    Returns:
        ``(B, K + 1, 6)`` float64 tensor: the predicted wrench on the bubble [N, N m] about its frame's origin, in
        its frame.
    """
    import torch

    from hydrosoft.bench.wrench_scenes import wrench_scene
    from hydrosoft.dynamics import advance_forces, body_wrenches, press_in
    from hydrosoft.geometry import se3
    from hydrosoft.scene import compile_scene

    if substeps < 1:
        raise ValueError(f"substeps must be at least 1, got {substeps}")
    objects = torch.as_tensor(object_poses, dtype=torch.float64)  # a tensor keeps its gradient (the fit's offset)
    bubbles = torch.as_tensor(bubble_poses, dtype=torch.float64)
    scene = wrench_scene(object_name, contact, spacing, object_pose=objects[0, 0].tolist(),
                         bubble_pose=bubbles[0, 0].tolist())
    model, _, _ = compile_scene(scene)
    if material is not None:
        model = replace(model, material=material)
    state = press_in(model, objects[:, 0], bubbles[:, 0:1])

    def tcp_wrench(state) -> torch.Tensor:
        w = body_wrenches(model, state)[:, 0]
        R = se3.quat_to_matrix(state.body_poses[:, 0, 3:])
        return torch.cat([(R.mT @ w[:, :3, None])[..., 0], (R.mT @ w[:, 3:, None])[..., 0]], dim=-1)

    def delta(start: torch.Tensor, end: torch.Tensor) -> torch.Tensor:
        turn = se3.quat_multiply(end[..., 3:], se3.quat_conjugate(start[..., 3:]))
        return torch.cat([end[..., :3] - start[..., :3], se3.so3_log(turn)], dim=-1)

    out = [tcp_wrench(state)]
    for k in range(1, bubbles.shape[1]):
        d_object, d_bubble = delta(objects[:, k - 1], objects[:, k]), delta(bubbles[:, k - 1], bubbles[:, k])
        for j in range(1, substeps + 1):
            fraction = j / substeps
            object_pose = se3.retract(objects[:, k - 1], fraction * d_object)
            bubble_pose = se3.retract(bubbles[:, k - 1], fraction * d_bubble)
            state = advance_forces(model, state, object_pose, bubble_pose.unsqueeze(1))
        out.append(tcp_wrench(state))
    return torch.stack(out, dim=1)


def predict_tcp_wrenches(object_name: str, object_poses: np.ndarray, bubble_poses: np.ndarray, contact: str,
                         spacing: float, substeps: int = DEFAULT_SUBSTEPS, material=None) -> np.ndarray:
    """``replay_tcp_wrenches`` without gradients, as a ``(B, K + 1, 6)`` float64 array."""
    import torch

    with torch.no_grad():
        return replay_tcp_wrenches(object_name, object_poses, bubble_poses, contact, spacing, substeps,
                                   material).numpy()


def length_batches(trajectories: Sequence) -> list[list[int]]:
    """Indices of ``trajectories`` grouped by length (``len(t.phases)``), shortest first, and by whether they are
    ``pretared`` (those last): each group replays as one batch."""
    keys = sorted({(t.pretared, len(t.phases)) for t in trajectories})
    return [[i for i, t in enumerate(trajectories) if (t.pretared, len(t.phases)) == key] for key in keys]


def predict_grouped(name: str, trajectories: Sequence, model: str, spacing: float, substeps: int,
                    material=None) -> list[np.ndarray]:
    """Predictions ``(K + 1, 6)`` per trajectory, replayed in batches of trajectories of equal length."""
    predicted: list[np.ndarray | None] = [None] * len(trajectories)
    for members in length_batches(trajectories):
        batch = predict_tcp_wrenches(name, np.stack([trajectories[i].object_poses for i in members]),
                                     np.stack([trajectories[i].bubble_poses for i in members]), model, spacing,
                                     substeps, material)
        for row, i in enumerate(members):
            predicted[i] = batch[row]
    return predicted
