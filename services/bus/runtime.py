"""The skeleton every service process shares: logging, the asyncio loop, signals, status, readiness, errors.

A service module provides ``async def main(service: Service) -> None``: it opens its driver and sockets through
``service``, registers shutdown hooks, calls ``await service.ready()`` once it can do its job and then loops,
waiting on sockets or timers (never spinning: an idle service sleeps). ``run_service`` runs it::

    def main_cli() -> int:
        return run_service("ft_reader", config.runtime, ft_reader_main)

What the runtime does around ``main``:

- logs to stderr as ``<time> <service> <LEVEL> <logger>: <text>``, and the same lines to its own file
  (``RuntimeConfig.log_file``, rotated at ``LOG_FILE_BYTES``), so that its shutdown lines survive a launcher that
  was killed (its stderr then goes nowhere); stdout carries only ``READY <name> <pid>``, printed (and flushed) by
  ``ready()`` for a launcher to wait on;
- on SIGINT or SIGTERM cancels ``main``; when ``main`` ends (cancelled, returned or raised) publishes state
  ``stopping``, runs the shutdown hooks (newest first) within ``shutdown_timeout_s`` and exits 0, or 1 when
  ``main`` raised or the hooks overran. The bound holds for hooks that await; a hook that blocks the loop
  (a synchronous driver call) cannot be cut off, so run such calls in an executor;
- publishes ``ServiceStatus`` on ``status/<name>`` every ``status_period_s`` and on each state change, and
  ``Heartbeat`` on ``heartbeat/<name>`` every ``heartbeat_period_s``, both on ``status_endpoint``;
- counts errors by kind (``count_error``, and every malformed message its subscribers and request servers see)
  and reports the counts and the newest text in the status, with the restart count the launcher passes in the
  environment variable ``HYDROSOFT_RESTARTS``, and the id of the stack launch it belongs to (``instance``), which
  the launcher passes in ``HYDROSOFT_INSTANCE`` (a service started alone makes its own);
- supervises the tasks ``main`` hands to ``supervise`` (a request server's ``serve``): one that ends other than
  by cancellation is logged and counted, and the service reports itself ``degraded`` from then on.

A long computation (a planner's solve) should run in an executor (``loop.run_in_executor``): while it holds the
loop, no timer fires, no heartbeat leaves and no subscriber reads.

``Latest`` (an input's newest value with a maximum age), ``Received`` and ``Stale`` live in ``sockets`` and are
re-exported here, since every service uses them.
"""

from __future__ import annotations

import asyncio
import logging
import os
import logging.handlers
import signal
import sys
import time
import uuid
from collections import Counter
from collections.abc import Awaitable, Callable, Iterable, Sequence

import msgspec

from hydrosoft.garbage_collection import settle_garbage_collector
from hydrosoft.services.bus.sockets import (
    Bus,
    BusConfigError,
    Curve,
    CurveKeys,
    ErrorCounter,
    Handler,
    Latest,
    LatestSubscriber,
    Publisher,
    Received,
    RequestServer,
    Stale,
    SUB_RCVHWM,
)
from hydrosoft.services.bus.messages import BusError, Heartbeat, ServiceState, ServiceStatus, topic_for

__all__ = ["Latest", "Received", "RuntimeConfig", "Service", "Stale", "new_instance_id", "run_service"]

