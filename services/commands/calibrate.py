"""``hydrosoft-stack calibrate task-frame CONFIG``: measure ``scene.task_frame`` from the tracked object.

Put the object on the table where and as the task should start it (the task scene's initial object pose:
the pushing cube resting on its base, faces along the table's axes as you want the task's x and y), with the stack
running (``hydrosoft-stack launch CONFIG``; only the tag tracker is read). The command averages the object poses the
tag tracker publishes for ``--seconds``, finds the level frame that carries the task's initial object pose onto
them (a turn about the base's z and a shift: the table top's height comes from the object resting on it), and
prints the ``task_frame = [...]`` line for the config's ``[scene]`` table, with the spread of the poses it used.

It refuses (exit 1) when no pose arrives (is the stack up, the object in view?) or when the object is not level
as the task starts it (tilted more than ``MAX_TASK_FRAME_TILT_DEG``: on another face, or propped up). It never
moves the arm.
"""

from __future__ import annotations

import argparse
import asyncio
import math
import sys
import time

import numpy as np
import torch

from hydrosoft.geometry import se3
from hydrosoft.services.bus import messages as msg
from hydrosoft.services.bus.config import MAX_TASK_FRAME_TILT_DEG, ConfigError, StackConfig, load_config

DEFAULT_SECONDS = 2.0
MIN_POSES = 5  # fewer tracked poses than this within the window: refuse (the object is barely in view)


class CalibrationError(RuntimeError):
    """The task frame cannot be measured; the message says why and what to do."""


def circular_mean(angles: torch.Tensor) -> torch.Tensor:
    """The mean direction (rad) of ``angles (n,)`` (rad): the angle of the mean unit vector, so it does not break
    where the angles wrap at +-pi."""
    return torch.atan2(torch.sin(angles).mean(), torch.cos(angles).mean())


def level_frame(object_poses: torch.Tensor, initial_pose: torch.Tensor) -> tuple[torch.Tensor, float]:
    """The level ``T_base_task`` ``(7,)`` that carries the task's initial object pose ``(7,)`` (task frame) onto
    the mean of the measured object poses ``(n, 7)`` (base frame), and the tilt (deg) of that mean from level.

    Each pose gives ``T = P_base P_task^-1``; the frame's yaw is the circular mean of their yaws, its position the
    mean of ``p_base - R_z(yaw) p_task``; the tilt is the largest angle between a ``T``'s z axis and the base's.
    """
    initial = initial_pose.double().expand_as(object_poses)
    frames = se3.compose(object_poses.double(), se3.inverse(initial))
    R = se3.quat_to_matrix(frames[:, 3:])
    tilt = float(torch.rad2deg(torch.arccos(R[:, 2, 2].clamp(-1.0, 1.0))).max())
    yaw = circular_mean(se3.yaw(frames))
    turn = torch.stack([torch.cos(yaw / 2), torch.zeros(()), torch.zeros(()), torch.sin(yaw / 2)]).double()
    position = (object_poses[:, :3].double() - se3.quat_rotate(turn, initial[:, :3])).mean(0)
    return torch.cat([position, turn]), tilt


def spread(object_poses: torch.Tensor) -> tuple[float, float]:
    """The poses' position spread (mm, the largest per-axis standard deviation) and yaw spread (deg, std)."""
    position_mm = 1e3 * float(object_poses[:, :3].double().std(0, correction=0).max())
    yaws = se3.yaw(object_poses.double())
    mean = circular_mean(yaws)
    yaw_deg = math.degrees(float(torch.atan2(torch.sin(yaws - mean), torch.cos(yaws - mean)).square().mean().sqrt()))
    return position_mm, yaw_deg


async def tracked_poses(config: StackConfig, seconds: float) -> torch.Tensor:
    """Every object pose ``(n, 7)`` (base frame) the running stack's tag tracker published within ``seconds``."""
    from hydrosoft.services.client import StackClient

    client = StackClient(config)
    poses = []
    try:
        subscriber = client.subscribe("tag_tracker", ("object_pose/",))
        loop = asyncio.get_running_loop()
        deadline = loop.time() + seconds
        while (remaining := deadline - loop.time()) > 0:
            if "object_pose/object" in await subscriber.wait(remaining):
                pose = subscriber.latest("object_pose/object", math.inf, msg.ObjectPose).value.pose
                poses.append(np.asarray(pose, dtype=np.float64))
    finally:
        client.close()
    return torch.as_tensor(np.array(poses, dtype=np.float64).reshape(-1, 7))


def measure(config: StackConfig, seconds: float) -> tuple[torch.Tensor, int, tuple[float, float]]:
    """``(T_base_task (7,), poses used, (position spread mm, yaw spread deg))``; CalibrationError when it
    cannot be measured."""
    from hydrosoft.tasks import make_task

    poses = asyncio.run(tracked_poses(config, seconds))
    if poses.shape[0] < MIN_POSES:
        raise CalibrationError(
            f"{poses.shape[0]} object poses from the tag tracker in {seconds} s (need {MIN_POSES}): is the stack "
            f"running (hydrosoft-stack launch CONFIG) and the object in the tag camera's view? "
            f"(hydrosoft-stack status CONFIG shows the tracker's rate)")
    frame, tilt = level_frame(poses, make_task(config.scene.task).initial_pose())
    if tilt > MAX_TASK_FRAME_TILT_DEG:
        raise CalibrationError(
            f"the object is {tilt:.1f} deg from the {config.scene.task} task's starting orientation about a "
            f"horizontal axis (at most {MAX_TASK_FRAME_TILT_DEG} deg): set it on the table as the task starts it "
            "(resting on the same face), then measure again")
    return frame, poses.shape[0], spread(poses)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("config", help="the stack config (its [scene] task, its tag tracker's endpoint)")
    parser.add_argument("--seconds", type=float, default=DEFAULT_SECONDS,
                        help=f"how long to average the tracked poses (default {DEFAULT_SECONDS} s)")


def run(args: argparse.Namespace) -> int:
    try:
        config = load_config(args.config)
    except (ConfigError, OSError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    tic = time.monotonic()
    try:
        frame, used, (position_mm, yaw_deg) = measure(config, args.seconds)
    except CalibrationError as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    values = ", ".join(f"{v:.6f}" for v in frame.tolist())
    print(f"# {used} object poses in {time.monotonic() - tic:.1f} s; spread {position_mm:.2f} mm, {yaw_deg:.2f} deg "
          f"(the tracker's noise: large values mean a poor view)")
    print(f"# the {config.scene.task} task's origin (its table top) in the base frame; put this in [scene] of "
          f"{args.config}:")
    print(f"task_frame = [{values}]")
    return 0
