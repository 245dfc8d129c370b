"""``hydrosoft-stack capture reference CONFIG --arm ARM [--frames N] [--out PATH]``: capture a Soft Bubble's
reference membrane (its undeformed depth image) for lab mode.

Opens the arm's depth camera as the bubble camera service does (``depth.device`` at the configured size, rate and
depth unit; stop that service first, a device opens once), takes the median of ``--frames`` frames
(``drivers.bubble.reference.capture_reference``) and writes the ``.npz`` reference file to ``--out``, by default the
file the config's ``depth.reference`` names. Nothing may touch the membrane meanwhile: the bubble at rest, inflated
to its working pressure, away from the object.
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import time

import numpy as np

from hydrosoft.drivers.bubble.reference import Reference, capture_reference, save_reference
from hydrosoft.drivers.errors import DriverError
from hydrosoft.services.bubble_camera import lab_depth_camera
from hydrosoft.services.bus.config import ConfigError, load_config

DEFAULT_FRAMES = 30  # one second at 30 Hz: enough for the median to reject a camera's outliers


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``hydrosoft-stack capture reference``."""
    parser.add_argument("config", help="the stack's TOML config (deploy/lab.toml)")
    parser.add_argument("--arm", required=True, help="the arm whose bubble to capture (its [[arms]] name)")
    parser.add_argument("--frames", type=int, default=DEFAULT_FRAMES,
                        help=f"frames to take the median of (default {DEFAULT_FRAMES})")
    parser.add_argument("--out", default=None,
                        help="the .npz file to write (default: the arm's depth.reference in the config)")


async def _capture(camera, frames: int) -> np.ndarray:
    await camera.connect()
    try:
        return await capture_reference(camera, frames)
    finally:
        await camera.close()


def run(args: argparse.Namespace) -> int:
    """Capture and write the reference; the exit status (2: a bad config or option, 1: the camera failed)."""
    try:
        config = load_config(args.config)
        depth = config.arm(args.arm).depth
        camera = lab_depth_camera(config, args.arm)
    except ConfigError as error:
        print(f"capture reference: {error}", file=sys.stderr)
        return 2
    out = args.out or depth.reference
    if not out:
        print(f"capture reference: give --out PATH.npz (arms.{args.arm}.depth.reference is empty)", file=sys.stderr)
        return 2
    if args.frames < 1:
        print(f"capture reference: --frames must be at least 1, got {args.frames}", file=sys.stderr)
        return 2
    try:
        reference_m = asyncio.run(_capture(camera, args.frames))
    except DriverError as error:
        print(f"capture reference: {error}", file=sys.stderr)
        return 1
    path = save_reference(out, Reference(reference_m, depth.depth_scale_m, args.frames, time.time_ns()))
    returned = np.isfinite(reference_m)
    median_m = float(np.median(reference_m[returned])) if returned.any() else float("nan")
    print(f"wrote {path}: {reference_m.shape[1]}x{reference_m.shape[0]} px from {args.frames} frames of "
          f"{camera}, median depth {median_m * 1e3:.1f} mm, {int((~returned).sum())} px without return")
    if str(path) != depth.reference:
        print(f"set arms.{args.arm}.depth.reference = \"{path}\" in {args.config} to use it")
    return 0
