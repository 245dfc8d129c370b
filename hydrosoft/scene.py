"""Declarative scenes and their compilation into the minimal model the scene needs.

A scene names one rigid object (shape, surface spacing, mass, pose), the compliant bodies (SDF shape, pose,
material, whether the controls move them; a table is a stiff compliant half-space), gravity, the contact
model and the step. ``load_scene`` reads it from TOML and validates it with messages that name the field.
``compile_scene`` turns it into a ``dynamics.Model`` and an initial ``dynamics.State``, keeping only what can
matter over the motion the scene declares (``reach``):

- planar (x, y, yaw) dynamics when the scene says ``planar = true`` (checked: gravity along -z, object upright);
- only body-object pairs that can touch: a body whose distance lower bound to the object's bounding sphere
  exceeds ``reach`` is dropped;
- only surface points that can touch a kept body: a point whose signed distance to every kept body exceeds
  ``reach`` times the SDF's Lipschitz bound is dropped (the active set).

The sub-step count comes from ``dynamics.substeps_for`` over the contact patch the scene starts with, grown by
``stability_margin`` (points within that distance of a body): a bound over states with that patch, without
assuming that every point within ``reach`` touches at once. Deeper presses are caught at run time: every step
checks its current contacts (``dynamics.substeps_needed``, with the same margin) and sub-steps more, up to
``max_substeps``. A planar scene's table (an unactuated horizontal half-space) becomes the model's ``support``.

Every omission is listed in the returned ``CompileReport``. Example TOML::

    contact = "nh"
    dt = 0.05
    epsilon = 0.5
    planar = true
    reach = 0.03
    [object]
    shape = "cube"
    params = { side = 0.05 }
    spacing = 0.005
    mass = 0.2
    pose = [0.0, 0.0, 0.025, 1.0, 0.0, 0.0, 0.0]
    [[bodies]]
    name = "table"
    sdf = "halfspace"
    E = 1e8
    K = 1e5
    mu = 0.3
    actuated = false
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import msgspec
import torch
from torch import Tensor

from hydrosoft import contact as contact_models
from hydrosoft.contact import Material
from hydrosoft.dynamics import Model, State, press_in, substeps_for
from hydrosoft.geometry import sdf as sdfs
from hydrosoft.geometry import se3
from hydrosoft.geometry import surface as surfaces
from hydrosoft.scene_spec import BodySpec, ObjectSpec, SceneError

MAX_SURFACE_POINTS = 100_000
"""Most surface points an object may have: each point costs every step of every planner sample a force state per
body, so more would exhaust memory (a 0.1 mm spacing on a 5 cm cube asks for 1.5 million)."""
MAX_SUBSTEPS = 10_000
"""Most sub-steps a scene may allow per step (``max_substeps``): more would take seconds per step."""
MAX_GRAVITY = 1e3
"""m/s^2: the largest gravity a scene may have (about 100 g); far beyond it the forces overflow."""


class Scene(msgspec.Struct, forbid_unknown_fields=True):
    """A whole scene; see the module docstring for the TOML layout. Times in s, lengths in m."""

    object: ObjectSpec
    bodies: list[BodySpec]
    contact: str = "nh"
    contact_params: dict[str, float] = {}
    dt: float = 0.05
    epsilon: float = 0.5
    planar: bool = False
    gravity: list[float] = msgspec.field(default_factory=lambda: [0.0, 0.0, -9.81])
    reach: float = 0.05
    stability_margin: float = 0.005
    max_substeps: int = 64

    def __post_init__(self) -> None:
        if self.contact not in contact_models.MODELS:
            raise SceneError(f"contact: unknown model {self.contact!r}; known: {', '.join(contact_models.MODELS)}")
        if not self.bodies:
            raise SceneError("bodies: a scene needs at least one compliant body")
        names = [b.name for b in self.bodies]
        if len(set(names)) != len(names):
            raise SceneError(f"bodies: names must be unique, got {names}")
        for field in ("dt", "epsilon"):
            value = getattr(self, field)
            if not (value > 0 and math.isfinite(value)):
                raise SceneError(f"{field}: must be a positive number of seconds, got {value}")
        for field in ("reach", "stability_margin"):
            value = getattr(self, field)
            if not (value >= 0 and math.isfinite(value)):
                raise SceneError(f"{field}: must be a non-negative number of metres, got {value}")
        if not math.isfinite(self.dt * self.dt / self.epsilon):
            raise SceneError(
                f"dt: the step's gain dt^2/epsilon overflows (dt = {self.dt} s, epsilon = {self.epsilon} s)")
        if len(self.gravity) != 3 or not all(math.isfinite(g) for g in self.gravity):
            raise SceneError(f"gravity: must be 3 finite numbers (m/s^2), got {self.gravity}")
        if math.hypot(*self.gravity) > MAX_GRAVITY:
            raise SceneError(f"gravity: its magnitude must be at most {MAX_GRAVITY:g} m/s^2, got {self.gravity}")
        if not 1 <= self.max_substeps <= MAX_SUBSTEPS:
            raise SceneError(f"max_substeps: must be 1..{MAX_SUBSTEPS}, got {self.max_substeps}")
        try:
            contact_models.make(self.contact, **self.contact_params)
        except ValueError as err:
            raise SceneError(f"contact_params.{err}") from None


def parse_scene(text: str | bytes, origin: str = "scene") -> Scene:
    """Validate a scene from TOML text. Raises SceneError naming ``origin`` and the offending field."""
    try:
        return msgspec.toml.decode(text, type=Scene)
    except msgspec.ValidationError as err:
        raise SceneError(f"invalid {origin}: {err}") from err
    except msgspec.DecodeError as err:
        raise SceneError(f"{origin} is not valid TOML: {err}") from err


def load_scene(path: str | Path) -> Scene:
    """Read and validate a scene TOML file. Raises SceneError naming the file and the offending field."""
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"scene file {path} does not exist")
    return parse_scene(path.read_bytes(), origin=f"scene {path}")


@dataclass(frozen=True)
class CompileReport:
    """What ``compile_scene`` kept and left out."""

    planar: bool
    bodies_kept: tuple[str, ...]
    bodies_dropped: tuple[str, ...]
    points_total: int
    points_kept: int
    pairs_kept: int
    substeps: int

    def summary(self) -> str:
        dropped = f"; dropped bodies out of reach: {', '.join(self.bodies_dropped)}" if self.bodies_dropped else ""
        return (
            f"{'planar SE(2)' if self.planar else 'spatial SE(3)'} model, bodies {', '.join(self.bodies_kept)}"
            f"{dropped}; {self.points_kept}/{self.points_total} surface points active, {self.pairs_kept} "
            f"point-body pairs of {self.points_kept * len(self.bodies_kept)}; "
            f"{self.substeps} sub-step(s) per step"
        )


def _surface(spec: ObjectSpec, spacing: float) -> surfaces.Surface:
    """The object's surface at ``spacing`` (m); SceneError naming ``object.params`` for bad sizes."""
    try:
        if spec.shape == "mesh":
            return surfaces.from_mesh(spec.path, spacing=spacing)
        return getattr(surfaces, spec.shape)(spacing=spacing, **spec.params)
    except (TypeError, ValueError) as err:
        raise SceneError(f"object.params: {err}") from err


