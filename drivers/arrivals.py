"""``Arrivals``: asyncio waiters woken by a driver's reader thread whenever it keeps a new sample.

A driver whose samples come in on a thread of its own (pyserial blocks) hands them to asyncio code without
polling: the waiter registers a future with ``expect`` before it looks at the newest sample, the reader thread
calls ``notify`` after storing each one, and every registered future is resolved on its own event loop
(``call_soon_threadsafe``). A sample stored between the look and the wait resolves the future already registered,
so none is missed.
"""

from __future__ import annotations

import asyncio
import threading


class Arrivals:
    """Futures resolved at the next ``notify``; ``expect`` and ``discard`` from event loops, ``notify`` from any
    thread."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._waiting: list[tuple[asyncio.AbstractEventLoop, asyncio.Future[None]]] = []

    def expect(self) -> asyncio.Future[None]:
        """A future of the running event loop, resolved (to None) at the next ``notify``; ``discard`` it when done."""
        loop = asyncio.get_running_loop()
        future: asyncio.Future[None] = loop.create_future()
        with self._lock:
            self._waiting.append((loop, future))
        return future

    def discard(self, future: asyncio.Future[None]) -> None:
        """Forget ``future`` (resolved, timed out or cancelled); unknown futures are ignored."""
        with self._lock:
            self._waiting = [entry for entry in self._waiting if entry[1] is not future]

    def notify(self) -> None:
        """Resolve every future expected so far, each on its own loop; a loop that has closed is skipped."""
        with self._lock:
            waiting, self._waiting = self._waiting, []
        for loop, future in waiting:
            try:
                loop.call_soon_threadsafe(_resolve, future)
            except RuntimeError:  # the loop closed: nobody waits on it any more
                continue


def _resolve(future: asyncio.Future[None]) -> None:
    if not future.done():
        future.set_result(None)
