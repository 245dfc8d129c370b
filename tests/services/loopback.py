"""Loopback addresses for the simulated UR controllers that tests start.

The ur_rtde client's ports are fixed, so tests that run controllers side by side (pytest-xdist, or a test still
tearing its controller down) each take their own 127.0.0.N.
"""

from __future__ import annotations

import os
import socket

from hydrosoft.drivers.ur.config import RTDE_PORT, SIM_CONTROL_PORT


def free_ur_host(first: int, count: int, taken: tuple[str, ...] = ()) -> str:
    """A 127.0.0.N with N in ``first .. first + count - 1`` (tried from a pid-dependent start), not in ``taken``,
    whose RTDE and simulator-control ports are free now. Raises RuntimeError when none is."""
    for offset in range(count):
        host = f"127.0.0.{first + (os.getpid() + offset) % count}"
        if host in taken:
            continue
        try:
            for port in (RTDE_PORT, SIM_CONTROL_PORT):
                with socket.socket() as probe:
                    probe.bind((host, port))
        except OSError:
            continue
        return host
    raise RuntimeError(f"no free 127.0.0.N (N in {first}..{first + count - 1}) for a simulated UR controller")
