"""The bus: sockets with a safe endpoint policy, publishers, latest-value subscribers and the client's
request/reply pair (pyzmq ``zmq.asyncio``; message frames in ``messages``).

Topology. Each publishing service binds its own PUB endpoint, listed in the launch config, and each subscriber
connects to the endpoints of the services it reads (one SUB socket may connect to several). There is no
XPUB/XSUB proxy: for a stack of ~7 processes on one host the config lists every endpoint anyway, and without a
proxy a depth frame crosses one hop instead of two (half the copies through the kernel and no extra process on
two shared cores), and no single proxy process takes every stream down when it dies or stalls. A publisher that
restarts binds the same endpoint again and its subscribers reconnect on their own.

Latest value. Sensor streams are read by their newest message only. A ``LatestSubscriber`` reads whenever its
socket is readable (its ``wait`` loop, or its ``run`` task) and keeps only the newest message per topic, so as
long as its event loop is free nothing queues anywhere. While the loop is blocked (a planner's solve), messages
queue: ``SUB_RCVHWM`` in the SUB socket, the OS socket buffers (a few hundred kB: thousands of small messages,
about one depth frame) and ``PUB_SNDHWM`` in the publisher, which then drops new ones. All of that is bounded and
is read in one burst once the loop is free again (~10 us a message). ``ZMQ_CONFLATE`` would keep one message,
but only for single-frame messages; ours are multipart. A message always travels with its age, and
``latest(topic, max_age_s)`` raises ``Stale`` rather than hand out an old one: a service that blocks its loop
should run the long computation in an executor, so its subscribers keep reading.

Endpoint policy. ``ipc://``, ``inproc://`` and ``tcp://127.x.x.x`` (IPv4 loopback) are allowed as they are. Any
other TCP address (``tcp://*``, ``tcp://0.0.0.0``, a LAN address, a host name) reaches beyond this host, so the
socket must be given CURVE keys (``CurveServer`` on the side that authenticates its peers, usually the binding
one; ``CurveClient`` on the other); without them ``BusConfigError`` says so. Keys are ``zmq.auth`` certificate
files (``zmq.auth.create_certificates(dir, name)`` writes ``name.key`` and ``name.key_secret``); a CURVE server
admits only the clients whose public ``.key`` files lie in its ``authorized_keys_dir``, checked by a ZAP
authenticator thread the ``Bus`` starts (a thread, so handshakes proceed while a planner's solve holds the loop).
It counts every peer it refuses (``Bus.curve_refused``, which a service's status reports as ``curve_refused``): a
refused peer's handshake fails, so it receives nothing and nothing it sends is delivered. A secret key file that
its owner's group or others may read or write is refused (``BusConfigError`` naming the file).

A process's ``CurveKeys`` (``Bus(curve=...)``) say which of its sockets use CURVE: every ``tcp://`` endpoint
beyond loopback, and with ``loopback`` also those on 127.x (so that CI runs the secure path); ``ipc://`` never
(it does not leave the host, and its file's permissions guard it). A bound socket is then a CURVE server, a
connected one a client of the server key the ``CurveKeys`` name for that endpoint. A bus's ``also_bind`` adds a
second endpoint to a bind (an ipc endpoint's tcp twin, for the peers on another host).

Dead peers. A CURVE tcp endpoint is an inter-host link, and its socket gets ``INTER_HOST_TCP_OPTIONS``: TCP
keepalive and a retransmission limit, so that the link to a host that died or whose cable was pulled is closed
within seconds (a subscriber counts it as ``link_dropped``, libzmq reconnects once the peer is back) instead of when
the kernel gives up, after minutes. ZeroMQ's own heartbeats (``ZMQ_HEARTBEAT_IVL``) are not used: libzmq 4.3.5
aborts a process whose subscriber holds unread messages when a heartbeat times out (docs/decisions.md). The stack's
safety does not wait for either: the arm commander stops on the planner's heartbeat age.

Every socket option (HWM, LINGER 0, MAXMSGSIZE, subscriptions, CURVE) is set before bind/connect, where libzmq
applies it. Receive timeouts are asyncio's (``wait(timeout_s)``, the client's ``timeout_s``): ``RCVTIMEO`` does
not govern ``zmq.asyncio`` sockets.

Clocks. Ages and deadlines use ``time.monotonic_ns``, which all processes on one host share. A bus that knows its
host's senders (``local_sources``) treats every other ``source`` as another host's clock: its subscribers and
request servers move that sender's clock fields (``SENDER_CLOCK_FIELDS``) onto this host's clock with the offset
``peer_clocks`` measures, before any age, order or deadline check; so no offset between the hosts' clocks makes a
message stale or fresh. Other ``*_ns`` fields (the planner's timing breakdown) stay on the sender's clock, for
latency statistics only. A bus without ``local_sources`` (one host) moves nothing, and a stamp in its future is
refused (``FutureStamp``).
"""

from __future__ import annotations

import asyncio
import ipaddress
import itertools
import logging
import math
import stat
import time
from collections import Counter, OrderedDict
from collections.abc import Awaitable, Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Generic, TypeVar

import msgspec
import zmq
import zmq.asyncio
import zmq.auth
from zmq.auth.thread import ThreadAuthenticator
from zmq.utils.monitor import parse_monitor_message

from hydrosoft.services.bus.peer_clocks import PeerClocks
from hydrosoft.services.bus.messages import (
    MAX_FRAME_BYTES,
    BusError,
    CommandReply,
    Message,
    MessageError,
    OversizedFrame,
    Reply,
    Request,
    UnknownTopic,
    decode,
    encode,
)

log = logging.getLogger(__name__)

