"""One small async interface per device kind, shared by the real drivers and their simulated twins.

Conventions for every driver:

- Poses are ``(7,)`` float64 arrays ``[x, y, z, qw, qx, qy, qz]``: metres and a unit quaternion, in the frame the
  docstring names (the arm's base frame for TCP poses). Drivers convert to and from vendor conventions (UR's
  rotation vectors) at their edge, never above it.
- Wrenches are ``(6,)`` float64 ``[Fx, Fy, Fz, Mx, My, Mz]`` in N and N m, in the sensor frame.
- Every reading carries ``stamp_ns`` (``time.monotonic_ns()`` when the host received it) and ``hw_stamp_ns`` (the
  device's own clock, converted to ns, or ``None`` when the device has none). Staleness is judged on these.
- A driver never returns an old reading as if it were new: a device that stops answering raises
  ``drivers.errors.Stale`` (or another ``DriverError``), it is not papered over.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np


@dataclass(frozen=True)
class ArmState:
    """One reading of an arm: ``tcp_pose (7,)`` in the base frame (m, wxyz), ``tcp_speed (6,)`` (m/s, rad/s),
    whether the controller is executing our commands (``running``), its protective/emergency stop flags and the
    stamps.

    controller_stop: the controller's named reason for not running our program ("" while it runs it normally), e.g.
    "safeguard stop", "program paused", "robot mode POWER_OFF". safety_flags: the names of every safety stop the
    controller reports at once (most severe first). link_since_ns: when the driver's link to the controller last
    came up (``time.monotonic_ns()``; 0 when the driver does not say): a reconnect changes it.
    """

    tcp_pose: np.ndarray
    tcp_speed: np.ndarray
    running: bool
    protective_stop: bool
    emergency_stop: bool
    stamp_ns: int
    hw_stamp_ns: int | None
    controller_stop: str = ""
    safety_flags: tuple[str, ...] = ()
    link_since_ns: int = 0


@dataclass(frozen=True)
class WrenchSample:
    """One F/T reading: ``wrench (6,)`` N and N m in the sensor frame, with stamps."""

    wrench: np.ndarray
    stamp_ns: int
    hw_stamp_ns: int | None


@dataclass(frozen=True)
class ImageFrame:
    """One camera image ``(H, W, 3)`` uint8 BGR or ``(H, W)`` uint8 grey, with stamps."""

    image: np.ndarray
    stamp_ns: int
    hw_stamp_ns: int | None


@dataclass(frozen=True)
class DepthFrame:
    """One depth image ``(H, W)`` uint16; metres = value x ``depth_scale_m`` (0 = no return), with stamps."""

    depth: np.ndarray
    depth_scale_m: float
    stamp_ns: int
    hw_stamp_ns: int | None


@runtime_checkable
class Arm(Protocol):
    """One arm's Cartesian servo interface. ``servo_to`` is called at the servo rate with the next interpolated
    target; ``stop`` decelerates the TCP to rest and must be safe to call at any time, repeatedly."""

    async def connect(self) -> None: ...

    async def read_state(self) -> ArmState: ...

    async def servo_to(self, tcp_pose: np.ndarray) -> None: ...

    async def stop(self) -> None: ...

    async def close(self) -> None: ...


@runtime_checkable
class ForceTorqueSensor(Protocol):
    """A streaming six-axis force/torque sensor. ``read`` returns the newest sample or raises ``Stale``."""

    async def connect(self) -> None: ...

    async def read(self) -> WrenchSample: ...

    async def close(self) -> None: ...


@runtime_checkable
class Camera(Protocol):
    """An RGB camera. ``read`` returns the next frame or raises a ``DriverError``."""

    async def connect(self) -> None: ...

    async def read(self) -> ImageFrame: ...

    async def close(self) -> None: ...


@runtime_checkable
class DepthCamera(Protocol):
    """A Soft Bubble's depth camera. ``read`` returns the next depth frame or raises a ``DriverError``."""

    async def connect(self) -> None: ...

    async def read(self) -> DepthFrame: ...

    async def close(self) -> None: ...