def build_surface(spec: ObjectSpec) -> surfaces.Surface:
    """The object's discretized surface from its spec.

    Raises SceneError naming ``object.spacing`` before building a surface of more than ``MAX_SURFACE_POINTS``
    points: the count is estimated as the surface area (exact from one cell per face) over ``spacing^2``.
    """
    estimate = _surface(spec, math.inf).total_area / spec.spacing**2
    if not estimate <= MAX_SURFACE_POINTS:
        raise SceneError(
            f"object.spacing: {spec.spacing} m would make about {estimate:.3g} surface points, more than the "
            f"{MAX_SURFACE_POINTS} allowed; raise the spacing"
        )
    return _surface(spec, spec.spacing)


def build_sdf(spec: BodySpec):
    """The signed distance function of a body spec."""
    try:
        return sdfs.from_spec(spec.sdf, **spec.params)
    except (TypeError, ValueError) as err:
        raise SceneError(f"bodies[{spec.name}]: {err}") from err


def _check_planar(scene: Scene) -> None:
    g = scene.gravity
    if abs(g[0]) > 1e-12 or abs(g[1]) > 1e-12 or not g[2] < 0:
        raise SceneError(f"planar: a planar scene needs gravity along -z (its table carries the weight), got {g}")
    qw, qx, qy, _ = scene.object.pose[3:]
    if abs(qx) > 1e-9 or abs(qy) > 1e-9:
        raise SceneError("planar: the object must be upright (its pose may only rotate about z)")


def fixed_contact_set(scene: Scene, spec: BodySpec, sdf) -> bool:
    """True when no motion can change which object points touch this body: in a planar scene the object's height
    and tilt are held, so its points keep their distances to an unactuated horizontal half-space (the table).
    Such a body is given exactly the points in contact at the start, for pruning and the stability bound."""
    qx, qy = spec.pose[4:6]
    return scene.planar and not spec.actuated and isinstance(sdf, sdfs.HalfSpace) and abs(qx) + abs(qy) <= 1e-12


def _consecutive_order(near: Tensor) -> Tensor:
    """An order ``(n,)`` of the kept points, given which bodies can touch each (``near (M, n)`` bool), in which the
    points of the first two bodies each lie consecutively: the first body's alone, then those both can touch, then
    the second body's alone, then the rest, each run in surface order. The step then reads each of those bodies'
    points as a slice rather than a gather (``dynamics.Model.point_sets``)."""
    first, second = near[0], near[1] if near.shape[0] > 1 else torch.zeros_like(near[0])
    run = torch.where(first, torch.where(second, 1, 0), torch.where(second, 2, 3))
    return torch.sort(run, stable=True).indices