#: Messages a PUB socket queues per subscriber before it drops new ones (a few frames of the fastest stream).
PUB_SNDHWM = 16
#: Messages a SUB socket holds for its reader (beyond that they wait in the OS buffers, then in the publisher);
#: small, as only the newest counts and each can be a 600 kB depth frame.
SUB_RCVHWM = 4
#: Largest frame a receiving socket accepts (libzmq's ``MAXMSGSIZE``), bytes. libzmq drops the connection that
#: carries a larger frame and does not connect it again, which would cut a subscriber off its publisher for good.
#: So it sits well above ``MAX_FRAME_BYTES``: a frame between the two arrives and is rejected by ``decode`` as
#: ``oversized_frame`` (counted, the link stays up); only a frame past this bound (a broken or hostile sender,
#: never one of ours, as ``encode`` refuses them) drops the link, and memory stays bounded. libzmq says nothing
#: when it does: a subscriber watches its socket's monitor and counts every dropped link as ``link_dropped``.
MAX_RECEIVE_BYTES = 4 * MAX_FRAME_BYTES
#: Longest a subscriber waits without checking its socket's monitor for dropped links, s.
LINK_CHECK_S = 1.0
#: Most messages one ``drain`` call decodes (~10 us each), so that a flood cannot hold the event loop for long.
MAX_DRAIN_MESSAGES = 1000
#: ``zmq.EVENTS`` and ``zmq.POLLIN`` as plain ints: the receive path tests them per message, and each operation on
#: pyzmq's enum members makes new enum objects (a tenth of a subscriber's Python time per message).
_EVENTS, _POLLIN = int(zmq.EVENTS), int(zmq.POLLIN)
#: A received ``stamp_ns`` may lie this far in the future of the receiver's clock (same host: scheduling only).
FUTURE_STAMP_TOLERANCE_NS = 5_000_000
#: Default time a client waits for a reply, s.
REQUEST_TIMEOUT_S = 2.0
#: Errors of one kind are logged on the 1st, (N+1)th, (2N+1)th ... occurrence.
LOG_EVERY_N = 100

_LOOPBACK = ipaddress.ip_network("127.0.0.0/8")
#: Socket options of every inter-host link (a CURVE tcp endpoint), set before its bind or connect. Keepalive
#: probes start after 1 s without data from the peer and repeat every 1 s; 3 unanswered close the link (a receiver
#: of a dead peer notices within ~4 s). ``TCP_MAXRT`` (Linux: ``TCP_USER_TIMEOUT``, ms) closes a sender's link whose
#: data stays unacknowledged for 4 s, which keepalive does not cover; it also closes the link to a reader that has
#: read nothing for 4 s (its queue and socket buffer full): it reconnects when it reads again, having missed only
#: stale messages.
INTER_HOST_TCP_OPTIONS = ((zmq.TCP_KEEPALIVE, 1), (zmq.TCP_KEEPALIVE_IDLE, 1), (zmq.TCP_KEEPALIVE_INTVL, 1),
                          (zmq.TCP_KEEPALIVE_CNT, 3), (zmq.TCP_MAXRT, 4000))
#: The message fields that hold the sender's ``time.monotonic_ns`` (a 0 means "none" and is kept): moved onto the
#: receiver's clock for a sender on another host.
SENDER_CLOCK_FIELDS = ("stamp_ns", "deadline_ns", "goal_started_ns", "plan_done_ns", "goal_floor_ns")

M = TypeVar("M", bound=Message)
T = TypeVar("T")


class BusConfigError(BusError):
    """A socket cannot be set up as configured (endpoint policy, keys, address in use); the text says what to
    change."""


class Stale(BusError):
    """No value, or only one older than the caller's maximum age."""


class FutureStamp(MessageError):
    """A received message's ``stamp_ns`` lies in the future of this host's monotonic clock."""

    kind = "future_stamp"


class StaleStamp(MessageError):
    """A received message is stamped before the newest one already held for its topic (a replayed or forged old
    message: one publisher's stamps only grow)."""

    kind = "stale_stamp"


# --- errors and latest values ------------------------------------------------------------------------------------


def on_receiver_clock(msg: M, offset_ns: int) -> M:
    """``msg`` with each non-zero ``SENDER_CLOCK_FIELDS`` field moved by ``offset_ns`` (the sender's clock offset,
    ``peer_clocks``)."""
    moved = {name: value + offset_ns for name in SENDER_CLOCK_FIELDS if (value := getattr(msg, name, 0))}
    return msgspec.structs.replace(msg, **moved)


class ErrorCounter:
    """Counts errors by kind, keeps the newest text and logs each kind's 1st, (N+1)th, ... occurrence."""

    def __init__(self, logger: logging.Logger = log, log_every: int = LOG_EVERY_N) -> None:
        self.counts: Counter[str] = Counter()
        self.last_error = ""
        self._logger = logger
        self._log_every = log_every

    def count(self, kind: str, text: str) -> None:
        """Count one error of ``kind`` (a short name such as ``"schema"``) with its explanation ``text``."""
        self.counts[kind] += 1
        n = self.counts[kind]
        self.last_error = f"{kind}: {text}"
        if n % self._log_every == 1 or self._log_every == 1:
            self._logger.warning("%s (%d so far, logged every %d): %s", kind, n, self._log_every, text)


@dataclass(frozen=True)
class Received(Generic[T]):
    """A value with its stamp and age. stamp_ns: ``time.monotonic_ns()`` when it was produced (for a message,
    published); age_s: seconds from then until it was handed out."""

    value: T
    stamp_ns: int
    age_s: float


class Latest(Generic[T]):
    """The newest value of one input and its stamp; ``get`` hands it out only while it is younger than
    ``max_age_s`` (s), otherwise raises ``Stale``: an old value is never reused silently."""

    def __init__(self, name: str, max_age_s: float, clock_ns: Callable[[], int] = time.monotonic_ns) -> None:
        if not max_age_s > 0:
            raise ValueError(f"Latest({name!r}): max_age_s must be > 0, got {max_age_s!r}")
        self.name = name
        self.max_age_s = max_age_s
        self._clock_ns = clock_ns
        self._value: T | None = None
        self._stamp_ns: int | None = None

    def put(self, value: T, stamp_ns: int) -> None:
        """Store ``value`` produced at ``stamp_ns`` (``time.monotonic_ns``) unless the held one is newer."""
        if self._stamp_ns is None or stamp_ns >= self._stamp_ns:
            self._value, self._stamp_ns = value, stamp_ns

    def get(self, max_age_s: float | None = None) -> Received[T]:
        """The value and its age; ``max_age_s`` overrides the holder's limit for this call. Raises Stale."""
        limit_s = self.max_age_s if max_age_s is None else max_age_s
        if self._stamp_ns is None:
            raise Stale(f"{self.name}: nothing received yet")
        age_s = (self._clock_ns() - self._stamp_ns) * 1e-9
        if age_s > limit_s:
            raise Stale(f"{self.name}: newest value is {age_s:.3f} s old, limit {limit_s:.3f} s")
        return Received(self._value, self._stamp_ns, age_s)  # type: ignore[arg-type]

    @property
    def stamp_ns(self) -> int | None:
        """Stamp of the held value, or None before the first ``put``."""
        return self._stamp_ns


