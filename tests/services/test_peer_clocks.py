"""Another host's clock: the one-way offset estimate (pure), and the bus moving a remote sender's stamps onto the
receiver's clock, so that a sender clock offset by +-1 h (the bus's ``clock_ns`` test hook) makes nothing stale or
fresh: input ages, request deadlines and the arm commander's goal, deadline and plan-age rules all hold."""

from __future__ import annotations

import asyncio
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

from hydrosoft.services.bus import sockets as b
from hydrosoft.services.bus import messages as m
from hydrosoft.services.arm_commander import ServoLogic
from hydrosoft.services.bus.config import LimitsConfig
from hydrosoft.services.arm.safety import watchdog
from hydrosoft.services.bus.peer_clocks import MAX_PEERS, WINDOW_NS, PeerClock, PeerClocks

S = 1_000_000_000
MS = 1_000_000
HOUR = 3600 * S
TEST_TIMEOUT_S = 20.0
CONNECT_TIMEOUT_S = 5.0
POSE = np.array([0.0, 0.0, 0.1, 1.0, 0.0, 0.0, 0.0])


# --- the offset estimate, without sockets ------------------------------------------------------------------------


@pytest.mark.parametrize("sender_offset_ns", [HOUR, -HOUR, 0])
def test_a_queued_message_keeps_its_age_whatever_the_senders_clock(sender_offset_ns):
    clock = PeerClock()
    now = 10 * HOUR
    for i in range(20):  # 1 ms transit, every 10 ms
        sent = now + i * 10 * MS
        offset = clock.observe(sent + sender_offset_ns, sent + MS)
    queued_sent = now + 200 * MS
    offset = clock.observe(queued_sent + sender_offset_ns, queued_sent + 300 * MS)  # waited 300 ms in a queue
    received = queued_sent + 300 * MS
    age_ns = received - (queued_sent + sender_offset_ns + offset)
    assert 299 * MS <= age_ns <= 300 * MS  # the true age, less the fastest transit (1 ms)


def test_the_window_follows_a_clock_that_jumped_back_after_it_and_a_faster_link_at_once():
    clock = PeerClock()
    assert clock.observe(0, 5 * MS) == 5 * MS
    assert clock.observe(S, S + MS) == MS  # a faster transit lowers the estimate at once
    jumped = -HOUR  # the sender's host rebooted: its stamps now lie an hour lower
    assert clock.observe(2 * S + jumped, 2 * S + MS) == MS  # old until the window has passed: its messages look old
    late = 2 * S + WINDOW_NS + S
    assert clock.observe(late + jumped, late + MS) == MS - jumped


def test_peer_clocks_keep_one_offset_per_sender_and_a_bounded_number_of_senders():
    clocks = PeerClocks()
    assert clocks.offset_ns("planner", 0, HOUR) == HOUR
    assert clocks.offset_ns("tag_tracker", HOUR, 0) == -HOUR
    assert clocks.offset_ns("planner", S, HOUR + S + MS) == HOUR
    for i in range(MAX_PEERS + 10):
        clocks.offset_ns(f"peer-{i}", 0, 0)
    assert len(clocks._peers) == MAX_PEERS


# --- over the bus -------------------------------------------------------------------------------------------------


def run(coroutine):
    return asyncio.run(asyncio.wait_for(coroutine, TEST_TIMEOUT_S))


@pytest.fixture
def ipc_dir():
    with tempfile.TemporaryDirectory(prefix="hs-clk-") as path:
        yield Path(path)


class OffsetClock:
    """``time.monotonic_ns`` plus ``offset_ns``, which a test may change (another host's clock)."""

    def __init__(self, offset_ns: int) -> None:
        self.offset_ns = offset_ns

    def __call__(self) -> int:
        return time.monotonic_ns() + self.offset_ns


async def connected(publisher: b.Publisher, subscriber: b.LatestSubscriber) -> None:
    deadline_s = time.monotonic() + CONNECT_TIMEOUT_S
    while time.monotonic() < deadline_s:
        await publisher.send(m.Heartbeat(period_s=1.0), "heartbeat/probe")
        if "heartbeat/probe" in await subscriber.wait(0.02):
            return
    raise AssertionError("the subscriber did not connect")


# the receiver's clock runs 2 h ahead of this machine's, the sender's 1 h or 3 h: -1 h or +1 h from the receiver's
RECEIVER_OFFSET_NS = 2 * HOUR