def compile_scene(
    scene: Scene, dtype: torch.dtype = torch.float64, device: str | torch.device = "cpu", prune: bool = True
) -> tuple[Model, State, CompileReport]:
    """Compile a scene into ``(model, initial state with B = 1, report)``.

    Pruning (``prune=True``) keeps only what the scene can use within ``reach``: bodies that can reach the
    object, surface points within reach of some body, and, per body, only the points within its reach
    (``Model.touchable``). A body whose contact set no motion can change (``fixed_contact_set``: the table of a
    planar scene) keeps exactly the points in contact at the start, with or without pruning: the stability bound
    then counts only those, instead of every point within ``stability_margin`` (the pushing cube's lowest side
    rows, whose horizontal normals would add the table's stiffness E to the planar bound and quadruple the
    sub-steps).
    ``prune=False`` keeps every body and point (the full model, for checking what pruning changes). The
    initial forces are those of pressing each body straight into its initial pose (``press_in``).
    """
    if scene.planar:
        _check_planar(scene)
    surface = build_surface(scene.object)
    object_pose = torch.tensor(scene.object.pose, dtype=torch.float64)
    bodies = [(spec, build_sdf(spec)) for spec in scene.bodies]

    world_points = se3.transform_points(object_pose, surface.points)
    kept, dropped, near, touching, support = [], [], [], [], None
    for spec, sdf in bodies:
        body_pose = torch.tensor(spec.pose, dtype=torch.float64)
        local = se3.transform_points(se3.inverse(body_pose), world_points)
        phi = sdf(local)
        centre = se3.transform_points(se3.inverse(body_pose), object_pose[:3].view(1, 3))[0]
        lower_bound = float(sdf(centre)) - sdf.lipschitz * surface.bounding_radius
        if prune and lower_bound > scene.reach * sdf.lipschitz:
            dropped.append(spec.name)
            continue
        kept.append((spec, sdf))
        fixed = fixed_contact_set(scene, spec, sdf)
        if fixed and support is None:
            support = len(kept) - 1
        reach, margin = (0.0, 0.0) if fixed else (scene.reach * sdf.lipschitz, scene.stability_margin)
        near.append(phi <= reach if prune else torch.ones_like(phi, dtype=torch.bool))
        touching.append(phi <= margin)
    if not kept:
        raise SceneError(
            f"no compliant body can reach the object within reach = {scene.reach} m: "
            f"dropped {', '.join(dropped)}; move the bodies closer or raise reach"
        )
    active = torch.stack(near)
    index = active.any(0).nonzero().squeeze(-1)
    if prune and index.numel() == 0:  # nothing within reach: keep everything, the bodies may still be brought in
        index = torch.arange(surface.n_points)
        active = torch.ones_like(active)
    index = index[_consecutive_order(active[:, index])]
    surface = surface.subset(index)
    touching = torch.stack(touching)[:, index]
    near = active[:, index]
    touchable = () if bool(near.all()) else tuple(row.nonzero().squeeze(-1) for row in near)

    specs = [spec for spec, _ in kept]
    material = Material(
        E=torch.tensor([s.E for s in specs], dtype=torch.float64),
        K=torch.tensor([s.K for s in specs], dtype=torch.float64),
        mu=torch.tensor([s.mu for s in specs], dtype=torch.float64),
    )
    model = Model(
        points=surface.points,
        normals=surface.normals,
        areas=surface.areas,
        bodies=tuple(sdf for _, sdf in kept),
        body_names=tuple(s.name for s in specs),
        material=material,
        actuated=torch.tensor([s.actuated for s in specs], dtype=torch.float64),
        contact=contact_models.make(scene.contact, **scene.contact_params),
        mass=scene.object.mass,
        inertia=scene.object.mass * surface.unit_inertia,
        gravity=torch.tensor(scene.gravity, dtype=torch.float64),
        dt=scene.dt,
        epsilon=scene.epsilon,
        planar=scene.planar,
        touchable=touchable,
        support=support,
        stability_margin=scene.stability_margin,
        max_substeps=scene.max_substeps,
    )
    try:
        n_sub = substeps_for(model, scene.max_substeps, touching)
    except ValueError as err:
        raise SceneError(str(err)) from err
    model = replace(model, substeps=n_sub).to(dtype=dtype, device=device)
    object_pose = object_pose.to(dtype=dtype, device=device).unsqueeze(0)
    body_poses = torch.tensor([s.pose for s in specs], dtype=dtype, device=device).unsqueeze(0)
    state = press_in(model, object_pose, body_poses)
    report = CompileReport(
        planar=scene.planar,
        bodies_kept=model.body_names,
        bodies_dropped=tuple(dropped),
        points_total=int(world_points.shape[0]),
        points_kept=int(index.numel()),
        pairs_kept=int(near.sum()),
        substeps=n_sub,
    )
    return model, state, report
