"""The wrench benchmark's recording: one MCAP file per object, written by ``hydrosoft-stack collect wrench`` and read
by ``hydrosoft-stack bench wrench``.

Layout of ``wrench-<object>.mcap``:

- one channel ``TOPIC`` (message encoding ``json``, schema encoding ``jsonschema``: ``SAMPLE_SCHEMA``, so standard
  viewers decode it), one message per recorded step of each trajectory: ``WrenchSample``;
- one metadata record ``METADATA_NAME`` naming the object and how it was recorded (``RecordingInfo``; MCAP metadata
  values are strings, so numbers and lists are JSON text).

Each trajectory starts with one sample out of contact (``phase = "start"``, step 0): the benchmark subtracts its
wrench from the trajectory's other samples (the tare: the bubble's weight and the sensor's offset in the lab). Times:
``stamp_ns`` is the host's ``time.monotonic_ns()`` when the sample was taken; MCAP ``log_time`` is the same stamp
plus the recording's offset to the Unix epoch (``RecordingInfo.epoch_offset_ns``), so viewers show the date.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

TOPIC = "wrench_bench/sample"
METADATA_NAME = "hydrosoft.wrench_bench"
SCHEMA_NAME = "hydrosoft.WrenchSample"
PHASES = ("start", "press", "shear")


def _vector(size: int, unit: str) -> dict[str, Any]:
    return {"type": "array", "items": {"type": "number"}, "minItems": size, "maxItems": size, "description": unit}


SAMPLE_SCHEMA = {
    "title": SCHEMA_NAME,
    "description": "One step of a press-and-shear trajectory of the wrench-transmission benchmark (paper Table II).",
    "type": "object",
    "properties": {
        "object": {"type": "string", "description": "benchmark object (hydrosoft.bench.wrench_scenes.BENCH_OBJECTS)"},
        "trajectory": {"type": "integer", "minimum": 0},
        "step": {"type": "integer", "minimum": 0, "description": "0: the out-of-contact tare sample"},
        "phase": {"type": "string", "enum": list(PHASES)},
        "stamp_ns": {"type": "integer", "description": "host time.monotonic_ns() when the sample was taken"},
        "bubble_pose": _vector(7, "measured TCP (bubble frame) pose, base frame: x, y, z (m), qw, qx, qy, qz"),
        "target_pose": _vector(7, "commanded TCP pose of this step, base frame: x, y, z (m), qw, qx, qy, qz"),
        "object_pose": _vector(7, "object pose, base frame: x, y, z (m), qw, qx, qy, qz"),
        "wrench": _vector(6, "measured wrench, F/T sensor frame: Fx, Fy, Fz (N), Mx, My, Mz (N m)"),
    },
    "required": ["object", "trajectory", "step", "phase", "stamp_ns", "bubble_pose", "target_pose", "object_pose",
                 "wrench"],
}


class WrenchSample(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """One recorded step (see ``SAMPLE_SCHEMA`` for units and frames)."""

    object: str
    trajectory: int
    step: int
    phase: str
    stamp_ns: int
    bubble_pose: tuple[float, ...]
    target_pose: tuple[float, ...]
    object_pose: tuple[float, ...]
    wrench: tuple[float, ...]


@dataclass(frozen=True)
class RecordingInfo:
    """How a recording was made. object: the benchmark object; config: the stack config's path; mode: ``sim`` or
    ``lab``; tcp_in_sensor: ``(7,)`` the TCP (bubble) frame in the F/T sensor's frame (identity in sim);
    plant_spacing_m: the sim plant's object surface spacing (m; None in the lab); seed: of the trajectories;
    epoch_offset_ns: Unix time minus ``time.monotonic_ns()`` when recording started; trajectories: each
    trajectory's parameters (``wrench_scenes.PressAndShear`` as a dict); config_toml: the config file's text."""

    object: str
    config: str
    mode: str
    tcp_in_sensor: tuple[float, ...]
    plant_spacing_m: float | None
    seed: int
    epoch_offset_ns: int
    trajectories: list[dict[str, Any]] = field(default_factory=list)
    config_toml: str = ""

    def to_metadata(self) -> dict[str, str]:
        """MCAP metadata: every value as a string (JSON text for numbers and lists)."""
        return {key: value if isinstance(value, str) else json.dumps(value) for key, value in asdict(self).items()}

    @classmethod
    def from_metadata(cls, data: dict[str, str]) -> RecordingInfo:
        """Read back ``to_metadata``'s strings; ValueError naming a missing or bad key."""
        values: dict[str, Any] = {}
        for name in cls.__dataclass_fields__:
            if name not in data:
                raise ValueError(f"metadata {METADATA_NAME} has no key {name!r}")
            text = data[name]
            values[name] = text if name in ("object", "config", "mode", "config_toml") else json.loads(text)
        values["tcp_in_sensor"] = tuple(values["tcp_in_sensor"])
        return cls(**values)


