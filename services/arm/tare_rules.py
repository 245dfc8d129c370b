"""When an F/T tare may be taken: pure rules, no sockets.

A tare takes the sensor's mean reading as its zero. Taken while the bubble presses on something, it hides that
load from every later reading (and from ``limits.max_force_n``). So the F/T reader takes one only on request
(``hydrosoft-stack ft tare ARM``), and only when, before and after averaging:

- the arm is at rest: a fresh ``arm_state/ARM`` (at most ``ARM_STATE_MAX_AGE_S`` old) whose TCP twist is below the
  commander's own "moving" speeds (``safety.is_moving``) and whose commander is not servoing towards targets (a
  planner could move the arm into contact during the average);
- the bubble shows no contact: a fresh ``deformation/ARM`` (at most ``DEFORMATION_MAX_AGE_S`` old) in which the
  membrane returns depth on most of the image and no patch is pressed in (``contact_pixels``);
- the readings averaged stayed steady (``spread_refusal``): nothing bumped the sensor meanwhile, judged on means of
  a few frames so the sensor's own noise does not count as a bump.

Each rule returns None when it is met, else the reason, a sentence the operator reads.
"""

from __future__ import annotations

import cv2
import numpy as np

from hydrosoft.services.bus import messages as msg
from hydrosoft.services.arm.safety import MOVING_ANGULAR_SPEED_RAD_S, MOVING_SPEED_M_S, is_moving

#: The newest arm state counts as the arm's state for this long, s (the commander publishes at 25 Hz or more).
ARM_STATE_MAX_AGE_S = 0.5
#: The newest deformation image counts as the membrane's shape for this long, s (the bubble camera sends 10-30 Hz).
DEFORMATION_MAX_AGE_S = 0.5
#: Side of the median filter applied before looking for contact, px. One pixel's depth noise (sim: 0.2 mm Gaussian
#: per pixel) makes 0.6 % of a 160 x 120 image exceed ``CONTACT_THRESHOLD_M`` (2.5 sigma) by chance; the median of
#: 3 x 3 pixels has about 0.42 sigma (0.08 mm), so the threshold is 6 of its sigmas and noise alone never reaches it.
MEDIAN_KERNEL_PX = 3
#: A pixel shows contact when its median-filtered deformation exceeds this, m: the bubble camera's own contact
#: threshold (``drivers.bubble.deformation.CONTACT_THRESHOLD_M``, 0.5 mm; not imported, as that module loads torch),
#: the shallowest press it reports as touching. A press shallower than this everywhere cannot be told from noise
#: and is not refused.
CONTACT_DEFORMATION_M = 5e-4
#: Contact needs at least this many such pixels (a blob, not one hot pixel the median let through).
MIN_CONTACT_PIXELS = 4
#: The membrane must return depth on at least this fraction of the image, or contact cannot be ruled out.
MIN_RETURN_FRACTION = 0.5
#: Largest peak-to-peak change of the force (N) and torque (N m) components over the averaged readings, each first
#: smoothed over ``SPREAD_MEAN_FRAMES``: above it, something touched the sensor or the arm moved during the tare.
MAX_SPREAD_N = 0.5
MAX_SPREAD_NM = 0.05
#: The readings are compared as means of this many frames (0.05 s at 100 Hz). The FT 300's own noise (0.1 N and
#: 0.005 N m per frame, Robotiq's datasheet, ``drivers.robotiq_ft300.noise``; not yet measured on the lab's sensor)
#: spans 0.5 N peak to peak over a tare's 50 raw frames about every second tare (a force axis's range is 4.5 sigma
#: on average); over 5-frame means it spans about 0.2 N, and 0.33 N in one tare of 10,000.
SPREAD_MEAN_FRAMES = 5


