"""The bus on real sockets (ipc:// and tcp://127.0.0.1 only): endpoint policy, CURVE, latest-value subscribers,
malformed traffic and the request/reply pair. Every test runs under a deadline."""

import asyncio
import json
import logging
import math
import shutil
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import msgspec
import numpy as np
import pytest
import zmq
import zmq.asyncio
import zmq.auth

from hydrosoft.services.bus import sockets as b
from hydrosoft.services.bus import messages as m

TEST_TIMEOUT_S = 20.0
#: How long a test waits for a subscription to reach its publisher (slow joiner), s.
CONNECT_TIMEOUT_S = 5.0
#: How long a test listens to show that nothing arrives, s.
SILENCE_S = 0.5

WRENCH = m.Wrench(sensor="ft", wrench=np.array([1.0, 2.0, 3.0, 0.1, 0.2, 0.3]), tared=True)


def run(coroutine, timeout_s: float = TEST_TIMEOUT_S):
    """Run ``coroutine`` in a fresh loop; a hang fails the test after ``timeout_s``."""
    return asyncio.run(asyncio.wait_for(coroutine, timeout_s))


@pytest.fixture
def ipc_dir():
    with tempfile.TemporaryDirectory(prefix="hs-bus-") as path:  # short: ipc paths are limited to ~100 bytes
        yield Path(path)


async def connected(publisher: b.Publisher, subscriber: b.LatestSubscriber) -> bool:
    """Send heartbeats until ``subscriber`` (subscribed to ``heartbeat``) receives one; False on timeout."""
    deadline_s = time.monotonic() + CONNECT_TIMEOUT_S
    while time.monotonic() < deadline_s:
        await publisher.send(m.Heartbeat(period_s=1.0), "heartbeat/probe")
        if "heartbeat/probe" in await subscriber.wait(0.02):
            return True
    return False


# --- endpoint policy ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("endpoint", ["ipc:///tmp/x.ipc", "inproc://bus", "tcp://127.0.0.1:5555", "tcp://127.4.5.6:*"])
def test_local_endpoints_need_no_keys(endpoint):
    assert b.is_local_endpoint(endpoint)
    b.check_endpoint(endpoint, None)


@pytest.mark.parametrize("endpoint", ["tcp://0.0.0.0:5555", "tcp://*:5555", "tcp://192.168.1.20:5555",
                                      "tcp://localhost:5555", "tcp://eth0:5555", "tcp://[::]:5555"])
def test_other_endpoints_need_curve_keys(endpoint):
    assert not b.is_local_endpoint(endpoint)
    with pytest.raises(b.BusConfigError, match="CURVE keys"):
        b.check_endpoint(endpoint, None)
    b.check_endpoint(endpoint, b.CurveServer(Path("server.key_secret"), Path("clients")))


@pytest.mark.parametrize("endpoint, reason", [("127.0.0.1:5555", "no transport"), ("pgm://eth0;239.1.1.1:5555",
                                              "not supported"), ("tcp://127.0.0.1", "no port")])
def test_malformed_endpoints_are_refused(endpoint, reason):
    with pytest.raises(b.BusConfigError, match=reason):
        b.is_local_endpoint(endpoint)


def test_binding_all_interfaces_without_keys_is_refused_before_any_socket_exists():
    with b.Bus() as bus:
        with pytest.raises(b.BusConfigError, match="expose the bus beyond this host"):
            b.Publisher(bus, "tcp://0.0.0.0:*", source="test")
        assert bus._sockets == []


@pytest.fixture
def keys(ipc_dir):
    """Certificates: a server, an authorized client, and an intruder whose key the server does not know."""
    paths = {}
    for name in ("server", "client", "intruder"):
        folder = ipc_dir / name
        folder.mkdir()
        public, secret = zmq.auth.create_certificates(folder, name)
        Path(secret).chmod(0o600)
        paths[name] = (Path(public), Path(secret))
    return paths


def test_curve_admits_the_authorized_client_only(keys):
    server = b.CurveServer(keys["server"][1], keys["client"][0].parent)

    async def scenario():
        with b.Bus() as bus:
            publisher = b.Publisher(bus, "tcp://127.0.0.1:*", source="test", curve=server)
            client = b.LatestSubscriber(bus, publisher.endpoint, curve=b.CurveClient(keys["client"][1],
                                                                                     keys["server"][0]))
            intruder = b.LatestSubscriber(bus, publisher.endpoint, curve=b.CurveClient(keys["intruder"][1],
                                                                                       keys["server"][0]))
            wrong_server_key = b.LatestSubscriber(bus, publisher.endpoint, curve=b.CurveClient(
                keys["client"][1], keys["intruder"][0]))
            plain = b.LatestSubscriber(bus, publisher.endpoint)
            assert await connected(publisher, client)
            for _ in range(round(SILENCE_S / 0.05)):
                await publisher.send(WRENCH)
                await asyncio.sleep(0.05)
            assert client.latest("wrench", 1.0, m.Wrench).value.sensor == "ft"
            for outsider in (intruder, wrong_server_key, plain):
                assert not outsider.drain() and not outsider.received

    run(scenario())


