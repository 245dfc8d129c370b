"""A ur_rtde client built with ``started_with_slack`` gives its threads the slack; the caller's own is restored."""

import sys
import threading

import pytest

from hydrosoft.drivers.ur.timer_slack import started_with_slack, thread_slack_ns

linux_only = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="timer slack is a Linux prctl")


def slack_of_a_thread_started_here() -> int | None:
    """The timer slack (ns) of a thread started by the calling thread, as a native client's would be."""
    seen: list[int | None] = []
    thread = threading.Thread(target=lambda: seen.append(thread_slack_ns()))
    thread.start()
    thread.join()
    return seen[0]


@linux_only
def test_threads_started_inside_get_the_slack_and_the_callers_slack_is_restored():
    before_ns = thread_slack_ns()
    assert before_ns is not None and before_ns > 0
    assert slack_of_a_thread_started_here() == before_ns
    assert started_with_slack(0.001, slack_of_a_thread_started_here) == 1_000_000
    assert thread_slack_ns() == before_ns
    assert slack_of_a_thread_started_here() == before_ns


@linux_only
def test_the_callers_slack_is_restored_when_the_start_raises():
    before_ns = thread_slack_ns()

    def failing_start() -> None:
        assert thread_slack_ns() == 2_000_000
        raise RuntimeError("could not connect")

    with pytest.raises(RuntimeError, match="could not connect"):
        started_with_slack(0.002, failing_start)
    assert thread_slack_ns() == before_ns


@pytest.mark.parametrize("slack_s", [0.0, -0.001, float("nan")])
def test_a_slack_that_is_not_positive_is_refused(slack_s):
    with pytest.raises(ValueError, match="timer slack"):
        started_with_slack(slack_s, lambda: None)
