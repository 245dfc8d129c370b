"""The renderer puts tag edges where the camera model projects them (distortion included), and only tags that face
the camera; noise is seeded."""

import cv2
import numpy as np
import pytest

from hydrosoft.drivers.camera.config import CameraIntrinsics
from hydrosoft.drivers.poses import compose, inverse, look_at, rvec_tvec_from_pose
from hydrosoft.drivers.camera.render import Renderer, RenderOptions, _PlacedObject
from hydrosoft.drivers.camera.tags import Tag, TagLayout, box_layout

FACING_CAMERA = np.array([0.0, 1.0, 0.0, 0.0])  # 180 deg about x: the tag's z points back at the camera


def one_tag(size_m: float = 0.08) -> TagLayout:
    return TagLayout((Tag(0, size_m, np.array([0, 0, 0, 1.0, 0, 0, 0])),))


def edge_position(profile: np.ndarray, high: float, low: float) -> float:
    """Sub-pixel position of a step from ``high`` (left) to ``low`` (right) in a profile of area-averaged pixels:
    the number of pixels' worth of ``high`` it holds, counted from the first pixel's left boundary (-0.5). Exact for
    area-averaged pixels whatever the edge's phase, unlike a linearly interpolated 50 % crossing (up to 0.09 px
    off when the samples do not sit symmetrically on the one-pixel ramp)."""
    return -0.5 + float(np.sum((profile - low) / (high - low)))


@pytest.mark.parametrize("distortion", [np.zeros(5), np.array([-0.25, 0.08, 0.001, -0.001, 0.0])])
def test_left_edge_of_the_black_square_is_where_the_model_projects_it(distortion):
    import cv2

    intrinsics = CameraIntrinsics(640, 480, 600.0, 600.0, 319.5, 239.5, distortion)
    options = RenderOptions(ambient=1.0)
    renderer = Renderer(intrinsics, options)
    T_camera_tag = np.concatenate([[0.09, 0.05, 0.5], FACING_CAMERA])  # off-centre: distortion matters
    image = renderer.render(T_camera_tag, one_tag())[:, :, 0].astype(float)
    # the black square's left edge in the tag frame (facing the camera, tag x is image right), projected densely
    edge = np.column_stack([np.full(2001, -0.04), np.linspace(-0.04, 0.04, 2001), np.zeros(2001)])
    projected, _ = cv2.projectPoints(edge, *rvec_tvec_from_pose(T_camera_tag), intrinsics.camera_matrix, distortion)
    projected = projected.reshape(-1, 2)
    order = np.argsort(projected[:, 1])
    for row in range(int(projected[:, 1].min()) + 5, int(projected[:, 1].max()) - 5, 7):
        expected_u = np.interp(row, projected[order, 1], projected[order, 0])
        start = int(expected_u) - 4  # nine pixels: quiet zone (white) on the left, black border on the right
        measured_u = start + edge_position(image[row, start:start + 9], options.white_level, options.black_level)
        assert measured_u == pytest.approx(expected_u, abs=0.02)


def test_tags_facing_away_are_not_drawn():
    intrinsics = CameraIntrinsics(320, 240, 300.0, 300.0, 159.5, 119.5)
    options = RenderOptions()
    image = Renderer(intrinsics, options).render(np.array([0, 0, 0.4, 1.0, 0, 0, 0]), one_tag(0.05))
    assert np.all(image == round(options.background))


def test_cube_on_table_shows_tags_faces_and_table():
    intrinsics = CameraIntrinsics(320, 240, 300.0, 300.0, 159.5, 119.5)
    options = RenderOptions(ambient=1.0)
    T_camera_object = np.concatenate([[0.0, 0.0, 0.3], FACING_CAMERA])  # object z (top face) towards the camera
    T_camera_table = np.concatenate([[0.0, 0.0, 0.325], FACING_CAMERA])
    image = Renderer(intrinsics, options).render(T_camera_object, box_layout((0.05,) * 3, 0.03), None,
                                                 T_camera_table)[:, :, 0]
    assert image.shape == (240, 320) and image.dtype == np.uint8
    # top face 0.275 m away: half-widths 16.4 px (black square), 20.5 px (quiet zone), 27.3 px (face)
    assert image[5, 5] == round(options.table_grey)
    assert image[119, 159 + 24] == round(options.face_grey)
    assert image[119, 159 + 19] == round(options.white_level)
    assert image[119, 159 + 16] == round(options.black_level)
    assert image[119, 159 + 30] == round(options.table_grey)


