"""Linux timer slack for the native threads a ``ur_rtde`` client starts.

ur_rtde 1.6.5's receive threads poll their socket: with no data waiting they sleep 100 us and look again, about
6,700 wake-ups a second each on Linux's default 50 us slack (8.2-8.6 % of a core per client against the simulated
controller). A thread's timer slack (``prctl(PR_SET_TIMERSLACK)``) lets the kernel end such a sleep up to that much
later, folded into other wake-ups; a thread inherits its creator's slack. ``started_with_slack`` builds a client on
the calling thread with its slack raised, so that only the threads the client starts keep it, and restores it.
With 1 ms the receive client took 1.6-2.0 % of a core, with 2 ms 0.6-0.7 % (3 runs each, alternated, 2026-11-28).

The cost: a package is seen up to the slack later. Threads at a real-time priority have no slack (Linux ignores it
for them), and on a system without ``prctl`` (not Linux) the client is built as it is. Measured in the stack:
docs/benchmarks.md, "The services' CPU beside the paper planner".
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import sys
from typing import Callable, TypeVar

log = logging.getLogger(__name__)

T = TypeVar("T")

PR_SET_TIMERSLACK = 29
PR_GET_TIMERSLACK = 30


def _prctl() -> Callable[..., int] | None:
    """libc's ``prctl`` on Linux, else None."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None


_PRCTL = _prctl()


def thread_slack_ns() -> int | None:
    """The calling thread's timer slack (ns), or None where it cannot be read."""
    if _PRCTL is None:
        return None
    slack = _PRCTL(PR_GET_TIMERSLACK, 0, 0, 0, 0)
    return None if slack < 0 else int(slack)


def _set_thread_slack_ns(slack_ns: int) -> bool:
    """Set the calling thread's timer slack (ns, > 0); whether it was set."""
    return _PRCTL is not None and _PRCTL(PR_SET_TIMERSLACK, ctypes.c_ulong(slack_ns), 0, 0, 0) == 0


def started_with_slack(slack_s: float, start: Callable[[], T]) -> T:
    """``start()`` (which starts native threads, e.g. a ur_rtde client's constructor) with the calling thread's
    timer slack at ``slack_s`` s (> 0), so that the threads it starts inherit that slack; the calling thread's own
    slack is restored afterwards, whether ``start`` returned or raised. Where the slack cannot be read or set,
    ``start()`` runs as it is (logged at debug level)."""
    if not slack_s > 0:
        raise ValueError(f"timer slack must be > 0 s, got {slack_s!r}")
    before_ns = thread_slack_ns()
    if before_ns is None or not _set_thread_slack_ns(max(1, round(slack_s * 1e9))):
        log.debug("timer slack not available: %s starts with the default slack", start)
        return start()
    try:
        return start()
    finally:
        _set_thread_slack_ns(before_ns)
