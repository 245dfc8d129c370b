"""What the material-fit tests share: the non-default material they record with, and a recording's replay batches."""

from __future__ import annotations

from pathlib import Path

from hydrosoft.bench import material_fit
from hydrosoft.bench.synthetic_wrench import write_synthetic_recording
from hydrosoft.bench.wrench_replay import load_recordings

TRUTH = {"E": 3e5 * 1.7, "K": 1e5 * 0.6, "mu": 0.35}
"""The plant's material in the fit tests: E x1.7 and K x0.6 of the defaults, mu 0.35 (the issue's example)."""


def replay_batches(path: Path) -> list:
    """The replay batches of every trajectory of the recording at ``path``."""
    groups = load_recordings([path])
    return material_fit.replay_batches(groups, {(g.object, t.index) for g in groups for t in g.trajectories})


def noisy_cube_fit(folder: Path) -> tuple[list, material_fit.MaterialFit]:
    """A cube recorded with ``TRUTH`` and the FT 300's noise (shear, twist and both; 6 steps each), written in
    ``folder``, and its replay batches with the NH fit of E, K and mu on them (one replay sub-step)."""
    path = folder / "wrench-cube.mcap"
    write_synthetic_recording(path, "cube", TRUTH, ["shear", "twist", "shear_twist"], steps=6, seed=4, noise_scale=1.0)
    batches = replay_batches(path)
    return batches, material_fit.fit_material(batches, "nh", list(TRUTH), substeps=1)