# --- sockets -----------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CurveServer:
    """CURVE for a socket that authenticates its peers. secret_key_file: its own ``.key_secret`` certificate;
    authorized_keys_dir: a directory of the admitted clients' public ``.key`` certificates."""

    secret_key_file: Path
    authorized_keys_dir: Path


@dataclass(frozen=True)
class CurveClient:
    """CURVE for a socket that connects to a CURVE server. secret_key_file: its own ``.key_secret`` certificate
    (its public half must be in the server's authorized directory); server_key_file: the server's public ``.key``."""

    secret_key_file: Path
    server_key_file: Path


Curve = CurveServer | CurveClient


@dataclass(frozen=True)
class CurveKeys:
    """A process's CURVE keys and the endpoints they apply to (see the module docstring).

    secret_key_file: this host's ``.key_secret`` certificate. authorized_keys_dir: the folder of the public ``.key``
    certificates of the peers its CURVE servers admit. server_key_files: per endpoint this process connects to,
    the public key certificate of the host that binds it; an endpoint not listed is bound on this host (its own
    public key, read from ``secret_key_file``). loopback: CURVE also on ``tcp://127.x.x.x`` endpoints.
    """

    secret_key_file: Path
    authorized_keys_dir: Path
    server_key_files: Mapping[str, Path] = field(default_factory=dict)
    loopback: bool = False

    def uses_curve(self, endpoint: str) -> bool:
        """Whether a socket on ``endpoint`` uses CURVE: tcp beyond loopback, or any tcp with ``loopback``."""
        return endpoint.startswith("tcp://") and (self.loopback or not is_local_endpoint(endpoint))

    def for_endpoint(self, endpoint: str, bind: bool) -> Curve | None:
        """The CURVE role of a socket bound (``bind``) or connected to ``endpoint``, or None for none."""
        if not self.uses_curve(endpoint):
            return None
        if bind:
            return CurveServer(self.secret_key_file, self.authorized_keys_dir)
        return CurveClient(self.secret_key_file, self.server_key_files.get(endpoint, self.secret_key_file))


def is_local_endpoint(endpoint: str) -> bool:
    """True for ``ipc://``, ``inproc://`` and ``tcp://`` on a literal 127.0.0.0/8 address. Raises BusConfigError
    for a transport other than those three or a tcp endpoint without a port."""
    transport, sep, address = endpoint.partition("://")
    if not sep:
        raise BusConfigError(f"endpoint {endpoint!r} has no transport: write ipc://PATH or tcp://127.0.0.1:PORT")
    if transport in ("ipc", "inproc"):
        return True
    if transport != "tcp":
        raise BusConfigError(f"endpoint {endpoint!r}: transport {transport!r} is not supported; use ipc:// or tcp://")
    host, sep, port = address.rpartition(":")
    if not sep or not (port == "*" or port.isdigit()):
        raise BusConfigError(f"endpoint {endpoint!r} has no port: write tcp://HOST:PORT (PORT may be * to bind)")
    try:
        return ipaddress.ip_address(host.strip("[]")) in _LOOPBACK
    except ValueError:
        return False


def check_endpoint(endpoint: str, curve: Curve | None) -> None:
    """Enforce the endpoint policy of the module docstring: raise BusConfigError for a non-local endpoint without
    CURVE keys."""
    if not is_local_endpoint(endpoint) and curve is None:
        raise BusConfigError(
            f"endpoint {endpoint!r} is not ipc:// or tcp://127.x.x.x, so it would expose the bus beyond this host; "
            "either use a local endpoint or configure CURVE keys for it: CurveServer(secret_key_file, "
            "authorized_keys_dir) on the authenticating side and CurveClient(secret_key_file, server_key_file) on "
            "the other (make key pairs with zmq.auth.create_certificates)"
        )


def check_secret_key_file(path: Path) -> None:
    """Raise BusConfigError naming ``path`` when its group or others may read or write it (or it is missing)."""
    try:
        mode = path.stat().st_mode
    except OSError as error:
        raise BusConfigError(f"cannot read CURVE certificate {path}: {error}") from None
    if mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise BusConfigError(f"CURVE secret key file {path} has mode {stat.S_IMODE(mode):04o}: it must be readable "
                             f"by its owner only; run chmod 600 {path}")


def _load_key_pair(path: Path, need_secret: bool) -> tuple[bytes, bytes | None]:
    try:
        public, secret = zmq.auth.load_certificate(path)
    except (OSError, ValueError) as error:
        raise BusConfigError(f"cannot read CURVE certificate {path}: {error}") from None
    if need_secret and secret is None:
        raise BusConfigError(f"CURVE certificate {path} holds no secret key: give the .key_secret file")
    if need_secret:
        check_secret_key_file(Path(path))
    return public, secret


class _CountingAuthenticator(ThreadAuthenticator):
    """pyzmq's ZAP thread, counting the peers it refuses (``refused``, written by its thread only)."""

    def __init__(self, context: zmq.Context, logger: logging.Logger) -> None:
        super().__init__(context, log=logger)
        self.refused = 0

    def _send_zap_reply(self, request_id: bytes, status_code: bytes, status_text: bytes,
                        user_id: str = "anonymous") -> None:
        if status_code != b"200":
            self.refused += 1
            if self.refused % LOG_EVERY_N == 1:
                self.log.warning("curve_refused (%d so far, logged every %d): a peer's key was refused: %s",
                                 self.refused, LOG_EVERY_N, status_text.decode(errors="replace"))
        super()._send_zap_reply(request_id, status_code, status_text, user_id)


