"""The whole sim stack as processes for the end-to-end tests: a private copy of ``deploy/sim.toml``, the launcher
as a subprocess in its own session, and the check that none of its processes is left.

Every process is stopped by its pid (the launcher's process group; the launcher stops its services by theirs).
"""

from __future__ import annotations

import asyncio
import itertools
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from hydrosoft.services.bus import messages as msg
from hydrosoft.services.client import StackClient
import loopback

SIM_TOML = Path(__file__).parents[2] / "deploy" / "sim.toml"
SIM_BIMANUAL_TOML = Path(__file__).parents[2] / "deploy" / "sim-bimanual.toml"
READY_TIMEOUT_S = 240.0  # every service up and READY on a busy 2-core machine
READY_POLL_S = 0.2  # between the status requests of a launch's wait for ready, s (a loopback request each: no load)
STOP_BOUND_S = 10.0


def free_ur_host(taken: tuple[str, ...] = ()) -> str:
    """A free 127.0.0.N, not in ``taken``, for this module's simulated UR controllers (``loopback.free_ur_host``)."""
    return loopback.free_ur_host(60, 60, taken)


def quick_planner(text: str) -> str:
    """A sim config ``text`` (deploy/sim.toml's) with the quick planner preset instead of the paper's: eager, ready
    in seconds (the paper's compiles for minutes at every cold start, too long for a test)."""
    assert 'preset = "paper"' in text, "the config names no paper planner preset"
    return text.replace('preset = "paper"', 'preset = "quick"', 1)


def sim_toml_text(compiled_plant: bool = False) -> str:
    """deploy/sim.toml's text with the quick planner (``quick_planner``), its plant compiled (``[sim] compile``,
    30-60 s before sim_world is READY) only when asked: only the end-to-end goals, where the cube must follow the
    bubble in real time, pay for it at every start."""
    text = quick_planner(SIM_TOML.read_text())
    return text if compiled_plant else re.sub(r"(\[sim\][^\[]*?)compile = true", r"\1compile = false", text)


def place_scene(text: str, task_frame: list[float]) -> str:
    """A sim config ``text`` with its scene moved to ``task_frame`` (``T_base_task``, a turn about z): the tag
    camera and the workspace box move with it, so the base-frame numbers all change and the physics does not."""
    from hydrosoft.services.bus.config import parse_config
    from hydrosoft.services.arm.task_frame import TaskFrame

    config = parse_config(text)
    frame = TaskFrame.from_pose(task_frame)
    camera = frame.to_base(torch.tensor(config.camera.pose, dtype=torch.float64)).tolist()
    corners = torch.tensor(list(itertools.product(*zip(config.limits.workspace_min, config.limits.workspace_max))),
                           dtype=torch.float64)
    corners = frame.points_to_base(corners)
    low, high = corners.min(0).values.tolist(), corners.max(0).values.tolist()
    text = text.replace("[scene]\n", f"[scene]\ntask_frame = {list(task_frame)}\n", 1)
    text = re.sub(r"^pose = \[[^\]]*\]", f"pose = {camera}", text, count=1, flags=re.M)  # the tag camera's
    text = re.sub(r"workspace_min = \[[^\]]*\]", f"workspace_min = {low}", text, count=1)
    return re.sub(r"workspace_max = \[[^\]]*\]", f"workspace_max = {high}", text, count=1)


def stack_config(tmp_path: Path, compiled_plant: bool = False, task_frame: list[float] | None = None,
                 object_offset_m: tuple[float, float] | None = None, task: str = "pushing") -> Path:
    """deploy/sim.toml with its run_dir, FT 300 link and UR address made private to this test, the scene of
    ``task`` on the table (``scene.task``: pushing, rotation or rolling), at ``task_frame`` when one is given
    (``place_scene``), and sim_world's object moved by ``object_offset_m`` (m, task frame x, y) from under the bubble
    when one is given."""
    run_dir = tmp_path / "run"
    text = sim_toml_text(compiled_plant)
    assert '\ntask = "pushing"' in text
    text = text.replace('\ntask = "pushing"', f'\ntask = "{task}"', 1)
    if task_frame is not None:
        text = place_scene(text, task_frame)
    if object_offset_m is not None:
        text = text.replace("[sim]\n", f"[sim]\nobject_offset_m = {list(object_offset_m)}\n", 1)
    text = text.replace('"/tmp/hydrosoft-sim/ft300-bubble"', f'"{run_dir}/ft300-bubble"')
    text = text.replace('"/tmp/hydrosoft-sim"', f'"{run_dir}"').replace('"127.0.0.2"', f'"{free_ur_host()}"')
    path = tmp_path / "sim.toml"
    path.write_text(text)
    return path


