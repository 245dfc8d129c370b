"""The ``drift`` section of ``hydrosoft-stack bench model``: float32 against float64 over a back-and-forth rollout.

The rolling scene (a 25 mm cylinder under the bubble, on the table) with the object's surface at ``spacing`` (default
10 mm). The bubble moves +``amplitude_m`` along x per step for ``leg`` steps, then back for ``leg`` steps, and so on
for ``steps`` steps (a whole number of round trips ends where it started). Run once per contact model and dtype from
the same start. Reported per model and dtype: how far the object ends from its start (``drift_mm``, ``drift_rad``),
and per model the largest float32-float64 gap over the rollout (``f32_gap_um``, ``f32_gap_rad``). A drift that both
dtypes share is the model's (stick-slip under a quasi-dynamic update does not retrace its path), not rounding.

Run time, eager, one thread: about 50 s of CPU per 1000 steps and rollout, so ``--drift-steps 1000`` (four rollouts)
takes about 4 minutes on an idle core; it took 38 minutes on the 2-core machine under heavy load (the default 100:
under a minute idle).
"""

from __future__ import annotations

import time

import msgspec
import torch

DRIFT_STEPS = 100
DRIFT_MODELS = ("nh", "nh_pressure_normal")


def _rotation_between(a: torch.Tensor, b: torch.Tensor) -> float:
    """Angle (rad) of the rotation from pose ``a`` to pose ``b``, both ``(7,)``."""
    from hydrosoft.geometry import se3

    relative = se3.quat_multiply(se3.quat_conjugate(a[3:]), b[3:])
    return se3.so3_log(relative).norm().item()


def rollout_poses(model_name: str, dtype: torch.dtype, steps: int, spacing: float = 0.01,
                  amplitude_m: float = 1e-3, leg: int = 25) -> torch.Tensor:
    """The object's pose after each step of the back-and-forth rollout: ``(steps + 1, 7)`` in float64, the start
    first."""
    from hydrosoft.dynamics import step
    from hydrosoft.scene import compile_scene
    from hydrosoft.tasks.scenes import task_scene

    replace = msgspec.structs.replace
    scene = task_scene("rolling")
    scene = replace(scene, contact=model_name, object=replace(scene.object, spacing=spacing))
    model, state, _ = compile_scene(scene, dtype=dtype)
    u = torch.zeros(1, model.n_bodies, 6, dtype=dtype)
    bubble = model.body_names.index("bubble")
    poses = [state.object_pose[0].double()]
    for k in range(steps):
        u[0, bubble, 0] = amplitude_m if (k // leg) % 2 == 0 else -amplitude_m
        state = step(model, state, u)
        poses.append(state.object_pose[0].double())
    return torch.stack(poses)


def drift(models: tuple[str, ...] = DRIFT_MODELS, steps: int = DRIFT_STEPS, spacing: float = 0.01,
          progress=lambda text: None) -> list[dict]:
    """One row per model and dtype (see the module docstring); ``progress`` gets a line per rollout."""
    rows = []
    for name in models:
        poses = {}
        for dtype in (torch.float64, torch.float32):
            tic = time.perf_counter()
            poses[dtype] = rollout_poses(name, dtype, steps, spacing)
            wall = time.perf_counter() - tic
            start, end = poses[dtype][0], poses[dtype][-1]
            rows.append({"model": name, "dtype": str(dtype).removeprefix("torch."), "steps": steps,
                         "spacing_m": spacing, "drift_mm": 1e3 * (end[:3] - start[:3]).norm().item(),
                         "drift_rad": _rotation_between(start, end), "wall_s": wall})
            progress(f"drift: {name} {rows[-1]['dtype']}, {steps} steps: {rows[-1]['drift_mm']:.3f} mm, "
                     f"{rows[-1]['drift_rad']:.4f} rad, {wall:.0f} s")
        single, double = poses[torch.float32], poses[torch.float64]
        gap_um = 1e6 * (single[:, :3] - double[:, :3]).norm(dim=-1).max().item()
        gap_rad = max(_rotation_between(a, b) for a, b in zip(double, single))
        for row in rows[-2:]:
            row.update(f32_gap_um=gap_um, f32_gap_rad=gap_rad)
    return rows