class Bus:
    """One process's ZeroMQ context and socket factory, with the ZAP authenticator its CURVE servers need.

    Close it (``close`` or a ``with`` block) to close every socket it made; a ``with`` block drops what is still
    queued for sending (LINGER 0), so that a dead peer never delays an exit.

    curve: which sockets use CURVE, with which keys (None: none). also_bind: a second endpoint for each bound one
    listed (its tcp twin). local_sources: the ``source`` names that stamp with this host's clock (None: all).
    clock_ns: this process's monotonic clock, ns (a test hook: a clock offset by hours stands for another host).
    """

    def __init__(
        self,
        curve: CurveKeys | None = None,
        also_bind: Mapping[str, str] | None = None,
        local_sources: frozenset[str] | None = None,
        clock_ns: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        self.context = zmq.asyncio.Context()
        self.curve = curve
        self.also_bind = dict(also_bind or {})
        self.local_sources = local_sources
        self.clock_ns = clock_ns
        self._authenticator: _CountingAuthenticator | None = None
        self._zap_domains: dict[Path, str] = {}
        self._sockets: list[zmq.asyncio.Socket] = []
        self._watches: list[tuple[asyncio.AbstractEventLoop, int]] = []  # (loop, file descriptor) of ``watch``

    def socket(
        self,
        socket_type: int,
        endpoints: str | Sequence[str],
        *,
        bind: bool,
        curve: Curve | None = None,
        options: Sequence[tuple[int, int | bytes]] = (),
    ) -> zmq.asyncio.Socket:
        """A socket of ``socket_type`` bound (``bind``) or connected to each of ``endpoints``.

        LINGER 0, ``options`` (``(zmq.SNDHWM, 16)``, ``(zmq.SUBSCRIBE, b"topic")``, ...) and the CURVE keys are
        set before any bind or connect, and ``INTER_HOST_TCP_OPTIONS`` before a CURVE endpoint's. ``curve`` applies
        to every endpoint; None: the bus's ``CurveKeys`` decide per endpoint (the endpoints without CURVE are joined
        first, as libzmq keeps a CURVE option once set).
        A bind also binds each endpoint's ``also_bind`` twin. Raises BusConfigError on a policy violation, bad keys
        or a failed bind.
        """
        endpoints = [endpoints] if isinstance(endpoints, str) else list(endpoints)
        if bind:
            endpoints += [self.also_bind[endpoint] for endpoint in endpoints if endpoint in self.also_bind]
        curves = {endpoint: self._curve_for(endpoint, bind, curve) for endpoint in endpoints}
        for endpoint in endpoints:
            check_endpoint(endpoint, curves[endpoint])
        sock = self.context.socket(socket_type)
        try:
            sock.setsockopt(zmq.LINGER, 0)
            for option, value in options:
                sock.setsockopt(option, value)
            for endpoint in sorted(endpoints, key=lambda endpoint: curves[endpoint] is not None):
                endpoint_curve = curves[endpoint]
                if endpoint_curve is not None:
                    for option, value in INTER_HOST_TCP_OPTIONS:
                        sock.setsockopt(option, value)
                if isinstance(endpoint_curve, CurveServer):
                    self._make_curve_server(sock, endpoint_curve)
                elif isinstance(endpoint_curve, CurveClient):
                    self._make_curve_client(sock, endpoint_curve)
                (sock.bind if bind else sock.connect)(endpoint)
        except zmq.ZMQError as error:
            sock.close(linger=0)
            raise BusConfigError(f"cannot {'bind' if bind else 'connect'} {endpoints}: {error}") from None
        except BaseException:
            sock.close(linger=0)
            raise
        self._sockets.append(sock)
        return sock

    def _curve_for(self, endpoint: str, bind: bool, curve: Curve | None) -> Curve | None:
        """``curve`` when given, else what the bus's ``CurveKeys`` say for ``endpoint`` (None without them)."""
        if curve is not None or self.curve is None:
            return curve
        return self.curve.for_endpoint(endpoint, bind)

    def _make_curve_server(self, sock: zmq.Socket, curve: CurveServer) -> None:
        public, secret = _load_key_pair(curve.secret_key_file, need_secret=True)
        sock.zap_domain = self._zap_domain(Path(curve.authorized_keys_dir)).encode()
        sock.curve_publickey = public
        sock.curve_secretkey = secret
        sock.curve_server = True

    def _make_curve_client(self, sock: zmq.Socket, curve: CurveClient) -> None:
        public, secret = _load_key_pair(curve.secret_key_file, need_secret=True)
        server_public, _ = _load_key_pair(curve.server_key_file, need_secret=False)
        sock.curve_publickey = public
        sock.curve_secretkey = secret
        sock.curve_serverkey = server_public

    def _zap_domain(self, keys_dir: Path) -> str:
        """The ZAP domain admitting the public keys in ``keys_dir``, starting the authenticator on first use."""
        keys_dir = keys_dir.resolve()
        if keys_dir in self._zap_domains:
            return self._zap_domains[keys_dir]
        if not keys_dir.is_dir() or not any(keys_dir.glob("*.key")):
            raise BusConfigError(f"CURVE authorized_keys_dir {keys_dir} holds no public .key certificates")
        if self._authenticator is None:
            self._authenticator = _CountingAuthenticator(self.context, log.getChild("zap"))
            self._authenticator.start()
        domain = f"hydrosoft-{len(self._zap_domains)}"
        self._authenticator.configure_curve(domain=domain, location=str(keys_dir))
        self._zap_domains[keys_dir] = domain
        return domain

    def is_remote(self, source: str) -> bool:
        """Whether ``source`` stamps with another host's clock (see Clocks in the module docstring)."""
        return self.local_sources is not None and source not in self.local_sources

    @property
    def curve_refused(self) -> int:
        """How many peers this bus's CURVE servers refused (an unauthorised key, or none)."""
        return self._authenticator.refused if self._authenticator is not None else 0

    def watch(self, loop: asyncio.AbstractEventLoop, fd: int, callback: Callable[[], None]) -> None:
        """Call ``callback()`` on ``loop`` whenever file descriptor ``fd`` (a socket's ``zmq.FD``) signals, until the
        bus closes."""
        loop.add_reader(fd, callback)
        self._watches.append((loop, fd))

    def close(self, linger_ms: int = 0) -> None:
        """Close every socket made here, stop the authenticator and end the context. linger_ms: how long queued
        outgoing messages may still be sent, ms (a clean shutdown's last status); 0 drops them."""
        for loop, fd in self._watches:
            loop.remove_reader(fd)  # before its socket closes (a closed loop has none left)
        self._watches.clear()
        for sock in self._sockets:
            sock.close(linger=linger_ms)
        self._sockets.clear()
        if self._authenticator is not None:
            self._authenticator.stop()
            self._authenticator = None
        self.context.destroy(linger=linger_ms)

    def __enter__(self) -> Bus:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


def _bound_endpoint(sock: zmq.Socket) -> str:
    return sock.getsockopt_string(zmq.LAST_ENDPOINT)


# --- streams -----------------------------------------------------------------------------------------------------


class Publisher:
    """A PUB socket that stamps and sends messages.

    Each ``send`` sets ``seq`` (per topic, from 1), ``stamp_ns`` (the bus's ``clock_ns``, ``time.monotonic_ns``) and
    ``source``, checks
    the message and hands its arrays to ZeroMQ without copying them (do not modify an array after sending it).
    A subscriber that is not keeping up loses new messages beyond ``sndhwm``; the publisher never blocks.

    Send path. A PUB socket never blocks (libzmq drops what a subscriber's queue cannot hold), so ``send`` hands
    the frames to a plain pyzmq socket that shadows this one, with ``NOBLOCK``, instead of ``zmq.asyncio``'s
    send: no future, no loop callback per message (``zmq.asyncio`` would only try the same non-blocking send
    first). ``send`` stays a coroutine, so a caller's code does not change.
    """

    def __init__(
        self,
        bus: Bus,
        endpoint: str,
        *,
        source: str,
        bind: bool = True,
        curve: Curve | None = None,
        sndhwm: int = PUB_SNDHWM,
    ) -> None:
        self.source = source
        self.sent: Counter[str] = Counter()
        self._clock_ns = bus.clock_ns
        self._sock = bus.socket(zmq.PUB, endpoint, bind=bind, curve=curve, options=[(zmq.SNDHWM, sndhwm)])
        self._plain = zmq.Socket.shadow(self._sock.underlying)  # the same socket, sent to without futures

    @property
    def endpoint(self) -> str:
        """The endpoint actually bound or connected (a ``tcp://127.0.0.1:*`` bind shows its port here)."""
        return _bound_endpoint(self._sock)

    async def send(self, msg: M, topic: str | None = None) -> M:
        """Stamp ``msg`` and publish it on ``topic`` (default its kind's topic); return the stamped message.
        Raises the ``MessageError`` of a message that breaks its kind's rules."""
        topic = msg.topic if topic is None else topic
        stamped = msgspec.structs.replace(msg, seq=self.sent[topic] + 1, stamp_ns=self._clock_ns(),
                                          source=self.source)
        self._plain.send_multipart(encode(stamped, topic), zmq.NOBLOCK, copy=False)  # PUB: never raises Again
        self.sent[topic] += 1
        return stamped


def _resolve(future: asyncio.Future[bool], value: bool) -> None:
    """Set ``future``'s result unless it is done."""
    if not future.done():
        future.set_result(value)


class LatestSubscriber:
    """A SUB socket that keeps the newest valid message per topic.

    Read it in one of two ways: await ``wait`` in the service's loop (an event-driven service), or start ``run``
    as a task and call ``latest`` whenever an input is needed (a service whose loop does other work). Only one
    coroutine may wait on a subscriber at a time. ``drain`` (called by both and by ``latest``) reads everything
    queued without blocking; invalid messages (and those stamped in the future, or before the newest one held
    for their topic) are counted in ``errors`` by kind (logged once per ``LOG_EVERY_N``) and dropped, never
    raised; so are the links it lost (``link_dropped``, checked at least every ``LINK_CHECK_S`` while it waits).
    ``received`` counts valid messages per topic. Topics are matched by prefix, as ZeroMQ subscriptions are
    (``""``: all).

    Receive path. The event loop watches the socket's file descriptor from the first ``wait`` on until the bus
    closes (``Bus.watch``), and a wake-up reads through a plain pyzmq socket that shadows this one, not through
    ``zmq.asyncio``'s poller and futures: one loop callback per wake-up and no future per message, 0.66 of the
    poller's CPU time per message (the bus's latency tail, docs/benchmarks.md). The descriptor only says that the
    socket's state may have changed, so every wake-up reads all that is queued.

    A subscriber that is not reading when a publisher exits can lose that publisher's last messages: libzmq
    discards what it had not yet read from a closed connection (seen with a final ``stopping`` status). Read
    status and other last words with a subscriber that reads all along (``run``).
    """

    def __init__(
        self,
        bus: Bus,
        endpoints: str | Sequence[str],
        topics: Sequence[str] = ("",),
        *,
        curve: Curve | None = None,
        rcvhwm: int = SUB_RCVHWM,
        errors: ErrorCounter | None = None,
    ) -> None:
        self.errors = errors if errors is not None else ErrorCounter()
        self.received: Counter[str] = Counter()
        self._bus = bus
        self._peer_clocks = PeerClocks()
        self._latest: dict[str, Latest[Message]] = {}
        self._arrivals: dict[str, asyncio.Event] = {}
        self._waiting = False
        options: list[tuple[int, int | bytes]] = [(zmq.RCVHWM, rcvhwm), (zmq.MAXMSGSIZE, MAX_RECEIVE_BYTES)]
        options += [(zmq.SUBSCRIBE, topic.encode()) for topic in topics]
        self._sock = bus.socket(zmq.SUB, endpoints, bind=False, curve=curve, options=options)
        self._plain = zmq.Socket.shadow(self._sock.underlying)  # the same socket, read without futures
        self._fd = self._sock.getsockopt(zmq.FD)
        self._watched: asyncio.AbstractEventLoop | None = None  # the loop that watches the descriptor
        self._woken: asyncio.Future[bool] | None = None  # what a waiting ``_readable`` awaits
        self._monitor = self._sock.get_monitor_socket(zmq.EVENT_DISCONNECTED)

    def _count_dropped_links(self) -> None:
        """Count (``link_dropped``) and log every connection the socket lost since the last call: its publisher
        exited (libzmq connects again when it is back), or it sent a frame over ``MAX_RECEIVE_BYTES`` (libzmq
        drops the link for good and would say nothing)."""
        while self._monitor.getsockopt(_EVENTS) & _POLLIN:
            event = parse_monitor_message(self._monitor.recv_multipart(zmq.NOBLOCK).result())
            endpoint = event["endpoint"].decode(errors="replace")
            self.errors.count("link_dropped", f"the link to {endpoint} dropped: its publisher exited, its host "
                                              "stopped answering (an inter-host link's keepalive), or it sent a "
                                              f"frame over {MAX_RECEIVE_BYTES} bytes (then the link stays down)")

    def drain(self) -> set[str]:
        """Read every message queued now (at most ``MAX_DRAIN_MESSAGES``) and keep the newest valid one per
        topic. Returns the topics that got a new message. Dropped links are counted first (``link_dropped``)."""
        self._count_dropped_links()
        updated: set[str] = set()
        for _ in range(MAX_DRAIN_MESSAGES):
            if not self._plain.getsockopt(_EVENTS) & _POLLIN:  # cheaper than a recv that fails with Again
                break
            frames = self._plain.recv_multipart(zmq.NOBLOCK, copy=False)
            received_ns = self._bus.clock_ns()
            try:
                topic, msg = decode(frames)
                if self._bus.is_remote(msg.source):
                    msg = on_receiver_clock(msg, self._peer_clocks.offset_ns(msg.source, msg.stamp_ns, received_ns))
                if msg.stamp_ns > received_ns + FUTURE_STAMP_TOLERANCE_NS:
                    raise FutureStamp(f"{topic!r} seq {msg.seq} from {msg.source!r} is stamped "
                                      f"{(msg.stamp_ns - received_ns) * 1e-6:.1f} ms in the future")
                slot = self._latest.get(topic)
                if slot is not None and msg.stamp_ns < slot.stamp_ns:
                    raise StaleStamp(f"{topic!r} seq {msg.seq} from {msg.source!r} is stamped "
                                     f"{(slot.stamp_ns - msg.stamp_ns) * 1e-6:.1f} ms before the newest one held")
            except MessageError as error:
                self.errors.count(error.kind, str(error))
                continue
            if slot is None:
                slot = self._latest[topic] = Latest(topic, math.inf, self._bus.clock_ns)
            slot.put(msg, msg.stamp_ns)
            self.received[topic] += 1
            updated.add(topic)
            arrival = self._arrivals.get(topic)
            if arrival is not None:
                arrival.set()
        return updated

    def arrival(self, topic: str) -> asyncio.Event:
        """An event that is set whenever a valid message on exactly ``topic`` is kept (by any drain); the reader
        clears it. A loop that idles can await it to wake on that input at once (one event per topic)."""
        return self._arrivals.setdefault(topic, asyncio.Event())

    async def wait(self, timeout_s: float | None = None) -> set[str]:
        """Wait until at least one valid message arrived (at most ``timeout_s`` s; None: no limit), drain, and
        return the topics that got a new message (empty on timeout)."""
        if self._waiting:
            raise RuntimeError("another coroutine already waits on this subscriber (wait and run exclude each other)")
        loop = asyncio.get_running_loop()
        deadline_s = None if timeout_s is None else loop.time() + timeout_s
        self._waiting = True
        try:
            updated = self.drain()
            while not updated:
                if deadline_s is None:
                    await self._readable(LINK_CHECK_S)  # then drain, which counts links dropped meanwhile
                else:
                    remaining_s = deadline_s - loop.time()
                    if remaining_s <= 0 or not await self._readable(remaining_s):
                        return self.drain()
                updated = self.drain()
            return updated
        finally:
            self._waiting = False

    def _on_signal(self) -> None:
        """The socket's descriptor signalled: wake the waiting ``_readable`` when a message is queued. Reading
        ``EVENTS`` re-arms the descriptor, also when no one waits (then the next ``wait`` drains first)."""
        queued = self._plain.getsockopt(_EVENTS) & _POLLIN  # read every time: it re-arms the descriptor
        if queued and self._woken is not None:
            _resolve(self._woken, True)

    async def _readable(self, timeout_s: float) -> bool:
        """Wait until the socket holds a message (True) or ``timeout_s`` (s) passed (False)."""
        loop = asyncio.get_running_loop()
        if self._watched is not loop:
            self._bus.watch(loop, self._fd, self._on_signal)
            self._watched = loop
        if self._plain.getsockopt(_EVENTS) & _POLLIN:  # queued since the last drain
            return True
        woken = self._woken = loop.create_future()
        timer = loop.call_later(timeout_s, _resolve, woken, False)
        try:
            return await woken
        finally:
            timer.cancel()
            self._woken = None

    async def run(self) -> None:
        """Read every message as it arrives, until cancelled (start it as a task; then use only ``latest``)."""
        while True:
            await self.wait()

    def latest(self, topic: str, max_age_s: float, kind: type[M] = Message) -> Received[M]:  # type: ignore[assignment]
        """The newest message on exactly ``topic`` (after a drain) with its age since it was published. Raises
        Stale when none arrived or the newest is older than ``max_age_s`` (s), TypeError when it is not a
        ``kind``."""
        self.drain()
        slot = self._latest.get(topic)
        if slot is None:
            raise Stale(f"{topic}: nothing received yet")
        received = slot.get(max_age_s)
        if not isinstance(received.value, kind):
            raise TypeError(f"{topic} carries {type(received.value).__name__}, not {kind.__name__}")
        return received  # type: ignore[return-value]


# --- client API ---------------------------------------------------------------------------------------------------

Handler = Callable[[Request], Awaitable[Reply]]

#: Most characters of user text (a task name, a reason) that a reply or a log line quotes.
QUOTE_CHARS = 80
#: Most characters of a reply's ``error`` text: with ``QUOTE_CHARS`` this keeps every refusal far below
#: ``MAX_HEADER_BYTES``, so that a refusal can always be sent.
MAX_ERROR_CHARS = 1000
#: Requests one client (one DEALER connection) may have handled per second, sustained. A client polls its goal's
#: status at 4/s; beyond this budget a request is refused at once (``rate_limited``, not decoded, not handled), so
#: a flooding client costs the server a few tens of microseconds per request and never starves the others.
CLIENT_REQUESTS_PER_S = 50.0
#: Requests one client may send back to back before its budget applies: a script's burst of requests answered
#: one by one (a test's ~60 fuzzed requests) stays within it.
CLIENT_REQUEST_BURST = 100
#: Requests all clients together may have handled per second, sustained, and back to back; beyond it requests are
#: refused as ``busy``. Handling a GetStatus costs the planner ~0.2 ms of its event loop, so this bounds the loop's
#: share spent on requests to a few percent.
SERVER_REQUESTS_PER_S = 200.0
SERVER_REQUEST_BURST = 200
#: Clients whose budgets a server keeps; the least recently seen is forgotten beyond it (memory stays bounded).
MAX_CLIENTS = 256


def quote(text: str, limit: int = QUOTE_CHARS) -> str:
    """``text`` quoted (``repr``), cut to its first ``limit`` characters with its full length said when longer."""
    if len(text) <= limit:
        return repr(text)
    return f"{text[:limit]!r}... ({len(text)} characters)"


def bounded(text: str, limit: int = MAX_ERROR_CHARS) -> str:
    """``text`` cut to at most ``limit`` characters (the cut marked with ``...``)."""
    return text if len(text) <= limit else text[:limit - 3] + "..."


class RateLimit:
    """A token bucket: ``take`` grants up to ``burst`` calls at once and ``rate_per_s`` calls per second sustained.
    clock_s: the time source (s, ``time.monotonic``)."""

    def __init__(self, rate_per_s: float, burst: int, clock_s: Callable[[], float] = time.monotonic) -> None:
        if not (rate_per_s > 0 and burst >= 1):
            raise ValueError(f"RateLimit needs rate_per_s > 0 and burst >= 1, got {rate_per_s!r}, {burst!r}")
        self.rate_per_s, self.burst = rate_per_s, burst
        self._clock_s = clock_s
        self._tokens = float(burst)
        self._then_s = clock_s()

    def take(self) -> bool:
        """Whether one more call is within the budget now (and, if so, spend it)."""
        now_s = self._clock_s()
        self._tokens = min(self.burst, self._tokens + (now_s - self._then_s) * self.rate_per_s)
        self._then_s = now_s
        if self._tokens < 1.0:
            return False
        self._tokens -= 1.0
        return True


class RequestBudget:
    """The request budgets of one server: one ``RateLimit`` per client identity (the ``MAX_CLIENTS`` most recently
    seen) and one for all clients together. ``admit`` names why a request is refused, or returns None."""

    def __init__(self, clock_s: Callable[[], float] = time.monotonic) -> None:
        self._clock_s = clock_s
        self._server = RateLimit(SERVER_REQUESTS_PER_S, SERVER_REQUEST_BURST, clock_s)
        self._clients: OrderedDict[bytes, RateLimit] = OrderedDict()

    def admit(self, identity: bytes) -> str | None:
        """None when a request of client ``identity`` may be handled now; else the error kind: ``rate_limited``
        (this client is over its budget) or ``busy`` (all clients together are)."""
        limit = self._clients.pop(identity, None)
        if limit is None:
            limit = RateLimit(CLIENT_REQUESTS_PER_S, CLIENT_REQUEST_BURST, self._clock_s)
            if len(self._clients) >= MAX_CLIENTS:
                self._clients.popitem(last=False)
        self._clients[identity] = limit
        if not limit.take():
            return "rate_limited"
        if not self._server.take():
            return "busy"
        return None


class RequestServer:
    """A ROUTER socket answering the client's requests with ``handler``, one at a time.

    Frames: ``[client identity, request id, message frames...]`` in, the same identity and id with the reply's
    frames out. A request that does not decode, is not a ``Request``, has passed its ``deadline_ns``, is over its
    client's or the server's budget (``RequestBudget``) or makes the handler raise gets ``CommandReply(ok=False,
    error=...)`` (or its kind's reply) and is counted in ``errors``; a reply that cannot be encoded (too large) is
    replaced by a short refusal, counted as ``reply_too_large``; any other failure of one request is counted as
    ``request_failed`` and logged. The server carries on in every case: ``serve`` ends only when cancelled or when
    its socket is closed. It yields to the event loop after every request, so that a flood of queued requests
    (which ``recv_multipart`` hands out without ever suspending) cannot hold the loop. Error texts are cut to
    ``MAX_ERROR_CHARS``.
    """

    def __init__(
        self,
        bus: Bus,
        endpoint: str,
        handler: Handler,
        *,
        source: str,
        bind: bool = True,
        curve: Curve | None = None,
        errors: ErrorCounter | None = None,
        budget: RequestBudget | None = None,
    ) -> None:
        self.source = source
        self.errors = errors if errors is not None else ErrorCounter()
        self._handler = handler
        self._budget = budget if budget is not None else RequestBudget()
        self._bus = bus
        self._peer_clocks = PeerClocks()
        self._replies = 0
        self._sock = bus.socket(zmq.ROUTER, endpoint, bind=bind, curve=curve,
                                options=[(zmq.MAXMSGSIZE, MAX_RECEIVE_BYTES)])

    @property
    def endpoint(self) -> str:
        """The endpoint actually bound or connected."""
        return _bound_endpoint(self._sock)

    async def serve(self) -> None:
        """Answer requests until cancelled (or until the socket is closed, which raises ``zmq.ZMQError``)."""
        while True:
            try:
                await self.handle_one()
            except Exception as error:  # noqa: BLE001 - one request never ends the server
                if self._sock.closed:
                    raise
                log.exception("request failed")
                self.errors.count("request_failed", bounded(repr(error)))
            await asyncio.sleep(0)  # let the heartbeat and the planning loop run between two queued requests

    async def handle_one(self) -> None:
        """Wait for one request and answer it."""
        frames = await self._sock.recv_multipart(copy=False)
        if len(frames) < 2:
            self.errors.count("frame_count", f"a request of {len(frames)} frame(s) has no request id")
            return
        identity, request_id = frames[0], frames[1]
        refusal = self._budget.admit(identity.bytes)
        if refusal is not None:
            self.errors.count(refusal, f"request refused: {refusal.replace('_', ' ')}")
            reply: Reply = CommandReply(ok=False, error=f"{refusal}: too many requests, try again later")
            kind: type[Reply] = CommandReply
        else:
            kind, reply = await self._answer(frames[2:])
        await self._sock.send_multipart([identity, request_id, *self._encode(kind, reply)], copy=False)

    def _encode(self, kind: type[Reply], reply: Reply) -> list[bytes | object]:
        """The frames of ``reply`` (stamped, its error text bounded), or of a short refusal of ``kind`` when the
        reply cannot be encoded."""
        self._replies += 1
        stamp = {"seq": self._replies, "stamp_ns": self._bus.clock_ns(), "source": self.source}
        try:
            return encode(msgspec.structs.replace(reply, error=bounded(reply.error), **stamp))
        except MessageError as error:
            text = f"the reply {type(reply).__name__} could not be sent: {bounded(str(error), QUOTE_CHARS * 2)}"
            self.errors.count("reply_too_large" if isinstance(error, OversizedFrame) else "reply_encode", text)
            return encode(kind(ok=False, error=text, **stamp))

    async def _answer(self, frames: Sequence[zmq.Frame]) -> tuple[type[Reply], Reply]:
        """The reply kind the request expects and the reply to it (a request from another host's clock moved onto
        this one's first)."""
        received_ns = self._bus.clock_ns()
        try:
            topic, request = decode(frames)
            if not isinstance(request, Request):
                raise UnknownTopic(f"{quote(topic)} is not a request topic")
        except MessageError as error:
            self.errors.count(error.kind, bounded(f"bad request: {error}"))
            return CommandReply, CommandReply(ok=False, error=f"{error.kind}: {error}")
        if self._bus.is_remote(request.source):
            request = on_receiver_clock(request, self._peer_clocks.offset_ns(request.source, request.stamp_ns,
                                                                             received_ns))
        kind = request.reply
        if request.deadline_ns and self._bus.clock_ns() > request.deadline_ns:
            text = f"{type(request).__name__} from {quote(request.source)} arrived after its deadline"
            self.errors.count("expired_request", text)
            return kind, kind(ok=False, error=text)
        try:
            reply = await self._handler(request)
        except Exception as error:  # the server outlives a failing handler; the client gets the reason
            log.exception("handler failed on %s", type(request).__name__)
            self.errors.count("handler", bounded(f"{type(request).__name__}: {error!r}"))
            return kind, kind(ok=False, error=f"handler failed: {error!r}")
        if not isinstance(reply, kind):
            text = f"handler answered {type(request).__name__} with {type(reply).__name__}, not {kind.__name__}"
            self.errors.count("handler", text)
            return kind, kind(ok=False, error=text)
        return kind, reply


class RequestClient:
    """A DEALER socket sending requests and waiting for their replies, one request at a time.

    Each request gets an id and a ``deadline_ns`` (now + timeout), so a server that receives it late refuses it
    instead of acting on it. Replies to earlier, timed-out requests are dropped. ``ZMQ_IMMEDIATE`` keeps requests
    from queueing on a connection that is not up.
    """

    def __init__(
        self,
        bus: Bus,
        endpoint: str,
        *,
        source: str,
        curve: Curve | None = None,
        timeout_s: float = REQUEST_TIMEOUT_S,
    ) -> None:
        self.source = source
        self.timeout_s = timeout_s
        self.endpoint = endpoint
        self._ids = itertools.count(1)
        self._clock_ns = bus.clock_ns
        self._lock = asyncio.Lock()
        self._sock = bus.socket(zmq.DEALER, endpoint, bind=False, curve=curve,
                                options=[(zmq.IMMEDIATE, 1), (zmq.MAXMSGSIZE, MAX_RECEIVE_BYTES)])

    async def request(self, request: Request, timeout_s: float | None = None) -> Reply:
        """Send ``request`` and return the server's reply (check its ``ok``). Raises TimeoutError when no reply
        comes within ``timeout_s`` (default the client's), or the ``MessageError`` of a malformed reply."""
        timeout_s = self.timeout_s if timeout_s is None else timeout_s
        async with self._lock:
            request_id = next(self._ids).to_bytes(8, "big")
            now_ns = self._clock_ns()
            request = msgspec.structs.replace(request, seq=int.from_bytes(request_id, "big"), stamp_ns=now_ns,
                                              source=self.source, deadline_ns=now_ns + int(timeout_s * 1e9))
            try:
                async with asyncio.timeout(timeout_s):
                    await self._sock.send_multipart([request_id, *encode(request)], copy=False)
                    while True:
                        frames = await self._sock.recv_multipart(copy=False)
                        if frames and frames[0].bytes == request_id:
                            break
            except TimeoutError:
                raise TimeoutError(f"no reply to {type(request).__name__} from {self.endpoint} within "
                                   f"{timeout_s} s") from None
        _, reply = decode(frames[1:])
        if not isinstance(reply, Reply):
            raise UnknownTopic(f"the server answered with {type(reply).__name__}, which is not a reply")
        return reply
