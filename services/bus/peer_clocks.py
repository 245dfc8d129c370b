"""Other hosts' monotonic clocks, measured one way: each message's stamps moved onto the receiver's clock.

Two hosts' ``time.monotonic_ns`` clocks share no origin. For every message from a peer on another host the receiver
knows two numbers: the sender's stamp ``stamp_ns`` (its clock) and its own receive time ``received_ns``. Their
difference is the clock offset plus the message's transit time, so its smallest value over the last
``WINDOW_NS`` is the offset plus the fastest transit seen (``offset_ns``). A stamp of that sender moved onto the
receiver's clock is ``stamp + offset_ns``: a message that waited in a queue (the receiver's loop was busy, a link
stalled) keeps its age, and any offset between the clocks, hours included, cancels out. Ages come out short by the
fastest transit in the window (tens of microseconds on loopback, well under a millisecond on a wired LAN), far
below any age limit of the stack. The window (not all history) follows the clocks' drift (tens of ppm: under a
millisecond over the window). A sender whose clock jumps back (its host rebooted) looks old, so its messages are
stale, until the window has passed: a wait, never a fresh look at an old message.
"""

from __future__ import annotations

from collections import OrderedDict, deque

#: How far back the smallest receive-minus-stamp difference is taken from, ns.
WINDOW_NS = 10_000_000_000
#: Senders whose offsets are kept; the least recently heard is forgotten beyond it (memory stays bounded).
MAX_PEERS = 256


class PeerClock:
    """One sender's clock offset: the sliding-window minimum of ``received_ns - stamp_ns`` (ns).

    A deque of ``(received_ns, difference)`` whose differences grow from front to back holds every sample that
    can still be the minimum, so each ``observe`` costs O(1) amortised.
    """

    def __init__(self, window_ns: int = WINDOW_NS) -> None:
        self.window_ns = window_ns
        self._samples: deque[tuple[int, int]] = deque()

    def observe(self, stamp_ns: int, received_ns: int) -> int:
        """Take one message stamped ``stamp_ns`` (sender's clock) and received at ``received_ns`` (ours); return
        the offset (ns) to add to the sender's stamps to put them on our clock."""
        difference = received_ns - stamp_ns
        while self._samples and self._samples[-1][1] >= difference:
            self._samples.pop()
        self._samples.append((received_ns, difference))
        while self._samples[0][0] < received_ns - self.window_ns:
            self._samples.popleft()
        return self._samples[0][1]


class PeerClocks:
    """The clock offsets of the senders on other hosts, by ``source`` name (the ``MAX_PEERS`` most recent)."""

    def __init__(self, window_ns: int = WINDOW_NS) -> None:
        self.window_ns = window_ns
        self._peers: OrderedDict[str, PeerClock] = OrderedDict()

    def offset_ns(self, source: str, stamp_ns: int, received_ns: int) -> int:
        """The offset of ``source``'s clock (ns, to add to its stamps), updated with one message of it stamped
        ``stamp_ns`` and received at ``received_ns``."""
        clock = self._peers.pop(source, None)
        if clock is None:
            clock = PeerClock(self.window_ns)
            if len(self._peers) >= MAX_PEERS:
                self._peers.popitem(last=False)
        self._peers[source] = clock
        return clock.observe(stamp_ns, received_ns)
