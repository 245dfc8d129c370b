"""``calibrate task-frame``: the level frame from tracked object poses (plain functions), then the command as a
real process reading poses that this test publishes on the config's tag tracker endpoint."""

from __future__ import annotations

import asyncio
import math
import sys

import pytest
import torch

from hydrosoft.geometry import se3
from hydrosoft.services.bus import messages as msg
from hydrosoft.services.bus.sockets import Bus, Publisher
from hydrosoft.services.commands.calibrate import level_frame, spread
from hydrosoft.services.bus.config import parse_config
from hydrosoft.services.arm.task_frame import TaskFrame
from hydrosoft.tasks import make_task

YAW = math.radians(-35.0)
TRUE_FRAME = [0.52, 0.07, -0.013, math.cos(YAW / 2), 0.0, 0.0, math.sin(YAW / 2)]
PROCESS_TIMEOUT_S = 60.0


def tracked(frame: list[float], n: int, noise_m: float, seed: int = 0) -> torch.Tensor:
    """``n`` poses of the pushing cube at its initial pose in ``frame``, with position noise (m) and 0.2 deg of
    yaw noise."""
    generator = torch.Generator().manual_seed(seed)
    initial = make_task("pushing").initial_pose()
    poses = TaskFrame.from_pose(frame).to_base(initial.expand(n, 7))
    poses[:, :3] += noise_m * torch.randn(n, 3, generator=generator, dtype=torch.float64)
    turn = torch.zeros(n, 6, dtype=torch.float64)
    turn[:, 5] = math.radians(0.2) * torch.randn(n, generator=generator, dtype=torch.float64)
    return se3.retract(poses, turn)


def test_the_level_frame_carries_the_tasks_start_onto_the_tracked_poses():
    frame, tilt = level_frame(tracked(TRUE_FRAME, 200, 0.0005), make_task("pushing").initial_pose())
    torch.testing.assert_close(frame[:3], torch.tensor(TRUE_FRAME[:3], dtype=torch.float64), atol=2e-4, rtol=0)
    assert math.degrees(float(se3.angle_between(frame[3:], torch.tensor(TRUE_FRAME[3:])))) < 0.05
    assert tilt < 0.01
    position_mm, yaw_deg = spread(tracked(TRUE_FRAME, 200, 0.0005))
    assert 0.3 < position_mm < 0.8 and 0.1 < yaw_deg < 0.3


def test_a_tipped_object_shows_as_tilt():
    poses = tracked(TRUE_FRAME, 10, 0.0)
    tipped = se3.retract(poses, torch.tensor([0, 0, 0, math.radians(10.0), 0, 0], dtype=torch.float64))
    assert level_frame(tipped, make_task("pushing").initial_pose())[1] == pytest.approx(10.0, abs=1e-6)


def config_text(tmp_path) -> str:
    return f'run_dir = "{tmp_path}"\n[[arms]]\nname = "bubble"\n'


async def run_command(tmp_path, poses: torch.Tensor | None, seconds: float = 1.5) -> tuple[int, str, str]:
    """Run the command as a process while this test publishes ``poses`` (cycled, 30 Hz) as the tag tracker."""
    path = tmp_path / "stack.toml"
    path.write_text(config_text(tmp_path))
    bus = Bus()
    out = Publisher(bus, parse_config(config_text(tmp_path)).endpoint("tag_tracker"), source="tag_tracker")
    process = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "hydrosoft.services.commands.cli", "calibrate", "task-frame", str(path), "--seconds", str(seconds),
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
    try:
        async def publish():
            k = 0
            while True:
                if poses is not None:
                    pose = poses[k % poses.shape[0]].numpy()
                    await out.send(msg.ObjectPose(object="object", pose=pose, tags_used=(0, 1), quality=1.0),
                                   msg.topic_for(msg.ObjectPose, "object"))
                k += 1
                await asyncio.sleep(1 / 30)

        publishing = asyncio.create_task(publish())
        stdout, stderr = await asyncio.wait_for(process.communicate(), PROCESS_TIMEOUT_S)
        publishing.cancel()
        return process.returncode, stdout.decode(), stderr.decode()
    finally:
        if process.returncode is None:
            process.kill()
            await process.wait()
        bus.close()


def test_the_command_prints_the_task_frame_line_from_the_tracked_poses(tmp_path):
    code, out, err = asyncio.run(run_command(tmp_path, tracked(TRUE_FRAME, 50, 0.0003)))
    assert code == 0, err
    line = next(line for line in out.splitlines() if line.startswith("task_frame = "))
    config = parse_config(config_text(tmp_path) + "[scene]\n" + line + "\n")  # the printed line is a valid config
    measured = torch.tensor(config.scene.task_frame, dtype=torch.float64)
    torch.testing.assert_close(measured[:3], torch.tensor(TRUE_FRAME[:3], dtype=torch.float64), atol=5e-4, rtol=0)
    assert math.degrees(float(se3.angle_between(measured[3:], torch.tensor(TRUE_FRAME[3:])))) < 0.2


def test_the_command_refuses_without_poses_and_says_what_to_check(tmp_path):
    code, out, err = asyncio.run(run_command(tmp_path, None, seconds=0.5))
    assert code == 1 and "task_frame" not in out
    assert "0 object poses" in err and "hydrosoft-stack launch" in err