def test_curve_keys_put_curve_on_tcp_beyond_loopback_and_on_loopback_only_when_forced(keys):
    secret, authorized = keys["client"][1], keys["client"][0].parent
    remote = "tcp://10.1.2.3:5600"
    keys_of = b.CurveKeys(secret, authorized, server_key_files={remote: keys["server"][0]})
    assert keys_of.for_endpoint("ipc:///tmp/x.data", bind=True) is None
    assert keys_of.for_endpoint("tcp://127.0.0.21:5600", bind=False) is None
    assert keys_of.for_endpoint(remote, bind=True) == b.CurveServer(secret, authorized)
    assert keys_of.for_endpoint(remote, bind=False) == b.CurveClient(secret, keys["server"][0])
    forced = b.CurveKeys(secret, authorized, loopback=True)
    assert forced.for_endpoint("ipc:///tmp/x.data", bind=False) is None
    assert forced.for_endpoint("tcp://127.0.0.21:5600", bind=False) == b.CurveClient(secret, secret)
    assert forced.for_endpoint("tcp://127.0.0.21:5600", bind=True) == b.CurveServer(secret, authorized)


def test_only_inter_host_tcp_links_get_keepalive_and_a_retransmission_limit(keys, ipc_dir):
    """A CURVE tcp endpoint (another host's; here loopback with CURVE forced) gets INTER_HOST_TCP_OPTIONS, on the
    binding and the connecting side; an ipc endpoint and a plain loopback tcp one keep libzmq's defaults."""
    secret, authorized = keys["server"][1], keys["server"][0].parent

    def tcp_options(sock: zmq.Socket) -> tuple[tuple[int, int], ...]:
        return tuple((option, sock.getsockopt(option)) for option, _ in b.INTER_HOST_TCP_OPTIONS)

    with zmq.Context() as context, context.socket(zmq.PUB) as fresh:
        defaults = tcp_options(fresh)
    assert defaults != b.INTER_HOST_TCP_OPTIONS
    with b.Bus(curve=b.CurveKeys(secret, authorized, loopback=True)) as bus:
        server = bus.socket(zmq.PUB, "tcp://127.0.0.1:*", bind=True)
        client = bus.socket(zmq.SUB, server.getsockopt_string(zmq.LAST_ENDPOINT), bind=False)
        assert tcp_options(server) == tcp_options(client) == b.INTER_HOST_TCP_OPTIONS
        assert tcp_options(bus.socket(zmq.PUB, f"ipc://{ipc_dir}/local.data", bind=True)) == defaults
    with b.Bus() as bus:  # no CURVE keys: loopback tcp stays on this host
        assert tcp_options(bus.socket(zmq.PUB, "tcp://127.0.0.1:*", bind=True)) == defaults


#: From a dead link (every packet lost) to both ends closing it, s: keepalive's 1 s idle and 3 probes 1 s apart
#: (the subscriber), the 4 s retransmission limit (the publisher), and scheduling slack on a busy machine.
DEAD_LINK_BOUND_S = 1.0 + 3 * 1.0 + 2.0


