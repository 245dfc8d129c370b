"""Render what a calibrated camera sees of an object's AprilTags (numpy + OpenCV, no GPU, no 3D engine).

The scene is flat polygons seen by a pinhole camera: an optional table plane, the object's faces that face the
camera (grey, shaded by the angle to the camera as if lit from it) and, on those, the tags that face the camera:
each is the 36h11 marker from ``cv2.aruco.generateImageMarker`` with its white quiet zone, mapped onto its square by
the homography of its projected corners. Since the object is convex (the layouts of ``tags.py`` are), back-face
culling alone resolves its visibility; the table is drawn first, so the object covers it.

Pipeline of ``Renderer.render`` (one grey float32 canvas, BGR only at the end):

1. draw on an undistorted (ideal pinhole) canvas ``supersample`` times finer than the image; polygons are clipped
   at ``NEAR_PLANE_M`` in front of the camera;
2. shrink it to the image's resolution with area averaging, which anti-aliases every edge (when the table fills the
   view, steps 1-2 run only in a window around the object, the rest being the table's uniform grey: the same image,
   bit for bit, for a fraction of the pixels);
3. apply the lens distortion exactly: each image pixel samples the ideal canvas (bilinear) where
   ``cv2.undistortPoints`` puts it (a homography of distorted corners would leave the tag's edges straight where
   the lens bends them). Resampling an area-averaged edge keeps its area position (measured: within 0.01 px with
   k1 = -0.25); remapping the supersampled canvas instead gave the same accuracy at twice the render time;
4. Gaussian blur (with the window drawn and no lens distortion, only in a patch around the window: the same image,
   bit for bit), then Gaussian noise from the caller's seeded ``numpy.random.Generator``, then round to uint8.

Grey levels are 0-255 floats until step 4.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from hydrosoft.drivers.camera.config import CameraIntrinsics
from hydrosoft.drivers.poses import compose, inverse, quat_to_matrix, transform_points
from hydrosoft.drivers.camera.tags import MARKER_CELLS, QUIET_ZONE_CELLS, TagLayout, tag_corners, tag_dictionary

NEAR_PLANE_M = 0.01  # geometry closer to the camera than this is clipped away
TABLE_HALF_EXTENT_M = 3.0  # the table is drawn as a square of this half-edge around the object
MAX_CANVAS_SCALE = 3.0  # a strongly distorted lens never needs an ideal canvas wider than this many images
TEXTURE_CELL_PX_RANGE = (2, 64)  # marker texture resolution per tag cell; chosen per tag near its projected size
EDGE_ON_COSINE = 1e-6  # surfaces seen closer to edge-on than this (cosine of the view angle) are skipped
UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-9)
#: The noise field is this many images across each axis: an image's noise is one of (H x W) distinct windows.
NOISE_FIELD_SCALE = 2
#: Canvas pixels to spare around the object's drawing window (``Renderer._object_window``): a quad's warp reads 1-2
#: pixels past its corners, and the table must cover the canvas by more than this to be a uniform background.
WINDOW_MARGIN_PX = 8
#: Image pixels per vector lane group of OpenCV's float row filter (a multiple of AVX-512's 16 floats): a patch blurred
#: on its own starts and ends on these, so its pixels are rounded as the whole image's are (``_blur_of_window``).
BLUR_LANE_PX = 16


@dataclass(frozen=True)
class RenderOptions:
    """How a scene looks. Grey levels are 0-255.

    background: grey of the empty scene. table_grey, face_grey: table and object faces seen head-on.
    black_level, white_level: a tag's black cells and white cells seen head-on. ambient: the fraction of a
    surface's grey that does not fade with its angle to the camera (light at the camera; 1 = no shading).
    noise_std: Gaussian noise in grey levels, independent per pixel within an image; each image takes a random
    window of a field ``NOISE_FIELD_SCALE`` times its size per axis, drawn once per renderer, so that an image's
    noise costs a slice (drawing 640x480 normals took 3 ms). blur_sigma_px: Gaussian blur in pixels (0 = none).
    supersample: canvas pixels per image pixel along each axis (anti-aliasing). grey: images ``(H, W)`` uint8 grey
    (a monochrome camera) instead of ``(H, W, 3)`` BGR: the same grey levels (the scene is grey), a third of the bytes.
    """

    background: float = 40.0
    table_grey: float = 90.0
    face_grey: float = 150.0
    black_level: float = 25.0
    white_level: float = 235.0
    ambient: float = 0.5
    noise_std: float = 0.0
    blur_sigma_px: float = 0.0
    supersample: int = 3
    grey: bool = False

    def __post_init__(self) -> None:
        for name in ("background", "table_grey", "face_grey", "black_level", "white_level"):
            value = getattr(self, name)
            if not 0.0 <= value <= 255.0:
                raise ValueError(f"RenderOptions.{name}: expected a grey level in [0, 255], got {value!r}")
        if not self.black_level < self.white_level:
            raise ValueError(f"RenderOptions: black_level {self.black_level} must be below white_level "
                             f"{self.white_level}")
        if not 0.0 <= self.ambient <= 1.0:
            raise ValueError(f"RenderOptions.ambient: expected a fraction in [0, 1], got {self.ambient!r}")
        for name in ("noise_std", "blur_sigma_px"):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"RenderOptions.{name}: expected a non-negative number, got {getattr(self, name)!r}")
        if not isinstance(self.supersample, int) or self.supersample < 1:
            raise ValueError(f"RenderOptions.supersample: expected a positive integer, got {self.supersample!r}")


def quantise(image: np.ndarray, noise: np.ndarray | None = None) -> np.ndarray:
    """Grey levels ``(H, W)`` uint8 of a float32 image ``(H, W)`` plus ``noise`` (``(H, W)`` float32, or none):
    ``np.clip(np.rint(image + noise), 0, 255).astype(np.uint8)``, bit for bit (the float32 sum, rounded half to
    even, saturated), in one OpenCV pass instead of numpy's four (640 x 480: 0.19 against 1.33 ms). For finite sums
    within +-2**31 (grey levels and their noise are; OpenCV's rounding to int overflows beyond)."""
    if noise is None:
        return cv2.add(image, 0.0, dtype=cv2.CV_8U)
    return cv2.add(image, noise, dtype=cv2.CV_8U)


class Renderer:
    """Renders images of one camera (``intrinsics``) in one look (``options``).

    Construction precomputes the lens-distortion lookup (a fraction of a second for a large distorted image), so
    keep one renderer per camera. Marker textures are cached per tag id and resolution, and ``render`` keeps its
    last noise-free image: a scene seen again exactly as before (a still object) gets fresh noise on it without
    being drawn again.
    """

    def __init__(self, intrinsics: CameraIntrinsics, options: RenderOptions | None = None) -> None:
        self.intrinsics = intrinsics
        self.options = options or RenderOptions()
        self._dictionary = tag_dictionary()
        self._textures: dict[tuple[int, int], np.ndarray] = {}
        self._distortion_map: tuple[np.ndarray, np.ndarray] | None = None
        self._origin = np.zeros(2)  # ideal-canvas pixel (0, 0) in ideal image pixel coordinates
        self._canvas_size = intrinsics.size
        if intrinsics.has_distortion:
            self._prepare_distortion()
        self._last_scene: tuple[tuple, np.ndarray, TagLayout] | None = None  # (key, noise-free image, layout)
        self._noise_field: np.ndarray | None = None  # drawn from the first rng given

    def render(
        self,
        T_camera_object: np.ndarray,
        layout: TagLayout,
        rng: np.random.Generator | None = None,
        T_camera_table: np.ndarray | None = None,
    ) -> np.ndarray:
        """Image ``(H, W, 3)`` uint8 BGR (``(H, W)`` grey with ``options.grey``) of the object with pose
        ``T_camera_object (7,)`` (m, wxyz, camera frame).

        Args:
            layout: the object's tags and faces (faces may be empty: tags then float in the air).
            rng: source of the pixel noise; required when ``options.noise_std > 0``.
            T_camera_table: pose of the table frame (its xy-plane is the table top, z up), or ``None`` for no table.
        """
        scene = (np.asarray(T_camera_object, dtype=np.float64).tobytes(), id(layout),
                 None if T_camera_table is None else np.asarray(T_camera_table, dtype=np.float64).tobytes())
        if self._last_scene is None or self._last_scene[0] != scene:  # the cache holds layout: its id stays its own
            self._last_scene = (scene, self._draw(T_camera_object, layout, T_camera_table), layout)
        return self._expose(self._last_scene[1], rng)

    def _draw(self, T_camera_object: np.ndarray, layout: TagLayout, T_camera_table: np.ndarray | None) -> np.ndarray:
        """The noise-free image ``(H, W)`` float32 of ``render``'s scene.

        When the table covers the whole canvas (``_table_covers_canvas``), only a window around the object
        (``_object_window``) is drawn and shrunk; the rest of the image is the table's uniform grey. The window's
        edges lie on whole image pixels and its offset is a whole number of canvas pixels, so the image is the
        whole canvas's, bit for bit, at a fraction of the pixels (deploy/sim.toml: 1 / 25)."""
        table = None
        if T_camera_table is not None:
            corners = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], dtype=np.float64)
            corners *= TABLE_HALF_EXTENT_M
            corners[:, :2] += transform_points(inverse(T_camera_table), T_camera_object[None, :3])[0, :2]
            polygon = transform_points(T_camera_table, corners)
            normal, centre = _normal(polygon), polygon.mean(axis=0)
            if _faces_camera(normal, centre):
                table = (polygon, self.options.table_grey * self._shade(normal, centre))
        placed = _PlacedObject.of(T_camera_object, layout)
        window = None
        if table is not None and self._table_covers_canvas(table[0]):
            window = self._object_window(placed)
        if window is None:
            canvas, offset = self._blank_canvas(), np.zeros(2)
            if table is not None:
                self._fill_polygon(canvas, table[0], table[1])
        else:
            x0, y0, x1, y1 = window
            canvas, offset = np.full((y1 - y0, x1 - x0), table[1], dtype=np.float32), np.array([x0, y0], dtype=float)
        for polygon in placed.faces:
            normal, centre = _normal(polygon), polygon.mean(axis=0)
            if _faces_camera(normal, centre):
                self._fill_polygon(canvas, polygon, self.options.face_grey * self._shade(normal, centre), offset)
        for tag, T_camera_tag, printed in zip(layout.tags, placed.tag_poses, placed.printed_tags):
            normal = quat_to_matrix(T_camera_tag[3:])[:, 2]
            if not _faces_camera(normal, T_camera_tag[:3]) or np.any(printed[:, 2] < NEAR_PLANE_M):
                continue
            cell_px = self._projected_cell_px(printed)
            shade = self._shade(normal, T_camera_tag[:3])
            self._draw_quad(canvas, self._marker_texture(tag.id, cell_px) * shade, printed, offset)
        if window is None:
            return self._optics(canvas)
        return self._optics_of_window(canvas, window, table[1])

    def _table_covers_canvas(self, table_camera: np.ndarray) -> bool:
        """Whether the table polygon ``(4, 3)`` (camera frame) covers every canvas pixel, with a margin of
        ``WINDOW_MARGIN_PX`` canvas pixels: each canvas corner inside its part in front of the camera."""
        clipped = _clip_near(table_camera)
        if len(clipped) < 3:
            return False
        polygon = self._to_canvas(clipped).astype(np.float32)
        s = self.options.supersample
        width, height = self._canvas_size[0] * s, self._canvas_size[1] * s
        return all(cv2.pointPolygonTest(polygon, (float(x), float(y)), True) > WINDOW_MARGIN_PX
                   for x in (-0.5, width - 0.5) for y in (-0.5, height - 0.5))

    def _object_window(self, placed: _PlacedObject) -> tuple[int, int, int, int] | None:
        """The canvas window ``(x0, y0, x1, y1)`` (slice bounds, canvas px, multiples of ``supersample``) that holds
        every face and tag of the ``placed`` object with ``WINDOW_MARGIN_PX`` to spare, cut at the canvas's border;
        ``None`` when some of the object is not in front of the camera (then the whole canvas is drawn)."""
        points = [*placed.faces, *placed.printed_tags]
        if not points:
            return 0, 0, 0, 0
        points_camera = np.concatenate(points)
        if np.any(points_camera[:, 2] < NEAR_PLANE_M):
            return None
        canvas = self._to_canvas(points_camera)
        s = self.options.supersample
        width, height = self._canvas_size[0] * s, self._canvas_size[1] * s
        low = np.floor((canvas.min(axis=0) - WINDOW_MARGIN_PX) / s) * s
        high = np.ceil((canvas.max(axis=0) + WINDOW_MARGIN_PX) / s) * s
        x0, y0 = int(min(max(low[0], 0), width)), int(min(max(low[1], 0), height))
        x1, y1 = int(min(max(high[0], x0), width)), int(min(max(high[1], y0), height))
        return x0, y0, x1, y1

    def _optics_of_window(self, window_canvas: np.ndarray, window: tuple[int, int, int, int],
                          table_grey: float) -> np.ndarray:
        """``_optics`` of a canvas that is ``table_grey`` everywhere but in ``window`` (canvas px), whose pixels are
        ``window_canvas``: only the window is shrunk and, without lens distortion, only the pixels the window's blur
        reaches are blurred (``_blur_of_window``); the rest is the blur of the uniform grey."""
        s = self.options.supersample
        width, height = self._canvas_size
        uniform = cv2.resize(np.full((s, s), table_grey, dtype=np.float32), (1, 1), interpolation=cv2.INTER_AREA)
        x0, y0, x1, y1 = (bound // s for bound in window)
        shrunk = None
        if x1 > x0 and y1 > y0:
            shrunk = cv2.resize(window_canvas, (x1 - x0, y1 - y0), interpolation=cv2.INTER_AREA)
        if shrunk is not None and self._distortion_map is None and self.options.blur_sigma_px > 0:
            return self._blur_of_window(shrunk, (x0, y0), uniform[0, 0])
        image = np.full((height, width), uniform[0, 0], dtype=np.float32)
        if shrunk is not None:
            image[y0:y1, x0:x1] = shrunk
        return self._lens(image)

    def _blur_of_window(self, shrunk: np.ndarray, corner: tuple[int, int], grey: np.float32) -> np.ndarray:
        """The blurred image ``(H, W)`` float32 of an undistorted image that is ``grey`` everywhere but in the window
        ``shrunk (h, w)`` whose top left pixel is ``corner (x, y)``: ``cv2.GaussianBlur`` of the whole image, bit for
        bit, from a patch around the window (deploy/sim.toml: about 1/25 of the pixels).

        The blur of a pixel reads only pixels within the kernel's radius, so the pixels further than that from the
        window are the blur of a uniform image (one row of it: all its rows are the same), and the patch (the window
        and twice the radius around it, in the image's border) gives the rest: its own border pixels, reflected, are
        the uniform grey as well. OpenCV's row filter rounds differently in a row's last, unvectorised, pixels, so the
        patch's columns start and end where the image's vector lanes do (``BLUR_LANE_PX``), or at the image's right
        edge."""
        sigma = self.options.blur_sigma_px
        radius = math.ceil(4.0 * sigma) + 1  # OpenCV's float kernel: round(8 sigma + 1) | 1 taps, radius <= this
        width, height = self._canvas_size
        x0, y0 = corner
        x1, y1 = x0 + shrunk.shape[1], y0 + shrunk.shape[0]
        px0 = max(x0 - 2 * radius, 0) // BLUR_LANE_PX * BLUR_LANE_PX
        px1 = min(-(-(x1 + 2 * radius) // BLUR_LANE_PX) * BLUR_LANE_PX, width)
        py0, py1 = max(y0 - 2 * radius, 0), min(y1 + 2 * radius, height)
        patch = np.full((py1 - py0, px1 - px0), grey, dtype=np.float32)
        patch[y0 - py0:y1 - py0, x0 - px0:x1 - px0] = shrunk
        patch = cv2.GaussianBlur(patch, (0, 0), sigma)
        far = cv2.GaussianBlur(np.full((2 * radius + 1, width), grey, dtype=np.float32), (0, 0), sigma)
        image = np.empty((height, width), dtype=np.float32)
        image[:] = far[radius]  # a row's unvectorised last pixels may differ from the rest by a rounding
        ex0, ey0 = max(x0 - radius, 0), max(y0 - radius, 0)
        ex1, ey1 = min(x1 + radius, width), min(y1 + radius, height)
        image[ey0:ey1, ex0:ex1] = patch[ey0 - py0:ey1 - py0, ex0 - px0:ex1 - px0]
        return image

    def render_plane(
        self,
        texture: np.ndarray,
        T_camera_plane: np.ndarray,
        size_m: tuple[float, float],
        rng: np.random.Generator | None = None,
    ) -> np.ndarray:
        """Image ``(H, W, 3)`` uint8 BGR (``(H, W)`` grey with ``options.grey``) of a flat printed target (a
        calibration board) on the background.

        Args:
            texture: ``(h, w)`` uint8 grey picture of the target; its pixel ``(0, 0)`` corner is the plane frame's
                origin, image columns run along the plane's +x and rows along its +y (OpenCV's board convention).
            T_camera_plane: pose of the plane frame in the camera frame (m, wxyz).
            size_m: ``(width, height)`` of the printed picture in metres.
            rng: source of the pixel noise; required when ``options.noise_std > 0``.
        """
        width_m, height_m = size_m
        corners = np.array([[0, 0, 0], [width_m, 0, 0], [width_m, height_m, 0], [0, height_m, 0]], dtype=np.float64)
        canvas = self._blank_canvas()
        polygon = transform_points(T_camera_plane, corners)
        if np.all(polygon[:, 2] >= NEAR_PLANE_M):
            self._draw_quad(canvas, texture.astype(np.float32), polygon)
        return self._expose(self._optics(canvas), rng)

    # Drawing on the supersampled ideal canvas.

    def _blank_canvas(self) -> np.ndarray:
        s = self.options.supersample
        width, height = self._canvas_size
        return np.full((height * s, width * s), self.options.background, dtype=np.float32)

    def _to_canvas(self, points_camera: np.ndarray, offset: np.ndarray | None = None) -> np.ndarray:
        """Canvas pixel coordinates ``(N, 2)`` of camera-frame points ``(N, 3)`` in front of the camera, less
        ``offset (2,)`` (whole canvas pixels: the corner of the window drawn; subtracting it is exact)."""
        K = self.intrinsics
        s = self.options.supersample
        uv = np.column_stack([K.fx * points_camera[:, 0] / points_camera[:, 2] + K.cx,
                              K.fy * points_camera[:, 1] / points_camera[:, 2] + K.cy])
        canvas = (uv - self._origin) * s + (s - 1) / 2.0
        return canvas if offset is None else canvas - offset

    def _fill_polygon(self, canvas: np.ndarray, polygon_camera: np.ndarray, grey: float,
                      offset: np.ndarray | None = None) -> None:
        clipped = _clip_near(polygon_camera)
        if len(clipped) < 3:
            return
        subpixel_bits = 4
        points = np.round(self._to_canvas(clipped, offset) * (1 << subpixel_bits)).astype(np.int64)
        limit = np.iinfo(np.int32).max // 4
        cv2.fillConvexPoly(canvas, np.clip(points, -limit, limit).astype(np.int32), float(grey), cv2.LINE_8,
                           subpixel_bits)

    def _draw_quad(self, canvas: np.ndarray, texture: np.ndarray, corners_camera: np.ndarray,
                   offset: np.ndarray | None = None) -> None:
        """Paint ``texture (h, w)`` float32 onto the quad ``corners_camera (4, 3)`` (its TL, TR, BR, BL corners) of a
        canvas whose pixel (0, 0) is the whole canvas's ``offset`` (``_to_canvas``)."""
        height, width = texture.shape
        source = np.array([[-0.5, -0.5], [width - 0.5, -0.5], [width - 0.5, height - 0.5], [-0.5, height - 0.5]],
                          dtype=np.float32)
        target = self._to_canvas(corners_camera, offset)
        x0, y0 = np.maximum(np.floor(target.min(axis=0)).astype(int) - 1, 0)
        x1 = min(int(math.ceil(target[:, 0].max())) + 2, canvas.shape[1])
        y1 = min(int(math.ceil(target[:, 1].max())) + 2, canvas.shape[0])
        if x1 <= x0 or y1 <= y0:
            return
        homography = cv2.getPerspectiveTransform(source, (target - [x0, y0]).astype(np.float32))
        size = (x1 - x0, y1 - y0)
        warped = cv2.warpPerspective(texture, homography, size, flags=cv2.INTER_LINEAR,
                                     borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
        alpha = cv2.warpPerspective(np.ones_like(texture), homography, size, flags=cv2.INTER_LINEAR,
                                    borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
        region = canvas[y0:y1, x0:x1]
        region += alpha * (warped - region)

    def _marker_texture(self, tag_id: int, cell_px: int) -> np.ndarray:
        """The tag's black square with its white quiet zone, ``cell_px`` texture pixels per cell, in the options'
        black and white grey levels (float32)."""
        key = (tag_id, cell_px)
        if key not in self._textures:
            marker = cv2.aruco.generateImageMarker(self._dictionary, tag_id, MARKER_CELLS * cell_px, borderBits=1)
            margin = QUIET_ZONE_CELLS * cell_px
            printed = cv2.copyMakeBorder(marker, margin, margin, margin, margin, cv2.BORDER_CONSTANT, value=255)
            black, white = self.options.black_level, self.options.white_level
            self._textures[key] = (black + (white - black) * (printed.astype(np.float32) / 255.0)).astype(np.float32)
        return self._textures[key]

    def _projected_cell_px(self, printed_camera: np.ndarray) -> int:
        """Texture resolution (pixels per cell, a power of two) close to the tag's size on the canvas."""
        corners = self._to_canvas(printed_camera)
        edge = float(np.max(np.linalg.norm(corners - np.roll(corners, 1, axis=0), axis=1)))
        cell = edge / (MARKER_CELLS + 2 * QUIET_ZONE_CELLS)
        low, high = TEXTURE_CELL_PX_RANGE
        return int(np.clip(2 ** math.ceil(math.log2(max(cell, 1.0))), low, high))

    def _shade(self, normal: np.ndarray, centre: np.ndarray) -> float:
        """Brightness factor in [ambient, 1] of a surface with unit ``normal (3,)`` at ``centre (3,)`` (camera
        frame), lit from the camera."""
        cosine = max(0.0, float(-normal @ centre) / float(np.linalg.norm(centre)))
        return self.options.ambient + (1.0 - self.options.ambient) * cosine

    # From canvas to image.

    def _optics(self, canvas: np.ndarray) -> np.ndarray:
        """The supersampled ideal canvas through the lens: the noise-free image ``(H, W)`` float32."""
        return self._lens(cv2.resize(canvas, self._canvas_size, interpolation=cv2.INTER_AREA))

    def _lens(self, image: np.ndarray) -> np.ndarray:
        """The shrunk ideal canvas ``image`` through the lens's distortion and blur."""
        if self._distortion_map is not None:
            image = cv2.remap(image, *self._distortion_map, interpolation=cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=self.options.background)
        if self.options.blur_sigma_px > 0:
            image = cv2.GaussianBlur(image, (0, 0), self.options.blur_sigma_px)
        return image

    def _expose(self, image: np.ndarray, rng: np.random.Generator | None) -> np.ndarray:
        """A noise-free image ``(H, W)`` float32 with the sensor's noise, as the camera's ``(H, W, 3)`` uint8 BGR
        (``(H, W)`` grey with ``options.grey``).

        The sum, its rounding (half to even) and its saturation to 0-255 in one OpenCV pass (``quantise``): the
        grey levels of ``np.clip(np.rint(image + noise), 0, 255)``, bit for bit, in a seventh of numpy's time."""
        noise = None
        if self.options.noise_std > 0:
            if rng is None:
                raise ValueError("Renderer: options.noise_std > 0 needs an rng (numpy.random.Generator)")
            noise = self._noise(rng)
        grey = quantise(image, noise)
        return grey if self.options.grey else cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)

    def _noise(self, rng: np.random.Generator) -> np.ndarray:
        """Noise ``(H, W)`` float32 with ``options.noise_std``: a window of the noise field at an offset from ``rng``
        (the field itself is drawn from the first ``rng`` given)."""
        height, width = self.intrinsics.height, self.intrinsics.width
        if self._noise_field is None:
            shape = (NOISE_FIELD_SCALE * height, NOISE_FIELD_SCALE * width)
            self._noise_field = rng.standard_normal(shape, dtype=np.float32) * np.float32(self.options.noise_std)
        row, column = rng.integers(0, (NOISE_FIELD_SCALE - 1) * np.array([height, width]), endpoint=True)
        return self._noise_field[row:row + height, column:column + width]

    def _prepare_distortion(self) -> None:
        """For each image pixel, the ideal-canvas point it sees; size the ideal canvas to cover them all."""
        K = self.intrinsics
        u, v = np.meshgrid(np.arange(K.width, dtype=np.float64), np.arange(K.height, dtype=np.float64))
        pixels = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
        ideal = cv2.undistortPoints(pixels, K.camera_matrix, K.distortion, P=K.camera_matrix,
                                    criteria=UNDISTORT_CRITERIA).reshape(-1, 2)
        span = np.array(K.size, dtype=np.float64) * MAX_CANVAS_SCALE
        centre = np.array([K.cx, K.cy])
        ideal = np.clip(ideal, centre - span / 2, centre + span / 2)
        self._origin = np.floor(ideal.min(axis=0)) - 1.0
        far = np.ceil(ideal.max(axis=0)) + 2.0
        self._canvas_size = (int(far[0] - self._origin[0]), int(far[1] - self._origin[1]))
        local = (ideal - self._origin).astype(np.float32)
        self._distortion_map = (local[:, 0].reshape(K.height, K.width), local[:, 1].reshape(K.height, K.width))


@dataclass(frozen=True)
class _PlacedObject:
    """An object's layout in the camera frame, computed once per drawn image. faces: each face's polygon ``(K, 3)``.
    tag_poses: each tag's ``T_camera_tag (7,)``. printed_tags: each tag's printed square with its quiet zone
    ``(4, 3)`` (TL, TR, BR, BL). All in ``layout``'s order, m."""

    faces: tuple[np.ndarray, ...]
    tag_poses: tuple[np.ndarray, ...]
    printed_tags: tuple[np.ndarray, ...]

    @classmethod
    def of(cls, T_camera_object: np.ndarray, layout: TagLayout) -> _PlacedObject:
        """``layout`` placed at ``T_camera_object (7,)`` (m, wxyz)."""
        quiet_scale = (MARKER_CELLS + 2 * QUIET_ZONE_CELLS) / MARKER_CELLS
        tag_poses = tuple(compose(T_camera_object, tag.T_object_tag) for tag in layout.tags)
        return cls(tuple(transform_points(T_camera_object, face) for face in layout.faces), tag_poses,
                   tuple(transform_points(T_camera_tag, tag_corners(tag.size_m * quiet_scale))
                         for tag, T_camera_tag in zip(layout.tags, tag_poses)))


def _normal(polygon: np.ndarray) -> np.ndarray:
    """Unit normal ``(3,)`` of a planar polygon ``(K, 3)`` by the right-hand rule on its vertex order."""
    normal = np.cross(polygon[1] - polygon[0], polygon[2] - polygon[0])
    return normal / np.linalg.norm(normal)


def _faces_camera(normal: np.ndarray, centre: np.ndarray) -> bool:
    """Whether a surface with unit ``normal (3,)`` at ``centre (3,)`` (camera frame) faces the camera at the origin,
    by more than ``EDGE_ON_COSINE`` (a surface seen edge-on is not drawn)."""
    return float(-normal @ centre) > EDGE_ON_COSINE * float(np.linalg.norm(centre))


def _clip_near(polygon: np.ndarray) -> np.ndarray:
    """The part ``(K', 3)`` of a convex polygon ``(K, 3)`` with ``z >= NEAR_PLANE_M`` (Sutherland-Hodgman)."""
    kept = []
    for a, b in zip(polygon, np.roll(polygon, -1, axis=0)):
        a_in, b_in = a[2] >= NEAR_PLANE_M, b[2] >= NEAR_PLANE_M
        if a_in:
            kept.append(a)
        if a_in != b_in:
            kept.append(a + (NEAR_PLANE_M - a[2]) / (b[2] - a[2]) * (b - a))
    return np.array(kept).reshape(-1, 3)
