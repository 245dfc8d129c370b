"""The wrench-transmission benchmark's objects (paper V-C, Fig. 5, Table II) as scenes, and the press-and-shear
trajectories that probe them.

Each object is clamped to the table: it does not move, and what the benchmark compares is the wrench the Soft Bubble
transmits to the wrist. In a scene the clamp is a rigid object of ``CLAMPED_MASS_KG`` without gravity, with a
damping time ``CLAMPED_EPSILON_S``: under 50 N of contact force it moves less than 1e-10 m per step (the plant of
``hydrosoft-stack collect wrench`` in sim mode), so the scenes need no table body. The bubble is the task scenes'
Soft Bubble (``hydrosoft/tasks/pushing.toml``): an ellipsoidal membrane 120 x 90 x 60 mm with ``E = 3e5`` and
``K = 1e5`` Pa/m and ``mu = 0.9``, its frame at the ellipsoid's centre (the arm's TCP frame), upright.

Sizes. The paper names the objects and gives the cylinders' radii; the rest is chosen here to fit under the bubble
(``BENCH_OBJECTS``). Every object rests on the table top (``z = 0`` of the scene's origin), centred at the origin
in x and y; prisms and cylinders lie with their axes along y.

============  ===================  ==============================================  ===========
name          Table II row         size (m)                                        top (m)
============  ===================  ==============================================  ===========
plate         Plane                0.12 x 0.12, 0.015 thick                        0.015
triangle      Triangle             equilateral, edge 0.05, 0.08 long, ridge up     0.043
trapezoid     Trapezoid            0.06 bottom, 0.03 top, 0.03 high, 0.08 long     0.030
cube          Cube                 edge 0.05                                       0.050
cylinder_r15  Cylinder R15         radius 0.015 (paper), 0.10 long, lying          0.030
cylinder_r25  Cylinder R25         radius 0.025 (paper), 0.10 long, lying          0.050
============  ===================  ==============================================  ===========

Trajectories (``press_and_shear``): from ``GAP_M`` above the object's highest point the bubble presses straight down
to a random depth, then shears in a random planar direction, twists about the vertical, or both (a third of the
trajectories each), in equal increments. Poses are ``(7,)`` ``[x, y, z, qw, qx, qy, qz]`` (m, wxyz) of the bubble
frame in the scene's world frame (the robot's base frame).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from hydrosoft.scene import BodySpec, ObjectSpec, Scene

CLAMPED_MASS_KG = 1e6  # the clamped object: (h^2/epsilon) F / m = 0.05^2 / 1e3 * 50 / 1e6 = 1.25e-10 m per step
CLAMPED_EPSILON_S = 1e3
BUBBLE_RADII_M = (0.06, 0.045, 0.03)  # the task scenes' Soft Bubble membrane (x, y, z semi-axes)
BUBBLE_E, BUBBLE_K, BUBBLE_MU = 3e5, 1e5, 0.9  # Pa/m, Pa/m, friction (hydrosoft/tasks/pushing.toml)
SCENE_DT_S = 0.05
SCENE_REACH_M = 0.04  # the bubble's largest travel from its start over a trajectory: gap + depth + shear, with margin
SPACING_M = 0.005  # default object surface spacing of the benchmark's models (m)

GAP_M = 0.002  # the bubble's lowest point this far above the object's highest point at a trajectory's start
DEPTH_RANGE_M = (0.004, 0.012)  # press depth below the object's highest point
SHEAR_RANGE_M = (0.004, 0.015)  # planar travel of the shear phase
TWIST_RANGE_RAD = (math.radians(4.0), math.radians(15.0))  # twist about the vertical (either sign)
PRESS_FRACTION = 1 / 3  # share of a trajectory's steps spent pressing
MAX_STEPS = 40  # the paper's trajectories are up to 40 steps long
UPRIGHT = (1.0, 0.0, 0.0, 0.0)
AXIS_ALONG_Y = (math.sqrt(0.5), math.sqrt(0.5), 0.0, 0.0)  # the shape factories' z axis turned onto -y


@dataclass(frozen=True)
class BenchObject:
    """One benchmark object. name: its key; title: its Table II row; shape and params: ``scene.ObjectSpec``'s
    (``hydrosoft.geometry.surface`` factories, m); orientation: the object frame in the world (wxyz); bottom_m,
    top_m: the distances from its centre of mass down to the table and up to its highest point (m)."""

    name: str
    title: str
    shape: str
    params: dict[str, Any]
    orientation: tuple[float, float, float, float]
    bottom_m: float
    top_m: float

    def pose(self, origin=(0.0, 0.0, 0.0)) -> np.ndarray:
        """The object's pose ``(7,)`` resting on the table top, centred over ``origin`` (``(3,)`` m, world)."""
        x, y, z = (float(v) for v in origin)
        return np.array([x, y, z + self.bottom_m, *self.orientation])

    def top_z(self, origin=(0.0, 0.0, 0.0)) -> float:
        """World height of the object's highest point (m)."""
        return float(origin[2]) + self.bottom_m + self.top_m


