"""A scene's object and bodies as the scene TOML declares them, read and checked without torch.

``ObjectSpec`` and ``BodySpec`` are the parts of ``hydrosoft.scene.Scene`` that the sensor services need (the tag
tracker lays its tags on the object, the bubble camera takes the membrane's radii from its body). They live here,
apart from the model library, so a service that needs only them starts without importing torch and its compiler:
about 2.7 CPU-s and 200 MB of a tracker's start (docs/benchmarks.md, "Stack start"). ``task_scene_parts`` reads a
task scene shipped with the package (``hydrosoft/tasks/NAME.toml``) this way, checking its object and bodies as
``Scene`` does; the rest of it (contact model, step) is checked where it is used, by ``hydrosoft.tasks.task_scene``.
"""

from __future__ import annotations

import math
from importlib import resources
from typing import Any

import msgspec

TASK_SCENES = ("pushing", "rotation", "rolling", "in_hand")
OBJECT_SHAPES = ("plate", "box", "cube", "triangle_prism", "trapezoid_prism", "cylinder", "mesh")
IDENTITY_POSE = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)


class SceneError(ValueError):
    """A scene that cannot be loaded or compiled; the message names the offending field."""


def _check_pose(pose: list[float], where: str) -> None:
    if len(pose) != 7 or not all(math.isfinite(v) for v in pose):
        raise SceneError(f"{where}: a pose is 7 finite numbers [x, y, z, qw, qx, qy, qz], got {pose}")
    if abs(math.sqrt(sum(v * v for v in pose[3:])) - 1.0) > 1e-6:
        raise SceneError(f"{where}: quaternion {pose[3:]} is not unit length")


class ObjectSpec(msgspec.Struct, forbid_unknown_fields=True):
    """The rigid object: ``shape`` (one of OBJECT_SHAPES; ``mesh`` takes ``path``), its size ``params`` (m),
    surface ``spacing`` (m), ``mass`` (kg) and initial ``pose``."""

    shape: str
    mass: float
    params: dict[str, Any] = {}
    spacing: float = 0.005
    pose: list[float] = msgspec.field(default_factory=lambda: list(IDENTITY_POSE))
    path: str | None = None

    def __post_init__(self) -> None:
        if self.shape not in OBJECT_SHAPES:
            raise SceneError(f"object.shape: unknown shape {self.shape!r}; known: {', '.join(OBJECT_SHAPES)}")
        if self.shape == "mesh" and not self.path:
            raise SceneError("object.path: a mesh object needs the path of a watertight STL/OBJ file")
        if not (self.mass > 0 and math.isfinite(self.mass)):
            raise SceneError(f"object.mass: must be a positive number of kg, got {self.mass}")
        if not (self.spacing > 0 and math.isfinite(self.spacing)):
            raise SceneError(f"object.spacing: must be a positive number of metres, got {self.spacing}")
        _check_pose(self.pose, "object.pose")


class BodySpec(msgspec.Struct, forbid_unknown_fields=True):
    """A compliant body: ``sdf`` kind and ``params`` (m), ``pose``, material ``E``, ``K`` (Pa/m), ``mu``."""

    name: str
    sdf: str
    E: float
    K: float
    mu: float
    params: dict[str, Any] = {}
    pose: list[float] = msgspec.field(default_factory=lambda: list(IDENTITY_POSE))
    actuated: bool = True

    def __post_init__(self) -> None:
        where = f"bodies[{self.name}]"
        for field in ("E", "K"):
            value = getattr(self, field)
            if not (value > 0 and math.isfinite(value)):
                raise SceneError(f"{where}.{field}: must be a positive number of Pa/m, got {value}")
        if not (self.mu >= 0 and math.isfinite(self.mu)):
            raise SceneError(f"{where}.mu: must be a non-negative number, got {self.mu}")
        _check_pose(self.pose, f"{where}.pose")


class SceneParts(msgspec.Struct):
    """A scene's object and compliant bodies, its other keys left unread."""

    object: ObjectSpec
    bodies: list[BodySpec]


def task_scene_text(name: str) -> bytes:
    """The TOML text of the task scene ``name`` (one of ``TASK_SCENES``) shipped with the package. Raises
    SceneError for an unknown name."""
    if name not in TASK_SCENES:
        raise SceneError(f"unknown task scene {name!r}; known: {', '.join(TASK_SCENES)}")
    return resources.files("hydrosoft").joinpath("tasks").joinpath(f"{name}.toml").read_bytes()


def task_scene_parts(name: str) -> SceneParts:
    """The object and bodies of the task scene ``name``, checked. Raises SceneError naming the field."""
    try:
        return msgspec.toml.decode(task_scene_text(name), type=SceneParts)
    except msgspec.ValidationError as err:
        raise SceneError(f"invalid task scene {name}.toml: {err}") from err
