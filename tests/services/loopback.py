"""Loopback addresses for the simulated UR controllers (and the simulated hosts of a split stack) that tests start.

The ur_rtde client's ports are fixed, so tests that run controllers side by side (pytest-xdist, or a test still
tearing its controller down) each take their own 127.0.0.N. Ranges in use: 21-59 split-stack hosts, 60-249 UR
controllers.
"""

from __future__ import annotations

import os
import socket
from collections.abc import Sequence

from hydrosoft.drivers.ur.config import RTDE_PORT, SIM_CONTROL_PORT


def free_ur_host(first: int, count: int, taken: tuple[str, ...] = ()) -> str:
    """A 127.0.0.N with N in ``first .. first + count - 1`` (tried from a pid-dependent start), not in ``taken``,
    whose RTDE and simulator-control ports are free now. Raises RuntimeError when none is."""
    return free_loopback_address(first, count, (RTDE_PORT, SIM_CONTROL_PORT), taken)


def free_loopback_address(first: int, count: int, ports: Sequence[int], taken: tuple[str, ...] = ()) -> str:
    """A 127.0.0.N with N in ``first .. first + count - 1`` (tried from a pid-dependent start), not in ``taken``,
    on which every one of ``ports`` is free now. Raises RuntimeError when none is."""
    for offset in range(count):
        host = f"127.0.0.{first + (os.getpid() + offset) % count}"
        if host in taken:
            continue
        try:
            for port in ports:
                with socket.socket() as probe:
                    probe.bind((host, port))
        except OSError:
            continue
        return host
    raise RuntimeError(f"no free 127.0.0.N (N in {first}..{first + count - 1}) with the ports {ports} free")
