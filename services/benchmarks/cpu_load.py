"""Other work on the host, made on purpose: processes that each keep one core busy a set fraction of the time.

The shared machine this stack is measured on runs slower in some hours than in others (its neighbours' work), so a
latency figure depends on the hour. ``bench soak --background-load CORES`` starts ``load_processes(CORES)`` of these
beside the stack, so the stack's margin can be measured against a known load in any hour: a result that holds its
targets with 0.3 cores taken away holds them in an hour that is that much slower.

Each process alternates, every ``PERIOD_S``, between spinning (``fraction`` of the period) and sleeping (the rest),
at the default priority, as a neighbour's work would. It takes at most ``fraction`` of one core; when the machine is
full it gets less, like any other process.

Run one: ``python -m hydrosoft.services.benchmarks.cpu_load FRACTION`` (0 < FRACTION <= 1); it runs until stopped.
"""

from __future__ import annotations

import math
import sys
import time

PERIOD_S = 0.01  # one spin-and-sleep cycle, s: shorter than a solve, so the load is spread over it


def load_processes(cores: float) -> list[float]:
    """The fraction of one core each process takes so that together they take ``cores`` (>= 0): as few processes
    as can, sharing it equally. ``[]`` for 0."""
    if not math.isfinite(cores) or cores < 0:
        raise ValueError(f"a background load is a number of cores >= 0, not {cores}")
    count = math.ceil(cores)
    return [cores / count] * count if count else []


def spin_and_sleep(fraction: float, cycles: int | None = None, period_s: float = PERIOD_S) -> None:
    """Spin for ``fraction`` of each ``period_s``, sleep for the rest; ``cycles`` times, or forever (None)."""
    if not 0.0 < fraction <= 1.0:
        raise ValueError(f"a process takes a fraction of one core in (0, 1], not {fraction}")
    next_s = time.monotonic()
    done = 0
    while cycles is None or done < cycles:
        busy_until_s = next_s + fraction * period_s
        while time.monotonic() < busy_until_s:
            pass
        next_s += period_s
        now_s = time.monotonic()
        if next_s > now_s:
            time.sleep(next_s - now_s)
        else:  # it got less than its share of the core: start the next cycle now, owe nothing
            next_s = now_s
        done += 1


def main(argv: list[str] | None = None) -> int:
    """Spin one process at the fraction in ``argv`` until stopped (SIGINT or SIGTERM)."""
    args = sys.argv[1:] if argv is None else argv
    try:
        fraction = float(args[0])
        spin_and_sleep(fraction)
    except (IndexError, ValueError) as error:
        print(f"usage: python -m hydrosoft.services.benchmarks.cpu_load FRACTION (0 < FRACTION <= 1): {error}",
              file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