def test_a_dead_inter_host_link_is_closed_within_seconds_and_counted_and_a_plain_one_is_not():
    """In a private network namespace (``dead_link.py``), the loopback interface going down cuts an inter-host link
    and a plain one: both ends of the inter-host link close it (the subscriber counts ``link_dropped``) within
    ``DEAD_LINK_BOUND_S``; the plain link, on the kernel's defaults, is still open when the watch ends."""
    if shutil.which("unshare") is None or shutil.which("ip") is None or subprocess.run(
            ["unshare", "-n", "true"], capture_output=True).returncode != 0:
        pytest.skip("needs a private network namespace: unshare -n (root or user namespaces) and ip")
    done = subprocess.run(["unshare", "-n", sys.executable, str(Path(__file__).parents[1] / "dead_link.py")],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    closed = json.loads(done.stdout)
    print(f"a dead link closed after (s): {closed}")
    assert all(seconds is not None and seconds < DEAD_LINK_BOUND_S for seconds in closed["inter_host"].values()), closed
    assert closed["plain"] == {"subscriber": None, "publisher": None}, closed


def test_a_secret_key_file_others_may_read_is_refused_naming_the_file(keys):
    secret = keys["server"][1]
    secret.chmod(0o644)
    with b.Bus() as bus:
        with pytest.raises(b.BusConfigError, match=f"{secret}.*readable by its owner only"):
            b.Publisher(bus, "tcp://127.0.0.1:*", source="t", curve=b.CurveServer(secret, keys["client"][0].parent))
        assert bus._sockets == []
    secret.chmod(0o600)
    b.check_secret_key_file(secret)


def test_forced_curve_on_loopback_admits_authorised_keys_and_counts_each_refused_peer(keys, ipc_dir):
    """The bus's own CurveKeys decide per endpoint: the tcp publisher is a CURVE server, the ipc one plain, and
    one subscriber reads both; a peer whose key is not authorised receives nothing and is counted."""
    authorized = ipc_dir / "authorized"
    authorized.mkdir()
    for name in ("server", "client"):
        (authorized / keys[name][0].name).write_bytes(keys[name][0].read_bytes())

    async def scenario():
        server_keys = b.CurveKeys(keys["server"][1], authorized, loopback=True)
        with b.Bus(curve=server_keys) as server, b.Bus() as peers:
            secure = b.Publisher(server, "tcp://127.0.0.1:*", source="secure")
            plain = b.Publisher(server, f"ipc://{ipc_dir}/plain", source="plain")
            endpoint = secure.endpoint

            def client_keys(name: str) -> b.CurveKeys:
                return b.CurveKeys(keys[name][1], authorized, {endpoint: keys["server"][0]}, loopback=True)

            with b.Bus(curve=client_keys("client")) as client_bus, b.Bus(curve=client_keys("intruder")) as intruder_bus:
                client = b.LatestSubscriber(client_bus, [endpoint, plain.endpoint])
                intruder = b.LatestSubscriber(intruder_bus, endpoint)
                no_keys = b.LatestSubscriber(peers, endpoint)
                assert await connected(secure, client)
                await plain.send(WRENCH)
                for _ in range(round(SILENCE_S / 0.05)):
                    await secure.send(WRENCH, "wrench/secure")
                    await asyncio.sleep(0.05)
                assert client.latest("wrench/secure", 1.0, m.Wrench).value.sensor == "ft"
                assert client.latest("wrench", 1.0, m.Wrench).value.sensor == "ft"
                assert not intruder.drain() and not intruder.received
                assert not no_keys.drain() and not no_keys.received
                assert server.curve_refused >= 1  # the intruder (libzmq retries, each try is counted)
                assert client_bus.curve_refused == 0

    run(scenario())


def test_curve_configuration_errors_say_what_is_missing(keys, ipc_dir):
    empty = ipc_dir / "empty"
    empty.mkdir()
    with b.Bus() as bus:
        with pytest.raises(b.BusConfigError, match="no secret key"):
            b.Publisher(bus, "tcp://127.0.0.1:*", source="t", curve=b.CurveServer(keys["server"][0], empty))
        with pytest.raises(b.BusConfigError, match="holds no public .key"):
            b.Publisher(bus, "tcp://127.0.0.1:*", source="t", curve=b.CurveServer(keys["server"][1], empty))
        with pytest.raises(b.BusConfigError, match="cannot read CURVE certificate"):
            b.LatestSubscriber(bus, "tcp://127.0.0.1:5", curve=b.CurveClient(ipc_dir / "none", keys["server"][0]))


def test_a_second_bind_to_the_same_endpoint_is_a_config_error():
    with b.Bus() as bus:
        first = b.Publisher(bus, "tcp://127.0.0.1:*", source="t")
        with pytest.raises(b.BusConfigError, match="cannot bind"):
            b.Publisher(bus, first.endpoint, source="t")


# --- streams -----------------------------------------------------------------------------------------------------


def test_a_publisher_whose_subscriber_reads_nothing_drops_at_its_hwm_and_never_suspends(ipc_dir):
    """The send path (a plain socket, NOBLOCK): every send completes at once, also with the subscriber's and the
    publisher's queues full, and only the subscriber's queue's worth arrives."""
    async def scenario():
        with b.Bus() as bus:
            publisher = b.Publisher(bus, f"ipc://{ipc_dir}/pub", source="ft_reader", sndhwm=2)
            subscriber = b.LatestSubscriber(bus, publisher.endpoint, ["heartbeat", "wrench"], rcvhwm=2)
            assert await connected(publisher, subscriber)
            received_before = subscriber.received["wrench"]
            for _ in range(2000):
                sending = publisher.send(WRENCH)
                with pytest.raises(StopIteration):  # done without yielding to the event loop once
                    sending.send(None)
            assert publisher.sent["wrench"] == 2000
            await asyncio.sleep(0.1)
            subscriber.drain()
            assert subscriber.received["wrench"] - received_before < 1000  # the rest was dropped, not queued
            assert not subscriber.errors.counts

    asyncio.run(scenario())


def test_publisher_stamps_each_topic_and_the_subscriber_hands_out_the_newest(ipc_dir):
    async def scenario():
        with b.Bus() as bus:
            publisher = b.Publisher(bus, f"ipc://{ipc_dir}/pub", source="ft_reader")
            subscriber = b.LatestSubscriber(bus, publisher.endpoint, ["heartbeat", "wrench"])
            assert await connected(publisher, subscriber)
            before_ns = time.monotonic_ns()
            sent = [await publisher.send(WRENCH, "wrench/left") for _ in range(3)]
            sent.append(await publisher.send(WRENCH, "wrench/right"))
            assert [msg.seq for msg in sent] == [1, 2, 3, 1]
            assert all(msg.source == "ft_reader" and msg.stamp_ns >= before_ns for msg in sent)
            while subscriber.received["wrench/left"] < 3 or subscriber.received["wrench/right"] < 1:
                assert await subscriber.wait(1.0)
            left = subscriber.latest("wrench/left", 1.0, m.Wrench)
            assert left.value.seq == 3 and left.stamp_ns == sent[2].stamp_ns
            assert 0 <= left.age_s < 1.0
            np.testing.assert_array_equal(left.value.wrench, WRENCH.wrench)
            assert subscriber.latest("wrench/right", 1.0).value.seq == 1
            with pytest.raises(TypeError, match="not DepthFrame"):
                subscriber.latest("wrench/left", 1.0, m.DepthFrame)
            with pytest.raises(b.Stale, match="nothing received"):
                subscriber.latest("wrench/middle", 1.0)
            await asyncio.sleep(0.05)
            with pytest.raises(b.Stale, match="old, limit 0.010 s"):
                subscriber.latest("wrench/left", 0.01)

    run(scenario())


def test_wait_returns_nothing_after_its_timeout(ipc_dir):
    async def scenario():
        with b.Bus() as bus:
            subscriber = b.LatestSubscriber(bus, f"ipc://{ipc_dir}/nobody")
            start_s = time.monotonic()
            assert await subscriber.wait(0.2) == set()
            assert 0.15 < time.monotonic() - start_s < 2.0

    run(scenario())


def test_a_flooded_subscriber_stays_bounded_and_gets_the_newest_message(ipc_dir):
    flood = 20_000

    async def scenario():
        with b.Bus() as bus:
            # ipc: a Unix socket's buffers are fixed (~200 kB); loopback TCP autotunes its buffers up to megabytes,
            # enough on some hosts to hold the whole flood
            publisher = b.Publisher(bus, f"ipc://{ipc_dir}/flood", source="test")
            subscriber = b.LatestSubscriber(bus, publisher.endpoint, ["heartbeat", "wrench"])
            assert await connected(publisher, subscriber)
            for _ in range(flood):  # back to back, while the subscriber does not read
                await publisher.send(WRENCH)
            while await subscriber.wait(0.2):  # read the backlog until quiet
                pass
            queued = subscriber.received["wrench"]
            # HWMs plus socket buffers held a few thousand small messages at most; the publisher dropped the rest
            assert 0 < queued < flood / 4
            final = await publisher.send(WRENCH)
            assert "wrench" in await subscriber.wait(2.0)
            newest = subscriber.latest("wrench", 1.0)
            assert newest.value.seq == final.seq == flood + 1
            assert subscriber.received["wrench"] == queued + 1

    run(scenario())


def test_a_background_reader_excludes_a_second_waiter(ipc_dir):
    async def scenario():
        with b.Bus() as bus:
            subscriber = b.LatestSubscriber(bus, f"ipc://{ipc_dir}/nobody")
            reader = asyncio.create_task(subscriber.run())
            await asyncio.sleep(0.01)
            with pytest.raises(RuntimeError, match="already waits"):
                await subscriber.wait(0.1)
            reader.cancel()
            with pytest.raises(asyncio.CancelledError):
                await reader
            assert await subscriber.wait(0.01) == set()  # free again once the reader stopped

    run(scenario())


def test_the_arrival_event_of_a_topic_wakes_on_that_topic_only(ipc_dir):
    async def scenario():
        with b.Bus() as bus:
            publisher = b.Publisher(bus, f"ipc://{ipc_dir}/pub", source="planner")
            subscriber = b.LatestSubscriber(bus, publisher.endpoint, ["heartbeat", "wrench"])
            assert await connected(publisher, subscriber)
            reader = asyncio.create_task(subscriber.run())
            arrived = subscriber.arrival("wrench/left")
            assert arrived is subscriber.arrival("wrench/left")
            arrived.clear()
            await publisher.send(WRENCH, "wrench/right")
            with pytest.raises(TimeoutError):
                async with asyncio.timeout(0.2):
                    await arrived.wait()
            sent = await publisher.send(WRENCH, "wrench/left")
            async with asyncio.timeout(2.0):
                await arrived.wait()
            assert subscriber.latest("wrench/left", 1.0).value.seq == sent.seq
            reader.cancel()

    run(scenario())


def test_malformed_traffic_is_counted_and_valid_messages_still_arrive(ipc_dir):
    endpoint = f"ipc://{ipc_dir}/raw"
    valid = m.encode(msg=m.Wrench(sensor="ft", wrench=np.zeros(6), tared=False, seq=1, stamp_ns=1))
    future = m.encode(m.Wrench(sensor="ft", wrench=np.zeros(6), tared=False, seq=2, stamp_ns=time.monotonic_ns()
                               + 10**12))
    bad = [
        [b"wrench", b"\xc1 garbage", bytes(48)],
        [b"torque", valid[1], bytes(48)],
        [b"wrench", valid[1], bytes(40)],
        [b"wrench", valid[1]],
        future,
    ]

    async def scenario():
        with b.Bus() as bus:
            raw = bus.socket(zmq.PUB, endpoint, bind=True)
            subscriber = b.LatestSubscriber(bus, endpoint)
            deadline_s = time.monotonic() + CONNECT_TIMEOUT_S
            while not subscriber.received and time.monotonic() < deadline_s:  # slow joiner
                await raw.send_multipart(valid)
                await subscriber.wait(0.02)
            assert subscriber.received["wrench"] >= 1
            for frames in bad * 3:
                await raw.send_multipart(frames)
            await raw.send_multipart(m.encode(m.Wrench(sensor="last", wrench=np.zeros(6), tared=False,
                                                       stamp_ns=time.monotonic_ns())))
            while subscriber.latest("wrench", math.inf).value.sensor != "last":
                assert await subscriber.wait(2.0)
            assert subscriber.errors.counts == {"garbage": 3, "unknown_topic": 3, "length": 3, "frame_count": 3,
                                                "future_stamp": 3}
            assert "future" in subscriber.errors.last_error

    run(scenario())


def test_errors_are_logged_once_per_n(caplog):
    counter = b.ErrorCounter(logging.getLogger("test.errors"), log_every=3)
    with caplog.at_level(logging.WARNING, logger="test.errors"):
        for i in range(7):
            counter.count("schema", f"bad {i}")
        counter.count("garbage", "junk")
    assert [r.getMessage().split(":")[-1].strip() for r in caplog.records] == ["bad 0", "bad 3", "bad 6", "junk"]
    assert counter.counts == {"schema": 7, "garbage": 1} and counter.last_error == "garbage: junk"


def test_latest_holder_refuses_stale_values():
    now_ns = [1_000_000_000]
    holder = b.Latest("wrench", max_age_s=0.1, clock_ns=lambda: now_ns[0])
    with pytest.raises(b.Stale, match="nothing received"):
        holder.get()
    holder.put("new", stamp_ns=now_ns[0] - 50_000_000)
    holder.put("older", stamp_ns=now_ns[0] - 80_000_000)  # out of order: ignored
    got = holder.get()
    assert got.value == "new" and got.age_s == pytest.approx(0.05)
    now_ns[0] += 60_000_000
    with pytest.raises(b.Stale, match="0.110 s old, limit 0.100 s"):
        holder.get()
    assert holder.get(max_age_s=0.2).value == "new"
    with pytest.raises(ValueError, match="max_age_s"):
        b.Latest("x", max_age_s=0.0)


# --- requests ----------------------------------------------------------------------------------------------------


async def handler(request: m.Request) -> m.Reply:
    if isinstance(request, m.GetStatus):
        return m.StatusReply(ok=True, running=False)
    if isinstance(request, m.Stop):
        if request.reason == "boom":
            raise RuntimeError("cannot stop")
        if request.reason == "slow":
            await asyncio.sleep(0.5)
        if request.reason == "confused":
            return m.StatusReply(ok=True)
    return m.CommandReply(ok=True)


def test_requests_get_their_replies_and_failures_become_error_replies(ipc_dir):
    endpoint = f"ipc://{ipc_dir}/api"

    async def scenario():
        with b.Bus() as bus:
            server = b.RequestServer(bus, endpoint, handler, source="planner")
            serving = asyncio.create_task(server.serve())
            client = b.RequestClient(bus, endpoint, source="client", timeout_s=2.0)
            reply = await client.request(m.Start())
            assert isinstance(reply, m.CommandReply) and reply.ok and reply.source == "planner"
            assert isinstance(await client.request(m.GetStatus()), m.StatusReply)
            failed = await client.request(m.Stop(reason="boom"))
            assert not failed.ok and "cannot stop" in failed.error
            confused = await client.request(m.Stop(reason="confused"))
            assert not confused.ok and "not CommandReply" in confused.error
            assert server.errors.counts == {"handler": 2}
            with pytest.raises(TimeoutError, match="no reply to Stop"):
                await client.request(m.Stop(reason="slow"), timeout_s=0.1)
            assert (await client.request(m.Start())).ok  # the late reply to Stop was dropped, not taken for this
            serving.cancel()

    run(scenario())


def test_malformed_and_expired_requests_get_error_replies(ipc_dir):
    endpoint = f"ipc://{ipc_dir}/api"
    expired = m.encode(m.Start(deadline_ns=time.monotonic_ns() - 1))

    async def scenario():
        with b.Bus() as bus:
            server = b.RequestServer(bus, endpoint, handler, source="planner")
            serving = asyncio.create_task(server.serve())
            raw = bus.socket(zmq.DEALER, endpoint, bind=False)
            replies = {}
            for request_id, frames in [(b"1", [b"cmd/start", b"\xc1"]), (b"2", m.encode(m.Heartbeat(period_s=1.0))),
                                       (b"3", expired)]:
                await raw.send_multipart([request_id, *frames])
                answer = await raw.recv_multipart()
                replies[answer[0]] = m.decode(answer[1:])[1]
            assert all(isinstance(reply, m.Reply) and not reply.ok for reply in replies.values())
            assert replies[b"1"].error.startswith("garbage:")
            assert "not a request topic" in replies[b"2"].error
            assert "after its deadline" in replies[b"3"].error
            assert server.errors.counts == {"garbage": 1, "unknown_topic": 1, "expired_request": 1}
            serving.cancel()

    run(scenario())


def test_a_request_without_a_server_times_out(ipc_dir):
    async def scenario():
        with b.Bus() as bus:
            client = b.RequestClient(bus, f"ipc://{ipc_dir}/nobody", source="client", timeout_s=0.2)
            start_s = time.monotonic()
            with pytest.raises(TimeoutError, match="within 0.2 s"):
                await client.request(m.GetStatus())
            assert time.monotonic() - start_s < 2.0

    run(scenario())


def test_a_waiting_subscriber_wakes_on_a_message_and_its_bus_takes_the_reader_off_the_loop(ipc_dir):
    """The event loop watches a subscriber's file descriptor from its first ``wait`` on (``Bus.watch``): a message
    sent while it waits wakes it at once, every queued message is read per wake-up (the newest kept), a wait with
    nothing queued times out empty, and closing the bus takes the descriptor off the loop (before its socket closes:
    a closed socket's descriptor number can be reused)."""
    async def scenario():
        bus = b.Bus()
        with bus:
            endpoint = f"ipc://{ipc_dir}/wake"
            publisher = b.Publisher(bus, endpoint, source="sender")
            subscriber = b.LatestSubscriber(bus, endpoint, ["heartbeat/", "wrench"])
            assert await connected(publisher, subscriber)
            loop = asyncio.get_running_loop()
            fd = subscriber._sock.getsockopt(zmq.FD)
            assert await subscriber.wait(0.05) == set()
            sending = loop.call_later(0.05, lambda: asyncio.ensure_future(publisher.send(WRENCH)))
            tic = time.monotonic()
            assert await subscriber.wait(CONNECT_TIMEOUT_S) == {"wrench"}
            woke_s = time.monotonic() - tic
            sending.cancel()
            for _ in range(3):
                await publisher.send(WRENCH)
            await asyncio.sleep(0.05)
            assert await subscriber.wait(CONNECT_TIMEOUT_S) == {"wrench"}  # all three in one wake-up
            assert subscriber.received["wrench"] == 4 and subscriber.latest("wrench", 1.0).value.seq == 4
        assert not loop.remove_reader(fd)  # the bus closed: nothing of it is left on the loop
        return woke_s

    assert run(scenario()) < 1.0  # sent after 0.05 s; the wait's limit was CONNECT_TIMEOUT_S


def test_an_oversized_frame_is_counted_the_link_stays_up_and_older_stamps_are_dropped(ipc_dir):
    async def scenario():
        with b.Bus() as bus:
            endpoint = f"ipc://{ipc_dir}/big"
            raw = bus.socket(zmq.PUB, endpoint, bind=True)
            subscriber = b.LatestSubscriber(bus, endpoint, ["wrench"])
            newest = m.encode(msgspec.structs.replace(WRENCH, seq=2, stamp_ns=time.monotonic_ns()))
            older = m.encode(msgspec.structs.replace(WRENCH, seq=1, stamp_ns=time.monotonic_ns() - 1_000_000))
            while "wrench" not in await subscriber.wait(0.02):  # slow joiner
                await raw.send_multipart(newest)
            await raw.send_multipart([b"wrench", b"\x80", bytes(m.MAX_FRAME_BYTES + 1)])  # above the frame limit
            await raw.send_multipart(older)
            deadline_s = time.monotonic() + CONNECT_TIMEOUT_S
            while subscriber.errors.counts["stale_stamp"] == 0:  # the link carried both after the big frame
                assert time.monotonic() < deadline_s, subscriber.errors.counts
                await subscriber.wait(0.02)
            assert subscriber.errors.counts[m.OversizedFrame.kind] == 1
            assert subscriber.latest("wrench", 1.0).value.seq == 2

    run(scenario())


# --- the request path cannot be killed or starved ----------------------------------------------------------------


async def raw_request(raw: zmq.asyncio.Socket, request_id: bytes, frames) -> m.Message:
    """Send one request's ``frames`` on the DEALER ``raw`` and decode the reply with that id."""
    await raw.send_multipart([request_id, *frames])
    while True:
        answer = await raw.recv_multipart()
        if answer[0] == request_id:
            return m.decode(answer[1:])[1]


async def huge_handler(request: m.Request) -> m.Reply:
    """A handler whose replies quote the user's text in full (too large to encode), or raise quoting it."""
    if isinstance(request, m.GetStatus):
        return m.StatusReply(ok=True, status=m.ServiceStatus(state="ready", pid=1, uptime_s=1.0,
                                                             last_error="x" * 70_000))
    if isinstance(request, m.Stop) and request.reason == "raise":
        raise RuntimeError("y" * 70_000)
    if isinstance(request, m.Stop):
        return m.CommandReply(ok=False, error=f"refused {request.reason!r}")
    return m.CommandReply(ok=True)


def test_a_reply_too_large_to_encode_is_refused_in_short_and_the_server_answers_on(ipc_dir):
    endpoint = f"ipc://{ipc_dir}/api"

    async def scenario():
        with b.Bus() as bus:
            server = b.RequestServer(bus, endpoint, huge_handler, source="planner")
            serving = asyncio.create_task(server.serve())
            client = b.RequestClient(bus, endpoint, source="client", timeout_s=2.0)
            status = await client.request(m.GetStatus())  # its encoded header would exceed MAX_HEADER_BYTES
            assert isinstance(status, m.StatusReply) and not status.ok and "could not be sent" in status.error
            refused = await client.request(m.Stop(reason="z" * 60_000))  # the refusal quotes 60,000 characters
            assert not refused.ok and len(refused.error) <= b.MAX_ERROR_CHARS
            raised = await client.request(m.Stop(reason="raise"))
            assert not raised.ok and len(raised.error) <= b.MAX_ERROR_CHARS
            assert (await client.request(m.Start())).ok  # still serving
            assert not serving.done()
            assert server.errors.counts["reply_too_large"] == 1 and server.errors.counts["handler"] == 1
            serving.cancel()

    run(scenario())


def test_a_request_that_fails_outside_the_handler_is_counted_and_the_server_answers_on(ipc_dir):
    endpoint = f"ipc://{ipc_dir}/api"

    async def scenario():
        with b.Bus() as bus:
            server = b.RequestServer(bus, endpoint, handler, source="planner")
            encode_calls = 0
            real_encode = server._encode

            def failing_once(kind, reply):
                nonlocal encode_calls
                encode_calls += 1
                if encode_calls == 1:
                    raise TypeError("cannot encode this")
                return real_encode(kind, reply)

            server._encode = failing_once
            serving = asyncio.create_task(server.serve())
            client = b.RequestClient(bus, endpoint, source="client", timeout_s=0.5)
            with pytest.raises(TimeoutError):
                await client.request(m.Start())
            assert (await client.request(m.Start())).ok
            assert server.errors.counts["request_failed"] == 1 and not serving.done()
            serving.cancel()

    run(scenario())


def test_a_goal_with_a_65300_character_task_is_refused_with_a_bounded_reply(ipc_dir):
    endpoint = f"ipc://{ipc_dir}/api"

    async def scenario():
        with b.Bus() as bus:
            server = b.RequestServer(bus, endpoint, handler, source="planner")
            serving = asyncio.create_task(server.serve())
            raw = bus.socket(zmq.DEALER, endpoint, bind=False)
            goal = m.Goal(task="t" * 65_300, tolerance_mm=5.0, timeout_s=10.0)
            header = msgspec.msgpack.encode(m.SetGoal(goal=goal))
            assert len(header) < m.MAX_HEADER_BYTES
            reply = await raw_request(raw, b"1", [b"cmd/set_goal", header])
            assert not reply.ok and len(reply.error) <= b.MAX_ERROR_CHARS and "t" * 200 not in reply.error
            assert (await raw_request(raw, b"2", m.encode(m.Start()))).ok
            serving.cancel()

    run(scenario())


def test_the_rate_limit_grants_its_burst_then_its_rate():
    now = [0.0]
    limit = b.RateLimit(10.0, 3, clock_s=lambda: now[0])
    assert [limit.take() for _ in range(4)] == [True, True, True, False]
    now[0] += 0.1
    assert [limit.take() for _ in range(2)] == [True, False]
    now[0] += 100.0
    assert sum(limit.take() for _ in range(10)) == 3  # the bucket holds at most the burst


def test_a_flooding_client_is_refused_beyond_its_budget_while_another_client_is_served():
    now = [0.0]
    budget = b.RequestBudget(clock_s=lambda: now[0])
    flood = [budget.admit(b"flood") for _ in range(1000)]
    assert flood.count(None) == b.CLIENT_REQUEST_BURST and set(flood) == {None, "rate_limited"}
    assert budget.admit(b"operator") is None
    for index in range(b.MAX_CLIENTS * 2):  # many clients: the server's budget holds, memory stays bounded
        budget.admit(index.to_bytes(4, "big"))
    assert len(budget._clients) == b.MAX_CLIENTS
    assert budget.admit(b"operator") == "busy"
    now[0] += 1.0
    assert budget.admit(b"operator") is None


def test_a_request_flood_leaves_the_event_loop_its_period_and_other_clients_their_answers(ipc_dir):
    """2,000 GetStatus queued at once: a 10 ms ticker on the same loop keeps its period, the flood is answered (in
    part refused as rate_limited), and another client's request is answered promptly."""
    endpoint = f"ipc://{ipc_dir}/api"

    async def scenario():
        with b.Bus() as bus:
            server = b.RequestServer(bus, endpoint, handler, source="planner")
            raw = bus.socket(zmq.DEALER, endpoint, bind=False)
            operator = b.RequestClient(bus, endpoint, source="client", timeout_s=2.0)
            serving = asyncio.create_task(server.serve())
            assert (await operator.request(m.Start())).ok  # connected before the flood
            serving.cancel()
            await asyncio.gather(serving, return_exceptions=True)
            flood = 2000
            request = m.encode(m.GetStatus())
            for index in range(flood):
                await raw.send_multipart([index.to_bytes(4, "big"), *request])
            await asyncio.sleep(0.3)  # everything queued at the server
            gaps, stop = [], asyncio.Event()

            async def ticker():
                then = time.monotonic()
                while not stop.is_set():
                    await asyncio.sleep(0.01)
                    now = time.monotonic()
                    gaps.append(now - then)
                    then = now

            ticking = asyncio.create_task(ticker())
            serving = asyncio.create_task(server.serve())
            answered = Counter()
            start_s = time.monotonic()
            operator_reply = await operator.request(m.Start())
            operator_s = time.monotonic() - start_s
            while sum(answered.values()) < flood:
                answer = await raw.recv_multipart()
                reply = m.decode(answer[1:])[1]
                answered["ok" if reply.ok else reply.error.partition(":")[0]] += 1
            stop.set()
            await ticking
            serving.cancel()
            assert operator_reply.ok and operator_s < 1.0, operator_s
            assert max(gaps) < 0.25, max(gaps)
            assert answered["rate_limited"] > 0 and answered["ok"] >= b.CLIENT_REQUEST_BURST, answered

    run(scenario())


def test_a_frame_over_the_receive_limit_drops_the_link_and_the_drop_is_counted(ipc_dir):
    async def scenario():
        with b.Bus() as bus:
            endpoint = f"ipc://{ipc_dir}/huge"
            raw = bus.socket(zmq.PUB, endpoint, bind=True)
            subscriber = b.LatestSubscriber(bus, endpoint, ["wrench"])
            frames = m.encode(msgspec.structs.replace(WRENCH, seq=1, stamp_ns=time.monotonic_ns()))
            while "wrench" not in await subscriber.wait(0.02):  # slow joiner
                await raw.send_multipart(frames)
            assert subscriber.errors.counts["link_dropped"] == 0
            await raw.send_multipart([b"wrench", b"\x80", bytes(b.MAX_RECEIVE_BYTES + 1)])
            deadline_s = time.monotonic() + CONNECT_TIMEOUT_S
            while subscriber.errors.counts["link_dropped"] == 0:
                assert time.monotonic() < deadline_s, "the dropped link was not counted"
                await subscriber.wait(0.05)
            assert "dropped" in subscriber.errors.last_error and endpoint in subscriber.errors.last_error

    run(scenario())


def test_a_background_reader_counts_a_dropped_link_without_new_messages(ipc_dir):
    async def scenario():
        with b.Bus() as bus:
            endpoint = f"ipc://{ipc_dir}/gone"
            raw = bus.socket(zmq.PUB, endpoint, bind=True)
            subscriber = b.LatestSubscriber(bus, endpoint, ["wrench"])
            reading = asyncio.create_task(subscriber.run())
            frames = m.encode(msgspec.structs.replace(WRENCH, seq=1, stamp_ns=time.monotonic_ns()))
            while not subscriber.received["wrench"]:
                await raw.send_multipart(frames)
                await asyncio.sleep(0.02)
            raw.close(linger=0)  # the publisher goes away
            deadline_s = time.monotonic() + b.LINK_CHECK_S + CONNECT_TIMEOUT_S
            while subscriber.errors.counts["link_dropped"] == 0:
                assert time.monotonic() < deadline_s, "the dropped link was not counted"
                await asyncio.sleep(0.05)
            reading.cancel()

    run(scenario())
