"""``DurationStats``: how often a repeated job of a simulated device ran and how long it took, for its log lines."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class DurationStats:
    """How often a repeated job ran and how long it took, since the last ``summary``."""

    name: str
    count: int = 0
    total_s: float = 0.0
    max_s: float = 0.0

    def add(self, duration_s: float, runs: int = 1) -> None:
        """Count ``runs`` runs done together in ``duration_s`` s (the max is per such batch)."""
        self.count += runs
        self.total_s += duration_s
        self.max_s = max(self.max_s, duration_s)

    def summary(self, window_s: float) -> str:
        """``"<name> <rate> Hz, <mean> ms mean, <max> ms max"`` over ``window_s`` s (mean per run); starts a new
        window."""
        mean_ms = 1e3 * self.total_s / self.count if self.count else 0.0
        text = f"{self.name} {self.count / window_s:.1f} Hz, {mean_ms:.1f} ms mean, {1e3 * self.max_s:.1f} ms max"
        self.count, self.total_s, self.max_s = 0, 0.0, 0.0
        return text