def rest_refusal(state: msg.ArmState | None, arm: str) -> str | None:
    """Why the arm is not known to be at rest (None: it is). ``state``: the newest fresh ``ArmState``, or None when
    none came within ``ARM_STATE_MAX_AGE_S``."""
    if state is None:
        return (f"no fresh arm state (arm_state/{arm}, at most {ARM_STATE_MAX_AGE_S} s old): is "
                f"arm_commander-{arm} running?")
    if state.servo_active:
        return f"arm {arm} is servoing towards the planner's targets: stop the goal first"
    if is_moving(state.tcp_speed):
        speed = state.tcp_speed
        return (f"arm {arm} is moving ({np.linalg.norm(speed[:3]) * 1e3:.1f} mm/s, "
                f"{np.linalg.norm(speed[3:]):.3f} rad/s; at rest is below {MOVING_SPEED_M_S * 1e3:.0f} mm/s and "
                f"{MOVING_ANGULAR_SPEED_RAD_S} rad/s)")
    return None


def contact_pixels(deformation: np.ndarray) -> int:
    """How many pixels of ``deformation`` ``(H, W)`` (m, NaN = no return) are pressed in by more than
    ``CONTACT_DEFORMATION_M`` after a ``MEDIAN_KERNEL_PX`` median filter (pixels without return count as 0)."""
    image = np.nan_to_num(np.asarray(deformation, dtype=np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    filtered = cv2.medianBlur(np.ascontiguousarray(image), MEDIAN_KERNEL_PX)
    return int(np.count_nonzero(filtered > CONTACT_DEFORMATION_M))


def contact_refusal(deformation: msg.MembraneDeformation | None, arm: str) -> str | None:
    """Why the bubble is not known to be free of contact (None: it is). ``deformation``: the newest fresh image, or
    None when none came within ``DEFORMATION_MAX_AGE_S``."""
    if deformation is None:
        return (f"no fresh membrane image (deformation/{arm}, at most {DEFORMATION_MAX_AGE_S} s old): is "
                f"bubble_camera-{arm} running?")
    image = deformation.deformation
    returned = float(np.isfinite(image).mean()) if image.size else 0.0
    if returned < MIN_RETURN_FRACTION:
        return (f"the bubble camera sees only {returned:.0%} of the membrane (at least {MIN_RETURN_FRACTION:.0%} "
                "needed to rule out contact)")
    pressed = contact_pixels(image)
    if pressed >= MIN_CONTACT_PIXELS:
        deepest_mm = float(np.nanmax(image)) * 1e3
        return (f"the bubble is in contact: {pressed} px of its membrane are pressed in by more than "
                f"{CONTACT_DEFORMATION_M * 1e3:.1f} mm (deepest {deepest_mm:.1f} mm); move it clear of everything "
                "and tare again")
    return None


def spread_refusal(wrenches: np.ndarray) -> str | None:
    """Why the readings ``(K, 6)`` (N, N m) averaged for a tare are not steady (None: they are): the peak-to-peak
    change of their ``SPREAD_MEAN_FRAMES``-frame means (of the readings themselves when fewer)."""
    wrenches = np.asarray(wrenches, dtype=np.float64).reshape(-1, 6)
    if wrenches.shape[0] == 0:
        return "no F/T reading to average"
    if wrenches.shape[0] >= SPREAD_MEAN_FRAMES:
        wrenches = np.lib.stride_tricks.sliding_window_view(wrenches, SPREAD_MEAN_FRAMES, axis=0).mean(axis=-1)
    spread = wrenches.max(axis=0) - wrenches.min(axis=0)
    force_n, torque_nm = float(spread[:3].max()), float(spread[3:].max())
    if force_n > MAX_SPREAD_N or torque_nm > MAX_SPREAD_NM:
        return (f"the F/T reading changed by {force_n:.2f} N / {torque_nm:.3f} N m while it was averaged (at most "
                f"{MAX_SPREAD_N} N / {MAX_SPREAD_NM} N m): something touched the sensor or the arm moved")
    return None


def tare_refusal(state: msg.ArmState | None, deformation: msg.MembraneDeformation | None, arm: str) -> str | None:
    """Why a tare of ``arm``'s sensor must be refused now (None: it may be taken): ``rest_refusal``, then
    ``contact_refusal``."""
    return rest_refusal(state, arm) or contact_refusal(deformation, arm)
