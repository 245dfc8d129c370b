"""``Arrivals``: a reader thread's ``notify`` resolves the futures that event loops expected before it, only those,
and skips loops that have closed."""

import asyncio
import threading

from hydrosoft.drivers.arrivals import Arrivals

TEST_TIMEOUT_S = 5.0


def test_a_notify_from_a_thread_resolves_the_futures_expected_before_it():
    arrivals = Arrivals()

    async def scenario():
        first, second = arrivals.expect(), arrivals.expect()
        threading.Thread(target=arrivals.notify).start()
        await asyncio.wait_for(asyncio.gather(first, second), TEST_TIMEOUT_S)
        later = arrivals.expect()  # after the notify: waits for the next one
        await asyncio.sleep(0.01)
        resolved_early = later.done()
        arrivals.notify()
        await asyncio.wait_for(later, TEST_TIMEOUT_S)
        return resolved_early

    assert asyncio.run(scenario()) is False


def test_a_discarded_future_is_not_resolved_and_a_closed_loop_is_skipped():
    arrivals = Arrivals()

    async def expect_and_discard():
        future = arrivals.expect()
        arrivals.discard(future)
        arrivals.notify()
        await asyncio.sleep(0.01)
        return future.done()

    assert asyncio.run(expect_and_discard()) is False

    async def expect_only():
        return arrivals.expect()

    asyncio.run(expect_only())  # its loop closes with the future still expected
    arrivals.notify()  # does not raise
