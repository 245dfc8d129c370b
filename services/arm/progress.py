"""Progress: a goal whose object stopped approaching its target ends early, with the reason, not at its timeout.

A goal can hold still short of its tolerance: the planner's cost has its minimum outside the tolerance (a cost term
that fights the goal, an unreachable yaw), the tolerance is tighter than the tracker's noise, or the object is
wedged. The planner would then press on it and replan until the goal's timeout. ``ProgressWatch`` tells it to stop
once the goal's ADD error (mm) has not fallen ``PROGRESS_MM`` below where it last made progress for
``planner.stall_s`` seconds of planning and at least ``MIN_CYCLES`` planning cycles.

Noise: the error judged is the median of the samples of the last ``FILTER_S`` seconds (a spike of the tracker does
not move it), and progress is counted against the error at the last progress, not the latest sample, so jitter of
a few tenths of a millimetre about a plateau is never progress. A goal still moving towards its tolerance faster
than ``PROGRESS_MM / stall_s`` (0.05 mm/s at the default 10 s) is never ended. Nothing ends while the latest error
lies within the tolerance: the goal then settles (the planner's ``SETTLE_S``) or leaves it again.

Time counts only while the planner plans: ``pause`` (inputs stale, the bubble off the object, a re-approach) stops
the clock until the next ``update``; ``restart`` (after a re-approach: a new contact and a fresh solver) judges the
goal afresh. Times are in seconds on one monotonic clock (the planner's ``time.monotonic()``).
"""

from __future__ import annotations

import math
import statistics
from collections import deque
from dataclasses import dataclass, field

PROGRESS_MM = 0.5  # the filtered error must fall this far below its value at the last progress to be progress
FILTER_S = 1.0  # the error judged is the median of the samples of this many seconds (the newest one's included)
#: A stall also takes this many planning cycles without progress: a planner starved by the machine's load, which
#: solved a few times in ``stall_s``, has not had its chance yet.
MIN_CYCLES = 20


@dataclass
class ProgressWatch:
    """One goal's progress. stall_s: planning time without progress that ends the goal (``planner.stall_s``, s).
    tolerance_mm: the goal's tolerance (mm). The rest is the watch's state: ``active_s`` the planning time so far,
    ``last_s`` the time of the last ``update`` (None after a pause), ``samples`` the recent ``(time s, error mm)``,
    ``reference_mm`` the filtered error at the last progress (inf before the first update), ``progress_s`` the
    planning time then, ``cycles`` the updates since, ``best_mm`` the lowest filtered error."""

    stall_s: float
    tolerance_mm: float
    active_s: float = 0.0
    last_s: float | None = None
    samples: deque[tuple[float, float]] = field(default_factory=deque)
    reference_mm: float = math.inf
    progress_s: float = 0.0
    cycles: int = 0
    best_mm: float = math.inf

    def update(self, now_s: float, error_mm: float) -> str | None:
        """Note one planning cycle's ADD error ``error_mm`` (mm) at ``now_s`` (s); the reason to end the goal when
        it has stalled, else None."""
        if self.last_s is not None:
            self.active_s += max(0.0, now_s - self.last_s)
        self.last_s = now_s
        self.samples.append((now_s, error_mm))
        while self.samples[0][0] < now_s - FILTER_S:
            self.samples.popleft()
        filtered = statistics.median(error for _, error in self.samples)
        self.best_mm = min(self.best_mm, filtered)
        if filtered < self.reference_mm - PROGRESS_MM:
            self.reference_mm, self.progress_s, self.cycles = filtered, self.active_s, 0
            return None
        self.cycles += 1
        stalled_s = self.active_s - self.progress_s
        if error_mm <= self.tolerance_mm or stalled_s < self.stall_s or self.cycles < MIN_CYCLES:
            return None
        return (f"no progress: error {filtered:.2f} mm (best {self.best_mm:.2f} mm, tolerance "
                f"{self.tolerance_mm:g} mm) did not fall {PROGRESS_MM:g} mm below {self.reference_mm:.2f} mm in "
                f"{stalled_s:.1f} s of planning ({self.cycles} cycles; planner.stall_s = {self.stall_s:g})")

    def pause(self) -> None:
        """The planner does not plan now: the time until the next ``update`` does not count."""
        self.last_s = None

    def restart(self) -> None:
        """Judge the goal afresh from the next ``update`` on (a new contact after a re-approach)."""
        self.active_s, self.last_s, self.reference_mm, self.progress_s, self.cycles = 0.0, None, math.inf, 0.0, 0
        self.samples.clear()