def _triangle(side: float, length: float) -> BenchObject:
    height = side * math.sqrt(3) / 2
    return BenchObject("triangle", "Triangle", "triangle_prism", {"side": side, "length": length}, UPRIGHT,
                       height / 3, 2 * height / 3)


def _trapezoid(bottom: float, top: float, height: float, length: float) -> BenchObject:
    centroid = height * (bottom + 2 * top) / (3 * (bottom + top))
    return BenchObject("trapezoid", "Trapezoid", "trapezoid_prism",
                       {"bottom": bottom, "top": top, "height": height, "length": length}, UPRIGHT,
                       centroid, height - centroid)


def _cylinder(name: str, title: str, radius: float, length: float) -> BenchObject:
    return BenchObject(name, title, "cylinder", {"radius": radius, "length": length}, AXIS_ALONG_Y, radius, radius)


BENCH_OBJECTS: dict[str, BenchObject] = {o.name: o for o in (
    BenchObject("plate", "Plane", "plate", {"length": 0.12, "width": 0.12, "thickness": 0.015}, UPRIGHT, 0.0075,
                0.0075),
    _triangle(0.05, 0.08),
    _trapezoid(0.06, 0.03, 0.03, 0.08),
    BenchObject("cube", "Cube", "cube", {"side": 0.05}, UPRIGHT, 0.025, 0.025),
    _cylinder("cylinder_r15", "Cylinder R15", 0.015, 0.10),
    _cylinder("cylinder_r25", "Cylinder R25", 0.025, 0.10),
)}


def bench_object(name: str) -> BenchObject:
    """The benchmark object ``name``; ValueError naming the known ones otherwise."""
    try:
        return BENCH_OBJECTS[name]
    except KeyError:
        raise ValueError(f"unknown benchmark object {name!r}; known: {', '.join(BENCH_OBJECTS)}") from None


def start_pose(obj: BenchObject, origin=(0.0, 0.0, 0.0)) -> np.ndarray:
    """The bubble's pose ``(7,)`` at a trajectory's start: upright over the object, its lowest point ``GAP_M`` above
    the object's highest point (out of contact)."""
    x, y, _ = (float(v) for v in origin)
    return np.array([x, y, obj.top_z(origin) + BUBBLE_RADII_M[2] + GAP_M, *UPRIGHT])