def test_noise_is_seeded_and_needs_a_generator():
    intrinsics = CameraIntrinsics(160, 120, 150.0, 150.0, 79.5, 59.5)
    options = RenderOptions(noise_std=3.0, blur_sigma_px=0.5)
    renderer = Renderer(intrinsics, options)
    pose = np.concatenate([[0.0, 0.0, 0.3], FACING_CAMERA])
    a = renderer.render(pose, one_tag(0.05), np.random.default_rng(7))
    b = Renderer(intrinsics, options).render(pose, one_tag(0.05), np.random.default_rng(7))
    c = Renderer(intrinsics, options).render(pose, one_tag(0.05), np.random.default_rng(8))
    np.testing.assert_array_equal(a, b)
    assert np.any(a != c)
    assert 1.5 < float(np.std(a[:10, :10].astype(float))) < 4.5
    with pytest.raises(ValueError, match="rng"):
        renderer.render(pose, one_tag(0.05))


def test_a_scene_seen_again_gets_fresh_noise_on_the_same_drawing_and_a_moved_one_is_drawn_again():
    intrinsics = CameraIntrinsics(160, 120, 150.0, 150.0, 79.5, 59.5)
    layout = one_tag(0.05)
    near = np.concatenate([[0.0, 0.0, 0.3], FACING_CAMERA])
    moved = np.concatenate([[0.01, 0.0, 0.3], FACING_CAMERA])
    renderer, fresh = Renderer(intrinsics), Renderer(intrinsics)
    first = renderer.render(near, layout)
    np.testing.assert_array_equal(renderer.render(moved, layout), fresh.render(moved, layout))
    np.testing.assert_array_equal(renderer.render(near, layout), first)
    assert np.any(first != fresh.render(moved, layout))
    noisy = Renderer(intrinsics, RenderOptions(noise_std=3.0))
    rng = np.random.default_rng(7)
    a, b = noisy.render(near, layout, rng), noisy.render(near, layout, rng)
    assert np.any(a != b)  # new noise each frame
    assert abs(float(np.mean(a.astype(float) - b.astype(float)))) < 0.2  # on the same picture
    frames = np.array([noisy.render(near, layout, rng)[:, :, 0] for _ in range(40)], dtype=np.float64)
    noise = frames - frames.mean(axis=0)
    # each pixel's noise varies from frame to frame as much as within an image, and frames are uncorrelated
    assert 2.6 < float(np.sqrt(np.mean(noise.var(axis=0, ddof=1)))) < 3.4
    assert abs(float(np.corrcoef(noise[:-1].ravel(), noise[1:].ravel())[0, 1])) < 0.05


def test_options_are_checked():
    with pytest.raises(ValueError, match="black_level"):
        RenderOptions(black_level=200.0, white_level=100.0)
    with pytest.raises(ValueError, match="supersample"):
        RenderOptions(supersample=0)


class WholeCanvasRenderer(Renderer):
    """The renderer as it was: the whole supersampled canvas drawn and shrunk for every image."""

    def _table_covers_canvas(self, table_camera: np.ndarray) -> bool:
        return False


@pytest.mark.parametrize("distortion", [np.zeros(5), np.array([-0.08, 0.02, 0.0, 0.0, 0.0])])
def test_an_object_on_a_table_that_fills_the_view_is_drawn_in_a_window_and_gives_the_whole_canvas_image(distortion):
    intrinsics = CameraIntrinsics(320, 240, 300.0, 300.0, 159.5, 119.5, distortion)
    options = RenderOptions(noise_std=0.0, blur_sigma_px=0.6)
    layout = box_layout((0.05,) * 3, 0.032)
    # deploy/sim.toml's view: 36 deg down at a cube 0.53 m away, the table's far edge out of sight
    T_camera_base = inverse(look_at([0.25, -0.35, 0.33], [0.0, 0.0, 0.02], [0.0, 0.0, 1.0]))
    T_camera_table = compose(T_camera_base, np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]))
    windowed, whole = Renderer(intrinsics, options), WholeCanvasRenderer(intrinsics, options)
    rng = np.random.default_rng(3)
    for _ in range(6):
        yaw = rng.uniform(-np.pi, np.pi)
        T_base_object = np.array([*rng.uniform(-0.05, 0.05, 2), 0.025, np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])
        T_camera_object = compose(T_camera_base, T_base_object)
        window = windowed._object_window(_PlacedObject.of(T_camera_object, layout))
        assert window is not None and (window[2] - window[0]) * (window[3] - window[1]) < 0.2 * 960 * 720
        image = windowed.render(T_camera_object, layout, None, T_camera_table)
        np.testing.assert_array_equal(image, whole.render(T_camera_object, layout, None, T_camera_table))
        assert np.any(image != image[0, 0])  # the object is in the image


