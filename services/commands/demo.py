"""``hydrosoft-stack demo``: a short simulated planar-pushing rollout that prints what happened."""

from __future__ import annotations

import time

import msgspec
import torch

from hydrosoft.dynamics import step
from hydrosoft.geometry import se3
from hydrosoft.scene import compile_scene
from hydrosoft.tasks.scenes import task_scene


def run_demo(steps: int = 20, model: str = "nh", speed_mm: float = 2.0) -> int:
    """Drag the cube of the pushing scene along +x with the bubble and print one line per step."""
    scene = msgspec.structs.replace(task_scene("pushing"), contact=model)
    compiled, state, report = compile_scene(scene)
    print(f"scene: planar pushing, contact model {model}: {report.summary()}")
    bubble = compiled.body_names.index("bubble")
    u = torch.zeros(1, compiled.n_bodies, 6, dtype=compiled.dtype)
    u[0, bubble, 0] = speed_mm / 1000.0
    start = se3.se3_to_se2(state.object_pose)[0]
    print(f"{'step':>4} {'bubble x mm':>11} {'object x mm':>11} {'object y mm':>11} {'yaw deg':>8} "
          f"{'bubble Fz N':>11} {'bubble Fx N':>11} {'table Fx N':>10}")
    t0 = time.perf_counter()
    for k in range(1, steps + 1):
        state = step(compiled, state, u)
        pose = se3.se3_to_se2(state.object_pose)[0]
        per_body = state.forces[0].sum(1)
        table = per_body[compiled.body_names.index("table")] if "table" in compiled.body_names else torch.zeros(3)
        print(f"{k:4d} {1000 * state.body_poses[0, bubble, 0].item():11.2f} {1000 * (pose[0] - start[0]).item():11.2f} "
              f"{1000 * (pose[1] - start[1]).item():11.2f} {torch.rad2deg(pose[2]).item():8.2f} "
              f"{-per_body[bubble, 2].item():11.3f} {per_body[bubble, 0].item():11.3f} {table[0].item():10.3f}")
    elapsed = time.perf_counter() - t0
    moved = 1000 * (se3.se3_to_se2(state.object_pose)[0, 0] - start[0]).item()
    print(f"the bubble moved {steps * speed_mm:.1f} mm, the object {moved:.2f} mm "
          f"({steps} steps in {elapsed:.2f} s, {1e3 * elapsed / steps:.2f} ms per step)")
    return 0
