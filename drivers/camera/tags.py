"""Where the AprilTags sit on an object: ``TagLayout`` and builders for a box and a cylinder.

Family: AprilTag 36h11 (``cv2.aruco.DICT_APRILTAG_36h11``): 6 x 6 data cells inside a one-cell black border, so the
black square is 8 cells across. A printed tag also needs a white quiet zone around the black square
(``QUIET_ZONE_CELLS`` cells wide) for the detector to find its edges; the builders check that tag and quiet zone fit
on the face.

Tag frame (the one ``cv2.solvePnP(..., SOLVEPNP_IPPE_SQUARE)`` reports): origin at the centre of the black square,
x to the right and y up as the tag is printed, z out of the face. ``size_m`` is the black square's edge.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from hydrosoft.drivers.poses import check_pose, pose_from_rt, transform_points

TAG_DICTIONARY_ID = cv2.aruco.DICT_APRILTAG_36h11
MARKER_CELLS = 8  # black square of a 36h11 tag: 6 data cells + a one-cell border on each side
QUIET_ZONE_CELLS = 1  # white margin around the black square, in cells
CYLINDER_SIDE_FACETS = 24  # flat facets approximating a cylinder's side in ``TagLayout.faces``


def tag_dictionary() -> cv2.aruco.Dictionary:
    """The 36h11 dictionary shared by the renderer and the detector."""
    return cv2.aruco.getPredefinedDictionary(TAG_DICTIONARY_ID)


def tag_corners(size_m: float) -> np.ndarray:
    """Corners ``(4, 3)`` (m) of the black square in the tag frame, in the detector's order: top-left, top-right,
    bottom-right, bottom-left as printed (``z = 0``)."""
    h = size_m / 2.0
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


@dataclass(frozen=True, eq=False)
class Tag:
    """One tag: its 36h11 ``id``, ``size_m`` (black square edge, m) and ``T_object_tag (7,)``, the pose of the
    tag's centre in the object frame (tag z out of the face)."""

    id: int
    size_m: float
    T_object_tag: np.ndarray

    def __post_init__(self) -> None:
        max_id = tag_dictionary().bytesList.shape[0] - 1
        if isinstance(self.id, bool) or not isinstance(self.id, (int, np.integer)) or not 0 <= self.id <= max_id:
            raise ValueError(f"Tag.id: expected an integer in [0, {max_id}] (36h11), got {self.id!r}")
        if not np.isfinite(self.size_m) or self.size_m <= 0:
            raise ValueError(f"Tag {self.id}: size_m must be a positive edge length in metres, got {self.size_m!r}")
        object.__setattr__(self, "id", int(self.id))
        object.__setattr__(self, "size_m", float(self.size_m))
        object.__setattr__(self, "T_object_tag", check_pose(self.T_object_tag, f"Tag {self.id}: T_object_tag"))

    @property
    def corners_object(self) -> np.ndarray:
        """The black square's corners ``(4, 3)`` (m) in the object frame, in the detector's order."""
        return transform_points(self.T_object_tag, tag_corners(self.size_m))


@dataclass(frozen=True, eq=False)
class TagLayout:
    """The tags of one rigid object, plus its outline for rendering.

    tags: the object's tags (ids unique). faces: the object's surface as convex planar polygons, each ``(K, 3)``
    (m, object frame) with vertices counter-clockwise seen from outside (outward normal by the right-hand rule);
    used only to draw the object in simulated images, may be empty.
    """

    tags: tuple[Tag, ...]
    faces: tuple[np.ndarray, ...] = ()

    def __post_init__(self) -> None:
        ids = [tag.id for tag in self.tags]
        if not ids:
            raise ValueError("TagLayout: needs at least one tag")
        duplicates = sorted({i for i in ids if ids.count(i) > 1})
        if duplicates:
            raise ValueError(f"TagLayout: tag ids must be unique, repeated: {duplicates}")
        object.__setattr__(self, "tags", tuple(self.tags))
        object.__setattr__(self, "faces", tuple(np.asarray(f, dtype=np.float64) for f in self.faces))

    @property
    def ids(self) -> tuple[int, ...]:
        """The tag ids in layout order."""
        return tuple(tag.id for tag in self.tags)

    def tag(self, tag_id: int) -> Tag | None:
        """The tag with ``tag_id``, or ``None`` when it is not on this object."""
        return next((tag for tag in self.tags if tag.id == tag_id), None)


BOX_FACE_NORMALS = {"+x": (1, 0, 0), "-x": (-1, 0, 0), "+y": (0, 1, 0), "-y": (0, -1, 0), "+z": (0, 0, 1),
                    "-z": (0, 0, -1)}