#: Environment variable in which the launcher passes how often it restarted the service.
RESTARTS_ENV = "HYDROSOFT_RESTARTS"
#: Environment variable in which the launcher passes the id of its launch to every service.
INSTANCE_ENV = "HYDROSOFT_INSTANCE"
#: Environment variable in which the launcher names the arms (comma separated) whose commanders it starts after the
#: planner: the planner takes goals and reports ready only once each of them has published its state.
AWAIT_ARMS_ENV = "HYDROSOFT_AWAIT_ARMS"
#: A service's log file is rotated when it reaches this size, bytes; ``LOG_FILE_BACKUPS`` older files are kept
#: (``NAME.log.1`` ...), so one service's logs take at most (1 + LOG_FILE_BACKUPS) * LOG_FILE_BYTES on disk.
LOG_FILE_BYTES = 10 * 1024 * 1024
LOG_FILE_BACKUPS = 3
#: Exit codes: a requested stop or a normal end; a failure of ``main`` or of the shutdown.
EXIT_OK = 0
EXIT_FAILED = 1
#: How long the last messages (the ``stopping`` status) may take to leave when the service exits, ms.
FINAL_LINGER_MS = 200

log = logging.getLogger(__name__)


class RuntimeConfig(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """The runtime part of a service's config.

    status_endpoint: where the service binds the PUB socket for its status and heartbeat (``ipc://`` or
    ``tcp://127.0.0.1:PORT``). status_period_s: seconds between status messages. heartbeat_period_s: seconds
    between heartbeats (readers should time out after more than twice this). shutdown_timeout_s: the longest the
    shutdown hooks may take, s. log_level: a ``logging`` level name. log_file: where the service also writes its
    log (its directory is created), or None for stderr only. curve: the CURVE keys of the service's sockets
    (``bus.CurveKeys``), or None where every endpoint is local. also_bind: per ipc endpoint the service binds, a
    tcp endpoint it binds beside it (a stack split across hosts: its peers on the other host read it there).
    local_sources: the senders that share this host's clock (``Bus.local_sources``; None: all).
    """

    status_endpoint: str
    status_period_s: float = 1.0
    heartbeat_period_s: float = 0.1
    shutdown_timeout_s: float = 2.0
    log_level: str = "INFO"
    log_file: str | None = None
    curve: CurveKeys | None = None
    also_bind: dict[str, str] = {}
    local_sources: frozenset[str] | None = None

    def __post_init__(self) -> None:
        for name in ("status_period_s", "heartbeat_period_s", "shutdown_timeout_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"RuntimeConfig.{name} must be > 0, got {getattr(self, name)!r}")
        if not isinstance(logging.getLevelName(self.log_level), int):
            raise ValueError(f"RuntimeConfig.log_level {self.log_level!r} is not a logging level name")


ShutdownHook = Callable[[], Awaitable[None]]


class Service:
    """A running service's identity, sockets, state, error counts and shutdown hooks (see the module docstring).

    Make sockets through ``publisher``, ``subscriber`` and ``request_server`` so that their rates and errors
    appear in the status.
    """

    def __init__(self, name: str, config: RuntimeConfig, bus: Bus) -> None:
        self.name = name
        self.config = config
        self.bus = bus
        self.pid = os.getpid()
        self.log = logging.getLogger(name)
        self.errors = ErrorCounter(self.log)
        self.state: ServiceState = "starting"
        self.restarts = _restarts_from_environment(self.log)
        self.note = ""  # a line for the status on a state worth knowing (ServiceStatus.note); set it any time
        self.compilation = ""  # its compiled part: compiling, compiled or eager (ServiceStatus.compilation)
        self.instance = new_instance_id() if not os.environ.get(INSTANCE_ENV) else os.environ[INSTANCE_ENV][:64]
        self._started_ns = time.monotonic_ns()
        self._publishers: list[Publisher] = []
        self._subscribers: list[LatestSubscriber] = []
        self._shutdown_hooks: list[ShutdownHook] = []
        self._tasks: set[asyncio.Task[None]] = set()  # held here: the loop keeps only weak references to tasks
        self._degraded_by: set[str] = set()  # the supervised tasks that ended
        self._rates_since_ns = self._started_ns
        self._published_then: Counter[str] = Counter()
        self._received_then: Counter[str] = Counter()
        self._published_hz: dict[str, float] = {}
        self._received_hz: dict[str, float] = {}
        self._status = self.publisher(config.status_endpoint)

    # --- sockets ---

    def publisher(self, endpoint: str, *, bind: bool = True, curve: Curve | None = None) -> Publisher:
        """A publisher with ``source`` = the service's name, counted in the status."""
        publisher = Publisher(self.bus, endpoint, source=self.name, bind=bind, curve=curve)
        self._publishers.append(publisher)
        return publisher

    def subscriber(
        self,
        endpoints: str | Sequence[str],
        topics: Sequence[str] = ("",),
        *,
        background: bool = False,
        curve: Curve | None = None,
        rcvhwm: int = SUB_RCVHWM,
    ) -> LatestSubscriber:
        """A latest-value subscriber whose malformed messages count as this service's errors. ``background``:
        start its ``run`` task here (then read it with ``latest`` only); otherwise await its ``wait``, or call
        ``latest`` alone (it drains what queued since: then ``rcvhwm`` must hold all of that)."""
        subscriber = LatestSubscriber(self.bus, endpoints, topics, curve=curve, rcvhwm=rcvhwm, errors=self.errors)
        self._subscribers.append(subscriber)
        if background:
            self._tasks.add(asyncio.create_task(subscriber.run(), name=f"{self.name}.subscriber"))
        return subscriber

    def request_server(self, endpoint: str, handler: Handler, *, curve: Curve | None = None) -> RequestServer:
        """A request server answering with ``handler``; its bad requests count as this service's errors. Run its
        ``serve()`` as a task of ``main``."""
        return RequestServer(self.bus, endpoint, handler, source=self.name, curve=curve, errors=self.errors)

    def supervise(self, task: asyncio.Task[None]) -> asyncio.Task[None]:
        """Hold ``task`` (a request server's ``serve``) until the service stops; should it end other than by
        cancellation, log and count it (``task_ended``) and report the service ``degraded`` from then on. (A
        request server's ``serve`` ends only when its socket fails: restarting it would fail the same way.)"""
        self._tasks.add(task)
        task.add_done_callback(self._on_supervised_end)
        return task

    def _on_supervised_end(self, task: asyncio.Task[None]) -> None:
        if task.cancelled() or self.state == "stopping":
            return
        error = task.exception()
        self.log.error("task %s ended: %r; the service is degraded", task.get_name(), error)
        self.count_error("task_ended", f"{task.get_name()} ended: {error!r}")
        self._degraded_by.add(task.get_name())
        self._tasks.add(asyncio.get_running_loop().create_task(self._send_health(self.set_state("degraded"))))

    # --- health ---

    def degrade(self, cause: str) -> None:
        """Report the service ``degraded`` from its next state change on (``ready()`` included), for ``cause`` (a short
        name): a service that runs and reports but cannot do its job (a planner whose GPU is missing)."""
        self._degraded_by.add(cause)

    def count_error(self, kind: str, text: str) -> None:
        """Count one error of ``kind`` (short, e.g. ``"driver_timeout"``) with its explanation ``text``."""
        self.errors.count(kind, text)

    def on_shutdown(self, hook: ShutdownHook) -> None:
        """Run ``await hook()`` on shutdown (hooks run newest first, all within ``shutdown_timeout_s``)."""
        self._shutdown_hooks.append(hook)

    async def ready(self) -> None:
        """Declare the service ready: settle the garbage collector (``settle_garbage_collector``), publish the state
        and print ``READY <name> <pid>`` on stdout."""
        settle_garbage_collector()
        await self.set_state("ready")
        print(f"READY {self.name} {self.pid}", flush=True)

    def effective_state(self, state: ServiceState) -> ServiceState:
        """The state ``set_state(state)`` would set: ``ready`` reads ``degraded`` once a supervised task ended. A
        loop that sets its state only on a change compares with this, so it does not publish at every sample."""
        return "degraded" if state == "ready" and self._degraded_by else state

    async def set_state(self, state: ServiceState) -> None:
        """Change the state (starting, ready, degraded, stopping) and publish the status at once. A service
        whose supervised task ended stays ``degraded`` (it may still go to ``stopping``)."""
        state = self.effective_state(state)
        if state != self.state:
            self.log.info("state %s -> %s", self.state, state)
        self.state = state
        await self.publish_status()

    def status(self) -> ServiceStatus:
        """The current status, with the rates measured over the last status period, and the peers its CURVE
        servers refused counted as ``curve_refused`` errors."""
        errors = dict(self.errors.counts)
        if self.bus.curve_refused:
            errors["curve_refused"] = self.bus.curve_refused
        return ServiceStatus(
            state=self.state,
            pid=self.pid,
            uptime_s=(time.monotonic_ns() - self._started_ns) * 1e-9,
            published_hz=self._published_hz,
            received_hz=self._received_hz,
            errors=errors,
            last_error=self.errors.last_error,
            restarts=self.restarts,
            note=self.note,
            compilation=self.compilation,
            instance=self.instance,
        )

    async def publish_status(self) -> None:
        """Publish ``status()`` on ``status/<name>``."""
        await self._status.send(self.status(), topic_for(ServiceStatus, self.name))

    def measure_rates(self) -> None:
        """Set the status's per-topic rates (Hz) to the messages counted since the previous call (the status task
        calls it once per status period)."""
        now_ns = time.monotonic_ns()
        window_s = max((now_ns - self._rates_since_ns) * 1e-9, 1e-9)
        published = _total(publisher.sent for publisher in self._publishers)
        received = _total(subscriber.received for subscriber in self._subscribers)
        self._published_hz = {topic: (n - self._published_then[topic]) / window_s for topic, n in published.items()}
        self._received_hz = {topic: (n - self._received_then[topic]) / window_s for topic, n in received.items()}
        self._published_then, self._received_then, self._rates_since_ns = published, received, now_ns

    async def _publish_status_forever(self) -> None:
        while True:
            await asyncio.sleep(self.config.status_period_s)
            self.measure_rates()
            await self._send_health(self.publish_status())

    async def _publish_heartbeat_forever(self) -> None:
        heartbeat = Heartbeat(period_s=self.config.heartbeat_period_s)
        topic = topic_for(Heartbeat, self.name)
        while True:
            await self._send_health(self._status.send(heartbeat, topic))
            await asyncio.sleep(self.config.heartbeat_period_s)

    async def _send_health(self, sending: Awaitable[object]) -> None:
        try:
            await sending
        except BusError as error:
            self.count_error("status", f"cannot publish health: {error}")

    async def _run_shutdown_hooks(self) -> None:
        for hook in reversed(self._shutdown_hooks):
            try:
                await hook()
            except Exception:  # one failing hook must not skip the others (e.g. the arm's stop)
                self.log.exception("shutdown hook %r failed", hook)


def _total(counters: Iterable[Counter[str]]) -> Counter[str]:
    total: Counter[str] = Counter()
    for counter in counters:
        total.update(counter)
    return total


def _restarts_from_environment(logger: logging.Logger) -> int:
    text = os.environ.get(RESTARTS_ENV, "0")
    if text.isdigit():
        return int(text)
    logger.warning("%s=%r is not a count; reporting 0 restarts", RESTARTS_ENV, text)
    return 0


def new_instance_id() -> str:
    """A fresh id for a stack launch (or a service started alone): 32 hex digits, unique across launches."""
    return uuid.uuid4().hex


def setup_logging(name: str, level: str, log_file: str | None = None) -> None:
    """Log to stderr with the service's name in every line, and to ``log_file`` too (appended, rotated at
    ``LOG_FILE_BYTES``; each line is written as it is logged). A log file that cannot be opened is reported on
    stderr and the service logs there only."""
    handlers: list[logging.Handler] = [logging.StreamHandler(sys.stderr)]
    problem = None
    if log_file is not None:
        try:
            os.makedirs(os.path.dirname(os.path.abspath(log_file)), exist_ok=True)
            handlers.append(logging.handlers.RotatingFileHandler(log_file, maxBytes=LOG_FILE_BYTES,
                                                                 backupCount=LOG_FILE_BACKUPS))
        except OSError as error:
            problem = f"cannot write the log file {log_file}: {error}; logging to stderr only"
    logging.basicConfig(level=level, handlers=handlers, force=True,
                        format=f"%(asctime)s {name} %(levelname)s %(name)s: %(message)s")
    if problem is not None:
        log.warning(problem)


def run_service(name: str, config: RuntimeConfig, main: Callable[[Service], Awaitable[None]]) -> int:
    """Run ``main(service)`` in a fresh asyncio loop as the service ``name``; return the exit code."""
    setup_logging(name, config.log_level, config.log_file)
    return asyncio.run(_run(name, config, main))


async def _run(name: str, config: RuntimeConfig, main: Callable[[Service], Awaitable[None]]) -> int:
    bus = Bus(curve=config.curve, also_bind=config.also_bind, local_sources=config.local_sources)
    try:
        service = Service(name, config, bus)
    except BusConfigError as error:
        log.error("%s cannot start: %s", name, error)
        bus.close()
        return EXIT_FAILED
    service.log.info("started (pid %d, stack launch %s, restart %d)", service.pid, service.instance, service.restarts)
    try:
        exit_code = await _run_main(service, main)
        exit_code = max(exit_code, await _shut_down(service))
    finally:
        bus.close(linger_ms=FINAL_LINGER_MS)
    service.log.info("stopped (exit %d)", exit_code)
    return exit_code


async def _run_main(service: Service, main: Callable[[Service], Awaitable[None]]) -> int:
    """Run ``main`` with the health tasks beside it until it ends or SIGINT/SIGTERM cancels it."""
    loop = asyncio.get_running_loop()
    main_task = asyncio.create_task(main(service), name=f"{service.name}.main")
    stop_signals: list[signal.Signals] = []

    def on_signal(sig: signal.Signals) -> None:
        if stop_signals:
            service.log.warning("%s again while stopping; still waiting for the shutdown hooks", sig.name)
            return
        service.log.info("%s received, stopping", sig.name)
        stop_signals.append(sig)
        main_task.cancel()

    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, on_signal, sig)
    service._tasks |= {asyncio.create_task(service._publish_status_forever(), name=f"{service.name}.status"),
                       asyncio.create_task(service._publish_heartbeat_forever(), name=f"{service.name}.heartbeat")}
    try:
        await main_task
    except asyncio.CancelledError:
        if not stop_signals:
            raise
    except Exception:
        service.log.exception("main failed")
        return EXIT_FAILED
    return EXIT_OK


async def _shut_down(service: Service) -> int:
    """Publish ``stopping``, run the hooks within their bound, cancel every other task; the exit code."""
    exit_code = EXIT_OK
    await service._send_health(service.set_state("stopping"))
    try:
        await asyncio.wait_for(service._run_shutdown_hooks(), service.config.shutdown_timeout_s)
    except TimeoutError:
        service.log.error("shutdown hooks did not finish within %.1f s; exiting anyway",
                          service.config.shutdown_timeout_s)
        exit_code = EXIT_FAILED
    others = service._tasks | (asyncio.all_tasks() - {asyncio.current_task()})  # and whatever main left
    for task in others:
        task.cancel()
    await asyncio.gather(*others, return_exceptions=True)
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.remove_signal_handler(sig)
        # ignored from here to the exit: a second stop signal (a killed launcher's parent-death SIGTERM can come
        # twice) must not end the process before its last lines are written; SIGKILL still ends it
        signal.signal(sig, signal.SIG_IGN)
    return exit_code
