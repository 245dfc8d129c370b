"""The simulator fixture of the FT 300 tests: every simulator a test starts is stopped at teardown."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import pytest

from hydrosoft.drivers.robotiq_ft300.simulator import SimulatedFT300


@pytest.fixture
def make_simulator(tmp_path) -> Iterator[Callable[..., SimulatedFT300]]:
    """``make_simulator(**kwargs)`` starts a ``SimulatedFT300`` behind ``tmp_path/ft300``; all stop at teardown."""
    started: list[SimulatedFT300] = []

    def make(**kwargs: Any) -> SimulatedFT300:
        kwargs.setdefault("link", tmp_path / f"ft300-{len(started)}")
        simulator = SimulatedFT300(**kwargs).start()
        started.append(simulator)
        return simulator

    yield make
    for simulator in started:
        simulator.stop()
