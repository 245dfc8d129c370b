"""The progress watch: a goal stalled short of its tolerance ends after ``stall_s`` of planning, with the reason; a
slow approach, the tracker's noise, the time off the object and a goal settling within its tolerance never end
one."""

import re

import numpy as np
import pytest

from hydrosoft.services.arm.progress import FILTER_S, MIN_CYCLES, PROGRESS_MM, ProgressWatch

STALL_S = 10.0
PERIOD_S = 0.1  # a planner cycle at 10 Hz
TOLERANCE_MM = 3.0


def first_end(watch: ProgressWatch, times_s, errors_mm) -> tuple[float | None, str | None]:
    """Feed the watch one sample per cycle; the time and reason of the first end, or (None, None)."""
    for now_s, error_mm in zip(times_s, errors_mm, strict=True):
        reason = watch.update(float(now_s), float(error_mm))
        if reason is not None:
            return float(now_s), reason
    return None, None


def approach_then_plateau(plateau_mm: float, rate_mm_s: float, start_mm: float = 12.0, until_s: float = 40.0):
    """Cycle times (s) and errors (mm): from ``start_mm`` down at ``rate_mm_s`` to a plateau at ``plateau_mm``; the
    plateau's start (s)."""
    times = np.arange(0.0, until_s, PERIOD_S)
    return times, np.maximum(start_mm - rate_mm_s * times, plateau_mm), (start_mm - plateau_mm) / rate_mm_s


def tracker_noise(n: int, seed: int, sigma_mm: float = 0.15) -> np.ndarray:
    """Per-cycle ADD noise (mm): Gaussian jitter of ``sigma_mm`` and, every 3 s, a one-image glitch 2 mm off
    either way."""
    noise = np.random.default_rng(seed).normal(0.0, sigma_mm, n)
    noise[::30] += 2.0
    noise[15::30] -= 2.0
    return noise


@pytest.mark.parametrize("seed", [None, 0, 1, 2])
def test_a_goal_stalled_on_a_plateau_ends_after_stall_s_with_the_reason_and_noise_neither_hastens_nor_hides_it(seed):
    """The soak's stall (3.05 mm against 3 mm): the goal ends ``stall_s`` after the error stopped falling, not at
    its timeout; the tracker's jitter and glitches (seeds 0-2; None: noiseless) do not end it sooner, nor keep it
    going by counting as progress."""
    rate_mm_s = 1.0
    times, errors, plateau_s = approach_then_plateau(3.05, rate_mm_s)
    if seed is not None:
        errors = errors + tracker_noise(len(times), seed)
    end_s, reason = first_end(ProgressWatch(STALL_S, TOLERANCE_MM), times, errors)
    assert end_s is not None, "the stall never ended the goal"
    # the last progress: at most PROGRESS_MM before the plateau, or half the filter's window after it
    assert plateau_s - PROGRESS_MM / rate_mm_s + STALL_S <= end_s <= plateau_s + STALL_S + FILTER_S, (end_s, plateau_s)
    error, best = (float(x) for x in re.match(r"no progress: error ([0-9.]+) mm \(best ([0-9.]+) mm", reason).groups())
    assert abs(error - 3.05) < 0.1 and best <= error and "tolerance 3 mm" in reason, reason
    assert "planner.stall_s = 10" in reason and f"did not fall {PROGRESS_MM:g} mm below" in reason, reason


@pytest.mark.parametrize("seed", [None, 0, 1])
def test_a_slow_steady_approach_is_never_ended(seed):
    """An error falling at 0.1 mm/s (twice ``PROGRESS_MM / stall_s``), with the tracker's noise, runs on until it
    reaches its tolerance; one falling at 0.02 mm/s is too slow to tell from a stall."""
    times = np.arange(0.0, 60.0, PERIOD_S)
    errors = 9.0 - 0.1 * times
    if seed is not None:
        errors = errors + tracker_noise(len(times), seed)
    assert first_end(ProgressWatch(STALL_S, TOLERANCE_MM), times, errors) == (None, None)
    crawling = 9.0 - 0.02 * times
    assert first_end(ProgressWatch(STALL_S, TOLERANCE_MM), times, crawling)[0] is not None


def test_time_off_the_object_is_not_counted_and_a_reapproach_judges_the_goal_afresh():
    """5 s stalled, then 30 s out of contact and re-approaching (paused: no updates) do not end the goal at the
    first cycle after; it ends once the planning time without progress adds up to ``stall_s``. After a
    re-approach (``restart``) a worse error, the object moved meanwhile, is the new reference."""
    watch = ProgressWatch(STALL_S, TOLERANCE_MM)
    before = np.arange(0.0, 5.0, PERIOD_S)
    assert first_end(watch, before, np.full(len(before), 4.0)) == (None, None)
    watch.pause()
    after = np.arange(35.0, 45.0, PERIOD_S)
    end_s, _ = first_end(watch, after, np.full(len(after), 4.0))
    assert end_s == pytest.approx(35.0 + STALL_S - (before[-1] - before[0]))  # 4.9 s before, 5.1 s after

    watch = ProgressWatch(STALL_S, TOLERANCE_MM)
    assert first_end(watch, before, np.full(len(before), 4.0)) == (None, None)
    watch.pause()
    watch.restart()
    again = np.arange(30.0, 30.0 + STALL_S - 1.0, PERIOD_S)  # 6 mm after the re-approach, falling 0.1 mm/s
    assert first_end(watch, again, 6.0 - 0.1 * (again - 30.0)) == (None, None)


def test_a_goal_within_its_tolerance_is_left_to_settle_and_one_jittering_across_it_ends():
    """No progress while within the tolerance is no stall (the goal settles, or leaves the tolerance again); an
    error jittering across a tolerance tighter than the tracker's noise ends on a sample outside it."""
    times = np.arange(0.0, 30.0, PERIOD_S)
    assert first_end(ProgressWatch(STALL_S, TOLERANCE_MM), times, np.full(len(times), 2.9)) == (None, None)
    across = np.where(np.arange(len(times)) % 2 == 0, 2.95, 3.05)
    end_s, reason = first_end(ProgressWatch(STALL_S, TOLERANCE_MM), times, across)
    assert end_s is not None and STALL_S <= end_s <= STALL_S + 2 * PERIOD_S and "best 2.95 mm" in reason, reason


def test_a_planner_starved_by_load_gets_its_cycles_before_a_stall():
    """At one cycle per 3 s the goal is not ended after ``stall_s`` but after ``MIN_CYCLES`` cycles without
    progress."""
    times = np.arange(0.0, 200.0, 3.0)
    end_s, reason = first_end(ProgressWatch(STALL_S, TOLERANCE_MM), times, np.full(len(times), 5.0))
    assert end_s == pytest.approx(3.0 * MIN_CYCLES) and f"({MIN_CYCLES} cycles;" in reason, reason
