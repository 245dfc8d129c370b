"""The rules for taking an F/T tare (``services/arm/tare_rules.py``): only at rest, only with the bubble out of contact
(judged on a noisy depth image), only from steady readings; every refusal says why."""

from __future__ import annotations

import numpy as np
import pytest

from hydrosoft.drivers.robotiq_ft300.noise import frame_noise, quantized
from hydrosoft.services.bus import messages as msg
from hydrosoft.services.arm.tare_rules import (
    CONTACT_DEFORMATION_M,
    MAX_SPREAD_N,
    contact_pixels,
    contact_refusal,
    rest_refusal,
    spread_refusal,
    tare_refusal,
)

SHAPE = (120, 160)  # the bubble camera's image, px
SIM_DEPTH_NOISE_M = 2e-4  # sim.depth_noise_m


def arm_state(speed=(0.0,) * 6, servo_active: bool = False) -> msg.ArmState:
    return msg.ArmState(arm="bubble", tcp_pose=np.array([0.0, 0.0, 0.1, 1.0, 0.0, 0.0, 0.0]),
                        tcp_speed=np.array(speed, dtype=np.float64), running=True, protective_stop=False,
                        emergency_stop=False, servo_active=servo_active)


def deformation(image: np.ndarray) -> msg.MembraneDeformation:
    return msg.MembraneDeformation(bubble="bubble", deformation=image.astype(np.float32), reference_stamp_ns=1)


def noise(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).normal(0.0, SIM_DEPTH_NOISE_M, SHAPE)


def pressed(depth_m: float, seed: int = 0, side_px: int = 12) -> np.ndarray:
    """Noise plus a square patch pressed in by ``depth_m``."""
    image = noise(seed)
    image[50:50 + side_px, 70:70 + side_px] += depth_m
    return image


def test_at_rest_means_a_fresh_still_arm_whose_commander_is_not_servoing():
    assert rest_refusal(arm_state(), "bubble") is None
    assert rest_refusal(arm_state(speed=(0.0005, 0, 0, 0, 0, 0.002)), "bubble") is None  # encoder jitter
    assert "arm_commander-bubble running" in rest_refusal(None, "bubble")
    assert "moving (5.0 mm/s" in rest_refusal(arm_state(speed=(0.0, 0.005, 0, 0, 0, 0)), "bubble")
    assert "moving" in rest_refusal(arm_state(speed=(0, 0, 0, 0.05, 0, 0)), "bubble")
    assert "servoing" in rest_refusal(arm_state(servo_active=True), "bubble")


@pytest.mark.parametrize("seed", range(20))
def test_depth_noise_alone_is_never_contact(seed):
    image = noise(seed)
    assert np.count_nonzero(image > CONTACT_DEFORMATION_M) > 20  # single pixels do cross the threshold ...
    assert contact_pixels(image) == 0  # ... the filtered image does not
    assert contact_refusal(deformation(image), "bubble") is None


@pytest.mark.parametrize("depth_m", [1e-3, 2e-3, 5e-3])  # 5 mm: the pushing scene's press at its start
def test_a_pressed_patch_is_contact_and_refused_with_its_depth(depth_m):
    refused = contact_refusal(deformation(pressed(depth_m, seed=3)), "bubble")
    assert refused is not None and "in contact" in refused and "px of its membrane" in refused
    deepest_mm = float(refused.split("deepest ")[1].split(" mm")[0])
    assert depth_m * 1e3 <= deepest_mm <= depth_m * 1e3 + 1.0  # the press plus at most 5 sigma of noise


def test_contact_is_the_bubble_cameras_own_threshold():
    from hydrosoft.drivers.bubble.deformation import CONTACT_THRESHOLD_M

    assert CONTACT_DEFORMATION_M == CONTACT_THRESHOLD_M


def test_a_small_contact_still_counts_but_one_hot_pixel_does_not():
    assert contact_refusal(deformation(pressed(1e-3, side_px=3)), "bubble") is not None  # a 3 x 3 px patch
    image = np.zeros(SHAPE)
    image[10, 10] = 0.01  # a single bad pixel, 10 mm
    assert contact_pixels(image) == 0


def test_a_membrane_the_camera_cannot_see_is_not_free_of_contact():
    assert "bubble_camera-bubble running" in contact_refusal(None, "bubble")
    blind = np.full(SHAPE, np.nan)
    blind[:40] = 0.0  # a third of the image returns depth
    assert "sees only 33%" in contact_refusal(deformation(blind), "bubble")
    half = np.full(SHAPE, np.nan)
    half[:60] = 0.0
    assert contact_refusal(deformation(half), "bubble") is None  # no-return pixels count as no contact


def test_the_readings_of_a_tare_must_be_steady():
    rng = np.random.default_rng(0)
    steady = np.array([1.2, -0.8, 2.5, 0.04, -0.03, 0.02]) + rng.normal(0, [0.03] * 3 + [0.002] * 3, (50, 6))
    assert spread_refusal(steady) is None
    bumped = steady.copy()
    bumped[30:, 2] += 2 * MAX_SPREAD_N
    assert "changed by 1.0" in spread_refusal(bumped)
    twisted = steady.copy()
    twisted[10:, 5] += 0.2
    assert "something touched the sensor" in spread_refusal(twisted)
    assert spread_refusal(np.empty((0, 6))) == "no F/T reading to average"


def test_the_ft300_noise_alone_never_refuses_a_tare_but_a_brief_touch_does():
    rng = np.random.default_rng(1)
    rest = np.array([1.2, -0.8, 2.5, 0.04, -0.03, 0.02])
    tares = [quantized(rest + frame_noise(rng, (50, 6))) for _ in range(300)]  # 0.5 s at 100 Hz, datasheet noise
    assert [spread_refusal(w) for w in tares] == [None] * len(tares)
    touched = tares[0].copy()
    touched[20:30, 0] += 0.8  # a touch of 0.8 N for 0.1 s
    assert "something touched the sensor" in spread_refusal(touched)


def test_the_tare_rule_needs_rest_and_no_contact():
    clear = deformation(noise(1))
    assert tare_refusal(arm_state(), clear, "bubble") is None
    assert "moving" in tare_refusal(arm_state(speed=(0.01, 0, 0, 0, 0, 0)), clear, "bubble")
    assert "in contact" in tare_refusal(arm_state(), deformation(pressed(5e-3)), "bubble")
    assert "arm state" in tare_refusal(None, deformation(pressed(5e-3)), "bubble")