def wrench_scene(name: str, contact: str = "nh", spacing: float = SPACING_M, body: str = "bubble",
                 object_pose=None, bubble_pose=None) -> Scene:
    """The scene of benchmark object ``name`` with one Soft Bubble called ``body``.

    contact: the contact model (``nh``, ``snh``, ``pf``, ``pff``); spacing: the object's surface spacing (m);
    object_pose, bubble_pose: ``(7,)`` world poses (default: the object on the table at the origin, the bubble at
    ``start_pose``).
    """
    obj = bench_object(name)
    object_pose = obj.pose() if object_pose is None else np.asarray(object_pose, dtype=np.float64)
    bubble_pose = start_pose(obj) if bubble_pose is None else np.asarray(bubble_pose, dtype=np.float64)
    return Scene(
        object=ObjectSpec(shape=obj.shape, mass=CLAMPED_MASS_KG, params=dict(obj.params), spacing=spacing,
                          pose=[float(v) for v in object_pose]),
        bodies=[BodySpec(name=body, sdf="ellipsoid", E=BUBBLE_E, K=BUBBLE_K, mu=BUBBLE_MU,
                         params={"radii": list(BUBBLE_RADII_M)}, pose=[float(v) for v in bubble_pose])],
        contact=contact, dt=SCENE_DT_S, epsilon=CLAMPED_EPSILON_S, planar=False, gravity=[0.0, 0.0, 0.0],
        reach=SCENE_REACH_M,
    )


Kind = Literal["shear", "twist", "shear_twist"]
KINDS: tuple[Kind, ...] = ("shear", "twist", "shear_twist")


@dataclass(frozen=True)
class PressAndShear:
    """One trajectory's parameters. kind: what the second phase does; depth_m: the press depth below the object's
    highest point (m); shear_m, direction_rad: planar travel (m) and its direction (rad from +x); twist_rad: the
    turn about the vertical (rad); press_steps, shear_steps: steps of each phase."""

    kind: Kind
    depth_m: float
    shear_m: float
    direction_rad: float
    twist_rad: float
    press_steps: int
    shear_steps: int

    @property
    def steps(self) -> int:
        return self.press_steps + self.shear_steps


def sample_press_and_shear(rng: np.random.Generator, steps: int, kind: Kind | None = None) -> PressAndShear:
    """Random trajectory parameters for ``steps`` steps (2 to ``MAX_STEPS``): a depth in ``DEPTH_RANGE_M``, then a
    shear in ``SHEAR_RANGE_M`` along a uniform direction, a twist of either sign in ``TWIST_RANGE_RAD``, or both
    (``kind``, or a uniform pick of ``KINDS``)."""
    if not 2 <= steps <= MAX_STEPS:
        raise ValueError(f"a trajectory has 2 to {MAX_STEPS} steps, got {steps}")
    kind = KINDS[int(rng.integers(len(KINDS)))] if kind is None else kind
    depth = float(rng.uniform(*DEPTH_RANGE_M))
    shear = float(rng.uniform(*SHEAR_RANGE_M)) if kind != "twist" else 0.0
    direction = float(rng.uniform(-math.pi, math.pi))
    twist = float(rng.uniform(*TWIST_RANGE_RAD) * rng.choice([-1.0, 1.0])) if kind != "shear" else 0.0
    press = max(1, round(steps * PRESS_FRACTION))
    return PressAndShear(kind, depth, shear, direction, twist, press, steps - press)


def press_and_shear(obj: BenchObject, trajectory: PressAndShear, origin=(0.0, 0.0, 0.0)) -> np.ndarray:
    """The bubble's target poses ``(steps + 1, 7)``: row 0 is ``start_pose`` (out of contact), rows ``1..press_steps``
    descend in equal steps to ``depth_m`` below the object's highest point, the remaining rows shear and twist in
    equal increments at that depth."""
    start = start_pose(obj, origin)
    poses = np.repeat(start[None], trajectory.steps + 1, axis=0)
    descent = GAP_M + trajectory.depth_m
    k = np.arange(trajectory.steps + 1)
    press = np.minimum(k, trajectory.press_steps) / trajectory.press_steps
    shear = np.clip(k - trajectory.press_steps, 0, None) / max(trajectory.shear_steps, 1)
    poses[:, 2] = start[2] - descent * press
    poses[:, 0] += trajectory.shear_m * math.cos(trajectory.direction_rad) * shear
    poses[:, 1] += trajectory.shear_m * math.sin(trajectory.direction_rad) * shear
    half_turn = 0.5 * trajectory.twist_rad * shear
    poses[:, 3:] = np.stack([np.cos(half_turn), 0 * half_turn, 0 * half_turn, np.sin(half_turn)], axis=-1)
    return poses