@pytest.mark.parametrize("with_noise", [True, False])
def test_quantise_gives_numpys_rounded_and_clipped_grey_levels_bit_for_bit(with_noise):
    from hydrosoft.drivers.camera.render import quantise

    rng = np.random.default_rng(3)
    image = (rng.random((48, 64), dtype=np.float32) * 400.0 - 70.0).astype(np.float32)
    image[0, :6] = np.array([0.5, 1.5, 2.5, 254.5, 255.5, -0.5], dtype=np.float32)  # ties round half to even
    image[1, :4] = np.array([-1000.0, 1000.0, 255.49, 0.49], dtype=np.float32)  # saturated on both sides
    noise = rng.standard_normal((48, 64), dtype=np.float32) * np.float32(3.0) if with_noise else None
    if noise is not None:
        noise[:2] = 0.0
    total = image if noise is None else image + noise
    expected = np.clip(np.rint(total), 0, 255).astype(np.uint8)
    got = quantise(image, noise)
    assert got.dtype == np.uint8 and got.shape == image.shape
    np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(got[0, :6], [0, 2, 2, 254, 255, 0])


@pytest.mark.parametrize("sigma_px", [0.6, 1.0, 2.3])
def test_the_blur_of_a_window_is_the_whole_images_blur_bit_for_bit(sigma_px):
    """Windows anywhere, at the image's edges and corners too, of any width (the patch's lanes, BLUR_LANE_PX)."""
    intrinsics = CameraIntrinsics(330, 250, 300.0, 300.0, 164.5, 124.5)  # a width no lane count divides
    renderer = Renderer(intrinsics, RenderOptions(blur_sigma_px=sigma_px))
    rng = np.random.default_rng(4)
    corners = [(0, 0), (330 - 40, 250 - 30), (0, 250 - 30), (330 - 40, 0)]
    for index in range(40):
        grey = np.float32(rng.uniform(30.0, 200.0))
        height, width = (30, 40) if index < len(corners) else rng.integers(1, 120, 2)
        x, y = corners[index] if index < len(corners) else (rng.integers(0, 330 - width), rng.integers(0, 250 - height))
        window = rng.uniform(0.0, 255.0, (height, width)).astype(np.float32)
        whole = np.full((250, 330), grey, dtype=np.float32)
        whole[y:y + height, x:x + width] = window
        got = renderer._blur_of_window(window, (int(x), int(y)), grey)
        np.testing.assert_array_equal(got, cv2.GaussianBlur(whole, (0, 0), sigma_px))


def test_a_grey_camera_gives_the_grey_levels_of_the_colour_cameras_bgr_image():
    intrinsics = CameraIntrinsics(320, 240, 300.0, 300.0, 159.5, 119.5)
    layout = box_layout((0.05,) * 3, 0.032)
    T_camera_base = inverse(look_at([0.25, -0.35, 0.33], [0.0, 0.0, 0.02], [0.0, 0.0, 1.0]))
    T_camera_table = compose(T_camera_base, np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]))
    T_camera_object = compose(T_camera_base, np.array([0.01, 0.0, 0.025, 1.0, 0.0, 0.0, 0.0]))
    colour = Renderer(intrinsics, RenderOptions(noise_std=2.0))
    grey = Renderer(intrinsics, RenderOptions(noise_std=2.0, grey=True))
    bgr = colour.render(T_camera_object, layout, np.random.default_rng(7), T_camera_table)
    image = grey.render(T_camera_object, layout, np.random.default_rng(7), T_camera_table)
    assert image.shape == (240, 320) and image.dtype == np.uint8 and bgr.shape == (240, 320, 3)
    for channel in range(3):
        np.testing.assert_array_equal(bgr[:, :, channel], image)
    assert np.any(image != image[0, 0])  # the object is in the image