def bimanual_stack_config(tmp_path: Path) -> Path:
    """deploy/sim-bimanual.toml (compiled plant, as deployed) with its run_dir, both FT 300 links and both UR
    addresses made private to this test."""
    run_dir = tmp_path / "run"
    text = SIM_BIMANUAL_TOML.read_text().replace('"/tmp/hydrosoft-bimanual', f'"{run_dir}')
    left = free_ur_host()
    text = text.replace('"127.0.0.3"', f'"{left}"').replace('"127.0.0.4"', f'"{free_ur_host((left,))}"')
    path = tmp_path / "sim-bimanual.toml"
    path.write_text(text)
    return path


class Stack:
    """The launcher as a subprocess in its own session, its output collected to a file."""

    def __init__(self, config: Path, log: Path) -> None:
        self.config, self.log = config, log
        self._out = log.open("wb")
        self.process = subprocess.Popen([sys.executable, "-m", "hydrosoft.services.commands.cli", "launch", str(config)],
                                        stdout=self._out, stderr=subprocess.STDOUT, start_new_session=True)

    def text(self) -> str:
        return self.log.read_text(errors="replace")

    def wait_ready(self, client: StackClient) -> None:
        deadline = time.monotonic() + READY_TIMEOUT_S
        while time.monotonic() < deadline:
            assert self.process.poll() is None, f"the launcher exited early:\n{self.text()[-4000:]}"
            try:
                reply = asyncio.run(asyncio.wait_for(client.status(), 5.0))
            except Exception:  # noqa: BLE001 - not up yet
                reply = None
            # up, and the planner receives object poses (the tracker's first detections come after its READY; a
            # Start before them is refused: "no fresh input")
            status = None if reply is None else reply.status
            if status is not None and status.received_hz.get("object_pose/object", 0) > 0:
                return
            time.sleep(READY_POLL_S)
        raise AssertionError(f"the stack did not become ready within {READY_TIMEOUT_S} s:\n{self.text()[-4000:]}")

    def stop(self) -> float:
        """SIGINT the launcher; the seconds until it exited (SIGKILL of its group after the bound)."""
        if self.process.poll() is not None:
            return 0.0
        tic = time.monotonic()
        os.killpg(self.process.pid, signal.SIGINT)
        try:
            self.process.wait(STOP_BOUND_S + 5)
        except subprocess.TimeoutExpired:
            os.killpg(self.process.pid, signal.SIGKILL)
            self.process.wait(5)
        self._out.close()
        return time.monotonic() - tic


def children_left(session_pid: int) -> list[str]:
    """Processes still in the launcher's session (``ps``), excluding zombies."""
    out = subprocess.run(["ps", "-eo", "pid,sid,stat,args"], capture_output=True, text=True).stdout.splitlines()
    return [line for line in out[1:] if line.split()[1] == str(session_pid) and not line.split()[2].startswith("Z")]


def assert_stopped_in_order(stack: Stack, elapsed_s: float, arms: tuple[str, ...]) -> None:
    """The launcher stopped within ``STOP_BOUND_S`` (``elapsed_s``, from ``Stack.stop``), left no process, and logged
    the planner stopped first, then every arm's commander, and sim_world after them."""
    assert elapsed_s < STOP_BOUND_S, elapsed_s
    assert not children_left(stack.process.pid), children_left(stack.process.pid)
    text = stack.text()
    planner, sim_world = text.find("stopped planner"), text.find("stopped sim_world")
    commanders = [text.find(f"stopped arm_commander-{arm}") for arm in arms]
    assert -1 not in (planner, sim_world, *commanders), text[-3000:]
    assert planner < min(commanders) and max(commanders) < sim_world, text[-3000:]


async def tracked_object_pose(client: StackClient) -> np.ndarray:
    """The tag tracker's newest object pose ``(7,)`` (base frame, m and wxyz), at most 1 s old, waiting up to 2 s for
    the subscription's first message."""
    poses = client.subscribe("tag_tracker", ("object_pose/object",))
    await poses.wait(2.0)
    return np.asarray(poses.latest("object_pose/object", 1.0, msg.ObjectPose).value.pose)
