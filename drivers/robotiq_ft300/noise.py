"""The FT 300's signal noise: one model for the simulator that adds it and for the material fit that weighs by it.

Each stream frame carries the true wrench plus independent Gaussian noise per component, of standard deviation
``SIGNAL_NOISE`` (Robotiq's datasheet figures), then rounded to the frame's resolution (``RESOLUTION``). The
simulated FT 300 (``simulator.SimulatedFT300``, ``sim.ft_noise`` in the stack config) sends such frames, the
synthetic recordings of the fit's tests and benchmark (``hydrosoft.bench.synthetic_wrench``) average them, and the
fit (``hydrosoft.bench.material_fit``) divides each component's error by ``SIGNAL_NOISE``.
"""

from __future__ import annotations

import numpy as np

from hydrosoft.drivers.robotiq_ft300.protocol import COUNTS_PER_UNIT

#: Standard deviation per frame of Fx, Fy, Fz (N), Mx, My (N m), Mz (N m): Robotiq's datasheet signal noise.
SIGNAL_NOISE = np.array([0.1, 0.1, 0.1, 0.005, 0.005, 0.003])
#: One count of a frame: 0.01 N for forces, 0.001 N m for torques.
RESOLUTION = 1 / COUNTS_PER_UNIT


def frame_noise(rng: np.random.Generator, shape: tuple[int, ...], scale: float = 1.0) -> np.ndarray:
    """Noise ``(*shape)`` (the last axis 6: N, N m) of as many frames: Gaussian, ``scale * SIGNAL_NOISE`` per
    component (0 gives zeros, still drawn, so a generator's later draws do not depend on the scale)."""
    return rng.normal(size=shape) * scale * SIGNAL_NOISE


def quantized(wrenches: np.ndarray) -> np.ndarray:
    """``wrenches (..., 6)`` (N, N m) rounded to the frame's resolution, as a frame carries them."""
    return np.round(wrenches / RESOLUTION) * RESOLUTION
