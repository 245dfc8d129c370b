"""What the material-fit tests share: the non-default material they record with, and a recording's replay batches."""

from __future__ import annotations

from pathlib import Path

from hydrosoft.bench import material_fit
from hydrosoft.bench.wrench_replay import load_recordings

TRUTH = {"E": 3e5 * 1.7, "K": 1e5 * 0.6, "mu": 0.35}
"""The plant's material in the fit tests: E x1.7 and K x0.6 of the defaults, mu 0.35 (the issue's example)."""


def replay_batches(path: Path) -> list:
    """The replay batches of every trajectory of the recording at ``path``."""
    groups = load_recordings([path])
    return material_fit.replay_batches(groups, {(g.object, t.index) for g in groups for t in g.trajectories})