class WrenchRecordingWriter:
    """Writes one object's recording: ``WrenchRecordingWriter(path, info)``, ``add(sample)`` per step, ``close()``
    (or use it as a context manager). The file is complete only after ``close``."""

    def __init__(self, path: str | Path, info: RecordingInfo) -> None:
        from mcap.writer import Writer

        self.path = Path(path)
        self.info = info
        self._file = self.path.open("wb")
        self._writer = Writer(self._file)
        self._writer.start(profile="", library="hydrosoft-stack")
        schema = self._writer.register_schema(SCHEMA_NAME, "jsonschema", json.dumps(SAMPLE_SCHEMA).encode())
        self._channel = self._writer.register_channel(TOPIC, "json", schema)
        self._sequence = 0

    def add(self, sample: WrenchSample) -> None:
        """Append one step."""
        stamp = sample.stamp_ns + self.info.epoch_offset_ns
        self._writer.add_message(self._channel, log_time=stamp, publish_time=stamp, sequence=self._sequence,
                                 data=msgspec.json.encode(sample))
        self._sequence += 1

    def close(self) -> None:
        """Write the metadata record and the summary, and close the file."""
        self._writer.add_metadata(METADATA_NAME, self.info.to_metadata())
        self._writer.finish()
        self._file.close()

    def __enter__(self) -> WrenchRecordingWriter:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


@dataclass(frozen=True)
class RecordedTrajectory:
    """One trajectory read back: ``bubble_poses``, ``target_poses``, ``object_poses`` ``(K + 1, 7)``, ``wrenches``
    ``(K + 1, 6)`` (sensor frame, as measured), ``phases`` per row; row 0 is the tare sample, unless ``pretared``:
    then the wrenches were tared before the trajectory (a stack recording that starts in contact, its stream tared by
    the F/T reader out of contact), row 0 is in contact and is measured as it is, and the replay starts it pressed
    in (``dynamics.press_in``)."""

    object: str
    index: int
    bubble_poses: np.ndarray
    target_poses: np.ndarray
    object_poses: np.ndarray
    wrenches: np.ndarray
    phases: tuple[str, ...]
    pretared: bool = False


def read_wrench_recording(path: str | Path) -> tuple[RecordingInfo, list[RecordedTrajectory]]:
    """The recording's info and its trajectories in order. ValueError naming the file when it has no
    ``METADATA_NAME`` record, a sample does not decode, or a trajectory does not start with its tare sample."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    path = Path(path)
    info, samples = None, []
    try:
        with path.open("rb") as stream:
            reader = make_reader(stream)
            for record in reader.iter_metadata():
                if record.name == METADATA_NAME:
                    info = RecordingInfo.from_metadata(dict(record.metadata))
            stream.seek(0)
            for _schema, _channel, message in make_reader(stream).iter_messages(topics=[TOPIC]):
                samples.append(msgspec.json.decode(message.data, type=WrenchSample))
    except (McapError, msgspec.DecodeError, ValueError, OSError) as error:
        raise ValueError(f"{path}: not a wrench benchmark recording: {error}") from error
    if info is None:
        raise ValueError(f"{path}: no {METADATA_NAME} metadata record (not a wrench benchmark recording)")
    by_index: dict[int, list[WrenchSample]] = {}
    for sample in samples:
        by_index.setdefault(sample.trajectory, []).append(sample)
    trajectories = []
    for index, rows in sorted(by_index.items()):
        rows.sort(key=lambda s: s.step)
        if rows[0].step != 0 or rows[0].phase != "start":
            raise ValueError(f"{path}: trajectory {index} does not start with its tare sample (step 0, phase start)")
        trajectories.append(RecordedTrajectory(
            object=info.object, index=index,
            bubble_poses=np.array([s.bubble_pose for s in rows]), target_poses=np.array([s.target_pose for s in rows]),
            object_poses=np.array([s.object_pose for s in rows]), wrenches=np.array([s.wrench for s in rows]),
            phases=tuple(s.phase for s in rows)))
    return info, trajectories
