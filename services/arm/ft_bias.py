"""An F/T sensor's stored tare: one small JSON file per arm, ``STATE_DIR/ft_bias-ARM.json``.

The F/T reader subtracts the stored bias from every reading and never tares by itself, so the file is what keeps a
tare across reader restarts, launches and reboots (``state_dir`` in the config; ``StackConfig.state_path``). It is
written by an accepted ``hydrosoft-stack ft tare ARM`` (the reader) and, in sim mode, by sim_world at its start
(the simulated sensor's zero-load reading). A file is written whole or not at all (a temporary file, flushed to
disk, then renamed over the old one), so a crash mid-write leaves the previous tare.

A file that cannot be read, is not a ``StoredBias``, holds a non-finite number, or names another arm or port is an
error (``BiasFileError``), never a zero bias: the reader then publishes untared readings and says why.

The time of the tare is wall-clock time (ns since the Unix epoch), the only clock that means something after a
reboot; it is shown as the bias's age and never used as a deadline.
"""

from __future__ import annotations

import math
import os
import time
from datetime import datetime, timezone
from pathlib import Path

import msgspec
import numpy as np

#: Most bytes a bias file may have (a real one has about 300); a larger file is refused unread.
MAX_FILE_BYTES = 4096


class BiasFileError(Exception):
    """A bias file that exists but cannot be used; the message names the file and the reason."""


class StoredBias(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """One arm's tare. arm: the arm's name. port: the sensor's serial port when it was taken (a bias belongs to
    one sensor: a file naming another port is refused). bias: ``[Fx, Fy, Fz, Mx, My, Mz]`` (N, N m, sensor frame),
    the reading with nothing touching the sensor. taken_unix_ns: when it was taken, ns since the Unix epoch.
    samples: how many readings it is the mean of (0: not measured, e.g. the simulator's known offset). source: who
    took it (``ft tare``, ``sim_world``)."""

    arm: str
    port: str
    bias: tuple[float, float, float, float, float, float]
    taken_unix_ns: int
    samples: int
    source: str

    def __post_init__(self) -> None:
        if not all(math.isfinite(v) for v in self.bias):
            raise ValueError(f"bias {list(self.bias)} holds a non-finite number")
        if self.taken_unix_ns <= 0 or self.samples < 0:
            raise ValueError(f"taken_unix_ns {self.taken_unix_ns} must be > 0 and samples {self.samples} >= 0")

    @property
    def vector(self) -> np.ndarray:
        """The bias as a ``(6,)`` float64 array (N, N m)."""
        return np.array(self.bias, dtype=np.float64)

    def age_s(self, now_unix_ns: int | None = None) -> float:
        """Seconds since the tare was taken (wall clock; ``now_unix_ns`` defaults to ``time.time_ns()``)."""
        return ((time.time_ns() if now_unix_ns is None else now_unix_ns) - self.taken_unix_ns) * 1e-9

    def describe(self, now_unix_ns: int | None = None) -> str:
        """One line for the status: the bias, when it was taken (UTC), its age, and who took it."""
        taken = datetime.fromtimestamp(self.taken_unix_ns * 1e-9, tz=timezone.utc).strftime("%Y-%m-%d %H:%M:%S")
        values = " ".join(f"{v:.3f}" for v in self.bias)
        return (f"tared: bias [{values}] N, N m, taken {taken} UTC ({format_age(self.age_s(now_unix_ns))} ago, "
                f"by {self.source})")


def format_age(age_s: float) -> str:
    """``age_s`` in the largest unit that keeps it at least 1: ``"42 s"``, ``"3.5 min"``, ``"2.0 h"``, ``"6.1 d"``."""
    for unit, size_s in (("d", 86400.0), ("h", 3600.0), ("min", 60.0)):
        if abs(age_s) >= size_s:
            return f"{age_s / size_s:.1f} {unit}"
    return f"{age_s:.0f} s"


def bias_path(state_dir: Path, arm: str) -> Path:
    """The bias file of ``arm`` in ``state_dir``."""
    return Path(state_dir) / f"ft_bias-{arm}.json"


def save_bias(path: Path, stored: StoredBias) -> None:
    """Write ``stored`` to ``path`` whole or not at all (creating its folder). Raises OSError when it cannot."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(temporary, "wb") as file:
            file.write(msgspec.json.format(msgspec.json.encode(stored)) + b"\n")
            file.flush()
            os.fsync(file.fileno())
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)


def load_bias(path: Path, arm: str, port: str) -> StoredBias | None:
    """The tare stored at ``path`` for ``arm``'s sensor on ``port``, or None when there is no file.

    Raises:
        BiasFileError: the file cannot be read, is too large, is not a ``StoredBias`` (bad JSON, a missing or
            unknown key, a non-finite value), or was taken for another arm or port.
    """
    path = Path(path)
    try:
        with open(path, "rb") as file:
            data = file.read(MAX_FILE_BYTES + 1)
    except FileNotFoundError:
        return None
    except OSError as error:
        raise BiasFileError(f"bias file {path} cannot be read: {error}") from error
    if len(data) > MAX_FILE_BYTES:
        raise BiasFileError(f"bias file {path} is larger than {MAX_FILE_BYTES} bytes: not a bias file")
    try:
        stored = msgspec.json.decode(data, type=StoredBias)
    except (msgspec.DecodeError, msgspec.ValidationError) as error:
        raise BiasFileError(f"bias file {path} is corrupt: {error}") from error
    if stored.arm != arm or stored.port != port:
        raise BiasFileError(f"bias file {path} was taken for arm {stored.arm!r} on port {stored.port!r}, not arm "
                            f"{arm!r} on port {port!r}: tare this sensor again")
    return stored