def box_layout(
    size_m: tuple[float, float, float],
    tag_size_m: float,
    first_id: int = 0,
    faces: tuple[str, ...] = ("+z", "+x", "-x", "+y", "-y"),
) -> TagLayout:
    """Layout of a box centred on the object origin with one tag centred on each listed face.

    Args:
        size_m: box edges ``(x, y, z)`` in metres.
        tag_size_m: black-square edge of every tag (m).
        first_id: id of the first tag; the others follow in ``faces`` order.
        faces: faces by outward normal, from ``+x, -x, +y, -y, +z, -z``. The default leaves out the bottom (on the
            table), so a camera above sees the top and up to two sides.

    Tag axes: on ``+z`` the tag's x, y are the object's; on ``-z`` x is the object's x; on a side face the tag's y
    is the object's ``+z`` (tags upright).

    Raises:
        ValueError: for an unknown face name or a tag (with its quiet zone) larger than its face.
    """
    half = np.asarray(size_m, dtype=np.float64) / 2.0
    if half.shape != (3,) or not np.all(half > 0):
        raise ValueError(f"box_layout: size_m must be three positive edges in metres, got {size_m!r}")
    printed_m = tag_size_m * (MARKER_CELLS + 2 * QUIET_ZONE_CELLS) / MARKER_CELLS
    tags = []
    for index, face in enumerate(faces):
        if face not in BOX_FACE_NORMALS:
            raise ValueError(f"box_layout: unknown face {face!r}, expected one of {list(BOX_FACE_NORMALS)}")
        normal = np.array(BOX_FACE_NORMALS[face], dtype=np.float64)
        axis = int(np.argmax(np.abs(normal)))
        face_edges = 2 * np.delete(half, axis)
        if printed_m > face_edges.min() + 1e-12:
            raise ValueError(f"box_layout: a {tag_size_m} m tag with its quiet zone ({printed_m:.4f} m) does not fit "
                             f"on face {face} ({face_edges[0]:.4f} x {face_edges[1]:.4f} m)")
        R = _face_rotation(normal)
        tags.append(Tag(first_id + index, tag_size_m, pose_from_rt(R, normal * half)))
    return TagLayout(tuple(tags), _box_faces(half))


def cylinder_layout(
    radius_m: float,
    length_m: float,
    tag_size_m: float,
    first_id: int = 0,
    caps: tuple[str, ...] = ("+z", "-z"),
) -> TagLayout:
    """Layout of a cylinder along the object's z axis, centred on the origin, with one tag on each listed end cap.

    Args:
        radius_m, length_m: the cylinder (m).
        tag_size_m: black-square edge (m); the tag with its quiet zone must fit inside the cap's circle.
        first_id: id of the first tag; the others follow in ``caps`` order.
        caps: ``"+z"`` (top) and/or ``"-z"`` (bottom).

    Raises:
        ValueError: for an unknown cap or a tag that does not fit on the cap.
    """
    if not radius_m > 0 or not length_m > 0:
        raise ValueError(f"cylinder_layout: radius_m and length_m must be positive, got {radius_m!r}, {length_m!r}")
    printed_m = tag_size_m * (MARKER_CELLS + 2 * QUIET_ZONE_CELLS) / MARKER_CELLS
    if printed_m * np.sqrt(2.0) / 2.0 > radius_m + 1e-12:
        raise ValueError(f"cylinder_layout: a {tag_size_m} m tag with its quiet zone ({printed_m:.4f} m square) does "
                         f"not fit in a cap of radius {radius_m} m")
    tags = []
    for index, cap in enumerate(caps):
        if cap not in ("+z", "-z"):
            raise ValueError(f"cylinder_layout: unknown cap {cap!r}, expected '+z' or '-z'")
        normal = np.array(BOX_FACE_NORMALS[cap], dtype=np.float64)
        tags.append(Tag(first_id + index, tag_size_m, pose_from_rt(_face_rotation(normal), normal * length_m / 2)))
    return TagLayout(tuple(tags), _cylinder_faces(radius_m, length_m))


def _face_rotation(normal: np.ndarray) -> np.ndarray:
    """Rotation ``(3, 3)`` whose z column is the face's outward ``normal`` (an axis): see ``box_layout``."""
    if abs(normal[2]) > 0.5:
        x = np.array([1.0, 0.0, 0.0])
        y = np.cross(normal, x)
    else:
        y = np.array([0.0, 0.0, 1.0])
        x = np.cross(y, normal)
    return np.column_stack([x, y, normal])


def _box_faces(half: np.ndarray) -> tuple[np.ndarray, ...]:
    """The six faces of a box with half-edges ``half (3,)``, each ``(4, 3)`` counter-clockwise from outside."""
    faces = []
    for normal in BOX_FACE_NORMALS.values():
        R = _face_rotation(np.array(normal, dtype=np.float64))
        axis = int(np.argmax(np.abs(normal)))
        extent = np.abs(R.T @ half)  # half-extent along the face's x, y (and its offset along z)
        square = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * extent[:2]
        faces.append(np.column_stack([square, np.full(4, half[axis])]) @ R.T)
    return tuple(faces)


def _cylinder_faces(radius_m: float, length_m: float) -> tuple[np.ndarray, ...]:
    """A cylinder as two ``CYLINDER_SIDE_FACETS``-gon caps and as many side quads, counter-clockwise from outside."""
    angles = np.linspace(0.0, 2 * np.pi, CYLINDER_SIDE_FACETS, endpoint=False)
    ring = np.column_stack([radius_m * np.cos(angles), radius_m * np.sin(angles)])
    top = np.column_stack([ring, np.full(CYLINDER_SIDE_FACETS, length_m / 2)])
    bottom = np.column_stack([ring, np.full(CYLINDER_SIDE_FACETS, -length_m / 2)])
    sides = [np.array([bottom[i], bottom[(i + 1) % CYLINDER_SIDE_FACETS], top[(i + 1) % CYLINDER_SIDE_FACETS], top[i]])
             for i in range(CYLINDER_SIDE_FACETS)]
    return (top, bottom[::-1].copy(), *sides)