@pytest.mark.parametrize("sender_offset_ns", [RECEIVER_OFFSET_NS - HOUR, RECEIVER_OFFSET_NS + HOUR])
def test_ages_of_a_remote_sender_are_its_messages_true_ages_whatever_its_clock(ipc_dir, sender_offset_ns):
    sender_clock = OffsetClock(sender_offset_ns)

    async def scenario():
        with b.Bus(clock_ns=sender_clock) as sender, \
                b.Bus(local_sources=frozenset({"commander"}), clock_ns=OffsetClock(RECEIVER_OFFSET_NS)) as receiver, \
                b.Bus(clock_ns=OffsetClock(RECEIVER_OFFSET_NS)) as one_host:
            publisher = b.Publisher(sender, f"ipc://{ipc_dir}/planner", source="planner")
            subscriber = b.LatestSubscriber(receiver, publisher.endpoint)
            same_clock_assumed = b.LatestSubscriber(one_host, publisher.endpoint)
            await connected(publisher, subscriber)
            for _ in range(5):
                await publisher.send(m.Heartbeat(period_s=0.1), "heartbeat/planner")
                await asyncio.sleep(0.01)
            await asyncio.sleep(0.05)
            fresh = subscriber.latest("heartbeat/planner", 0.2, m.Heartbeat)
            assert 0.04 <= fresh.age_s < 0.2 and not subscriber.errors.counts
            sender_clock.offset_ns -= 300 * MS  # a message that waited 300 ms before it left
            await publisher.send(m.Heartbeat(period_s=0.1), "heartbeat/late")
            sender_clock.offset_ns += 300 * MS
            await asyncio.sleep(0.05)
            with pytest.raises(b.Stale, match="old"):
                subscriber.latest("heartbeat/late", 0.2)
            assert 0.3 <= subscriber.latest("heartbeat/late", 1.0).age_s < 0.4
            # a bus that takes every sender for its own clock judges the same messages by the hour between them
            same_clock_assumed.drain()
            with pytest.raises(b.Stale):
                same_clock_assumed.latest("heartbeat/planner", 0.2)

    run(scenario())


@pytest.mark.parametrize("sender_offset_ns", [RECEIVER_OFFSET_NS - HOUR, RECEIVER_OFFSET_NS + HOUR])
def test_a_remote_clients_request_deadline_holds_whatever_its_clock(ipc_dir, sender_offset_ns):
    async def handle(request: m.Request) -> m.Reply:
        return m.CommandReply(ok=True)

    async def scenario():
        with b.Bus(clock_ns=OffsetClock(sender_offset_ns)) as client_bus, \
                b.Bus(local_sources=frozenset({"planner"}), clock_ns=OffsetClock(RECEIVER_OFFSET_NS)) as server_bus:
            server = b.RequestServer(server_bus, f"ipc://{ipc_dir}/cmd", handle, source="planner")
            serving = asyncio.create_task(server.serve())
            client = b.RequestClient(client_bus, server.endpoint, source="client", timeout_s=2.0)
            for _ in range(3):
                reply = await client.request(m.Stop())
                assert reply.ok, reply.error
            assert not server.errors.counts
            serving.cancel()

    run(scenario())


LIMITS = LimitsConfig(workspace_min=(-0.15, -0.15, 0.0), workspace_max=(0.15, 0.15, 0.2), max_target_lead_s=0.5,
                      max_plan_age_s=0.6, heartbeat_timeout_s=0.3)


@pytest.mark.parametrize("sender_offset_ns", [RECEIVER_OFFSET_NS - HOUR, RECEIVER_OFFSET_NS + HOUR])
def test_the_commanders_goal_deadline_and_plan_age_rules_hold_for_a_planner_an_hour_off(ipc_dir, sender_offset_ns):
    """A goal the planner started before the commander's start is not acted on, one started after it is; a
    target's deadline and its plan's age count on the commander's clock: a plan 1 s old stops the arm, a fresh
    one does not. With the planner's clock an hour ahead (or behind), none of that changes."""
    planner_clock, commander_clock = OffsetClock(sender_offset_ns), OffsetClock(RECEIVER_OFFSET_NS)

    async def scenario():
        with b.Bus(clock_ns=planner_clock) as planner, \
                b.Bus(local_sources=frozenset({"arm_commander-a"}), clock_ns=commander_clock) as commander:
            targets = b.Publisher(planner, f"ipc://{ipc_dir}/planner", source="planner")
            inputs = b.LatestSubscriber(commander, targets.endpoint)
            await connected(targets, inputs)
            before_start = planner_clock()
            await asyncio.sleep(0.05)
            logic = ServoLogic(LIMITS, "a", started_ns=commander_clock())
            await asyncio.sleep(0.05)

            async def offer(goal_ns: int, plan_done_ns: int) -> tuple[str, str] | None:
                now = planner_clock()
                await targets.send(m.ArmTarget(arm="a", tcp_pose=POSE, deadline_ns=now + S // 2, plan_seq=1,
                                               goal_started_ns=goal_ns, plan_done_ns=plan_done_ns), "arm_target/a")
                while "arm_target/a" not in await inputs.wait(1.0):  # the test's timeout bounds it
                    pass
                received = inputs.latest("arm_target/a", 1.0, m.ArmTarget).value
                return logic.offer(received, commander_clock())

            assert (await offer(before_start, planner_clock()))[0] == "old_goal"
            assert logic.target is None
            goal_ns = planner_clock()
            assert await offer(goal_ns, planner_clock()) is None
            assert logic.target is not None
            deadline_lead_ns = logic.deadline_ns - commander_clock()
            assert 0.3 * S < deadline_lead_ns <= 0.5 * S  # its deadline, on the commander's clock
            assert watchdog(commander_clock(), logic.deadline_ns, commander_clock(), commander_clock(), 0.0, LIMITS,
                            logic.target.plan_done_ns) is None  # a fresh plan and deadline: no stop
            assert await offer(goal_ns, planner_clock() - S) is None  # the same goal, its plan done 1 s ago
            reason = watchdog(commander_clock(), logic.deadline_ns, commander_clock(), commander_clock(), 0.0, LIMITS,
                              logic.target.plan_done_ns)
            assert reason is not None and "no plan completed for 1.0" in reason, reason

    run(scenario())
