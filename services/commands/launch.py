"""``hydrosoft-stack launch CONFIG``: start the stack's services as subprocesses, keep them up, stop them safely.

Start. The launcher takes ``config.run_dir`` (creates it, holds ``run_dir/launcher.lock`` so that no second stack
drives the same arms, removes stale ipc socket files of its endpoints), then starts every service of
``config.service_names()`` (or the ``--only`` subset) in that order as
``python -m hydrosoft.services.MODULE CONFIG --name NAME`` (MODULE = NAME before the first ``-``). Each runs in its
own session and process group, with ``HYDROSOFT_RESTARTS`` set to its restart count, ``HYDROSOFT_INSTANCE`` to
the launch's id (one per launch, shared by all its services and shown in their status: a goal set on one launch
is refused by the next) and stdin closed; on Linux it gets SIGTERM if the launcher dies, so a killed launcher
leaves no unsupervised arm commander behind. Every line of its stdout and stderr is echoed as ``[NAME] line``
(and appended to ``LOG_DIR/NAME.log`` with ``--log-dir``); each service also writes its own log file
(``config.service_log_dir()``), which holds its shutdown lines even when the launcher was killed.
The next service starts once this one printed ``READY NAME PID`` (within its ``ready_timeout_s``); one that exits
or stays silent fails the launch: the error names it and everything started is stopped again. The planner is the
exception (``start_order``): it starts first, and the others start one after another while it builds and loads its
solver; at its first start it gets ``HYDROSOFT_AWAIT_ARMS`` (the arms of the launch's arm commanders) and takes no
goal, nor reports ready, before each of those commanders has published its arm state; the stack is ready when it is
too.

Supervision. A service that exits is restarted by its policy (``never``; ``on-failure``: a non-zero exit or a
signal; ``always``) after a backoff that doubles from ``backoff_s`` (capped at ``MAX_BACKOFF_S``), at most
``max_restarts`` times over the launcher's life; then it is given up (logged) and the rest stay up. A restarted
service that does not report READY within its ``ready_timeout_s`` is killed and counts as a failed run. When no
service is left running the launcher exits 1.

Shutdown (SIGINT or SIGTERM), within ``SHUTDOWN_BOUND_S`` in all:
1. the planner (no new targets);
2. every arm commander at once (their shutdown stops the arm and waits until it is at rest; exit 0 confirms it);
3. the rest in reverse start order (sim_world, which hosts the simulated arms, last).
Each gets SIGINT and up to ``STOP_WAIT_S`` (``ARM_STOP_WAIT_S`` for an arm commander; less when the overall
budget runs short) to exit, then SIGKILL of its process group; after it exits, its group is swept with SIGKILL so
that no process it started stays behind. Once less than ``KILL_WAIT_S + OUTPUT_DRAIN_S`` of the budget is left,
the remaining services are killed together.
Each step is logged as ``stopping NAME`` / ``stopped NAME (...)``; an arm commander's line says ``(arm stopped)``
when it exited 0 and ``(arm stop NOT confirmed)`` otherwise.

Recording and live view. ``--record PATH.mcap`` and ``--view [--view-port P]`` add the ``recorder`` service
(``services/recorder.py``): it starts first and stops last, so the file holds every service's start and shutdown,
and it is supervised like the others (a restarted recorder writes ``PATH.restartN.mcap``).

A config with CURVE keys whose secret key file its group or others may read is refused before anything starts
(exit 2, naming the file).

Split across hosts. ``--host NAME`` starts only the services of the config's ``[hosts.NAME]`` (in start order),
reads the config as that host (its run_dir; ``config.on_host``) and passes ``HYDROSOFT_HOST=NAME`` to every
service, so that each reads its own host's services over ipc and the other host's over CURVE tcp. Run one
launcher per host with the same config.

Exit codes: 0 after a requested stop, 1 when the launch failed or no service was left running, 2 for a bad config
or ``--only`` name.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import ctypes
import fcntl
import os
import signal
import stat
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO

from hydrosoft.services.bus.sockets import BusConfigError, check_secret_key_file
from hydrosoft.services.bus.config import HOST_ENV, ConfigError, ServiceConfig, StackConfig, load_config
from hydrosoft.services.bus.runtime import AWAIT_ARMS_ENV, INSTANCE_ENV, RESTARTS_ENV, new_instance_id

#: The package holding the service modules.
SERVICE_PACKAGE = "hydrosoft.services"
#: Environment variable naming one module to run for every service instead (tests run fake services with it).
SERVICE_MODULE_ENV = "HYDROSOFT_SERVICE_MODULE"
#: Per service, the longest wait after SIGINT before SIGKILL of its group, s. Above the runtime's shutdown bound
#: (``RuntimeConfig.shutdown_timeout_s``, 2 s) plus the interpreter's exit.
STOP_WAIT_S = 3.0
#: The same for an arm commander, s: its stop-and-confirm took 2.6 s on a loaded 2-core machine, and a SIGKILL
#: there leaves the arm's stop unconfirmed.
ARM_STOP_WAIT_S = 4.0
#: The longest wait for a process to vanish after SIGKILL, s.
KILL_WAIT_S = 0.5
#: The whole shutdown, every SIGKILL included, s; the systemd unit's TimeoutStopSec lies above it.
SHUTDOWN_BOUND_S = 8.5
#: How long a stopped service's last output may take to arrive, s.
OUTPUT_DRAIN_S = 0.5
#: Longest backoff between restarts, s.
MAX_BACKOFF_S = 30.0
#: A child's output line longer than this is cut and echoed in pieces, bytes.
MAX_LINE_BYTES = 64 * 1024
#: Longest ipc:// socket path (sun_path holds 108 bytes with its terminating NUL).
IPC_PATH_MAX_BYTES = 107
#: The lock file in run_dir that a running launcher holds.
LOCK_FILE = "launcher.lock"
#: Prefix of the launcher's own log lines.
LAUNCHER_TAG = "[launcher]"
#: Linux prctl option: the signal a process gets when its parent dies.
_PR_SET_PDEATHSIG = 1

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_USAGE = 2

CommandFor = Callable[[str, str], list[str]]
#: The name of the recorder service that ``--record`` and ``--view`` add.
RECORDER = "recorder"
#: The planner service (``start_order``).
PLANNER = "planner"
#: The services whose start the next ones do not wait for: the launcher starts the next service at once and waits for
#: these ones' READY at the end (``start_order``).
STARTS_ALONGSIDE = frozenset({PLANNER})


class LaunchError(Exception):
    """The stack cannot be (or stay) launched; the message names the service, path or key."""


# --- plain functions ---------------------------------------------------------------------------------------------


def module_for(name: str) -> str:
    """The service module of service ``name``: the part before the first ``-`` (``ft_reader-left`` -> ``ft_reader``)."""
    return name.partition("-")[0]


def command_for(name: str, config_path: str) -> list[str]:
    """The command line of service ``name``: ``python -m hydrosoft.services.MODULE CONFIG --name NAME``, or the
    module named by ``$HYDROSOFT_SERVICE_MODULE`` for every service when that is set."""
    module = os.environ.get(SERVICE_MODULE_ENV) or f"{SERVICE_PACKAGE}.{module_for(name)}"
    return [sys.executable, "-m", module, config_path, "--name", name]


@dataclass(frozen=True)
class RecorderLaunch:
    """What the recorder service of a launch does: record to ``path`` (None: not), serve the live view (``view``) on
    ``view_port`` (None: the recorder's default)."""

    path: Path | None = None
    view: bool = False
    view_port: int | None = None

    @property
    def wanted(self) -> bool:
        """Whether the launch runs the recorder at all."""
        return self.path is not None or self.view

    def command(self, config_path: str) -> list[str]:
        """The recorder's command line (always the real recorder, also when ``$HYDROSOFT_SERVICE_MODULE`` is set)."""
        command = [sys.executable, "-m", f"{SERVICE_PACKAGE}.{RECORDER}", config_path, "--name", RECORDER]
        if self.path is not None:
            command += ["--record", str(self.path)]
        if self.view:
            command += ["--view"] + ([] if self.view_port is None else ["--view-port", str(self.view_port)])
        return command

    def with_recorder(self, command: CommandFor) -> CommandFor:
        """``command``, with the recorder's command line for the service ``RECORDER``."""
        return lambda name, config_path: self.command(config_path) if name == RECORDER else command(name, config_path)


def select_services(config: StackConfig, only: str | None) -> list[str]:
    """The services to run, in start order: all of this host's ``config.local_services()``, or those named in
    ``only`` (comma separated). Raises LaunchError naming an unknown name."""
    names = config.local_services()
    if not only:
        return names
    wanted = [part.strip() for part in only.split(",") if part.strip()]
    unknown = [name for name in wanted if name not in names]
    if unknown or not wanted:
        raise LaunchError(f"--only {only!r}: no such service {', '.join(unknown) or '(empty list)'}; "
                          f"the services are {', '.join(names)}")
    return [name for name in names if name in wanted]


def start_order(names: Sequence[str]) -> list[str]:
    """The order the launcher starts the services ``names`` (given in ``config.service_names()`` order) in: that
    order, but the planner first (after the recorder, which records every start). Its start-up is the longest (its
    imports, its model, its solver worker processes, its compiled step) and needs no other service, so it runs while
    the others start (``STARTS_ALONGSIDE``). It takes no goal before the arms' owners run: it serves its client API
    and reports ready only once every arm commander the launch starts has published its state
    (``$HYDROSOFT_AWAIT_ARMS``, ``awaited_arms``)."""
    if PLANNER not in names:
        return list(names)
    rest = [name for name in names if name != PLANNER]
    at = 1 if rest[:1] == [RECORDER] else 0
    return rest[:at] + [PLANNER] + rest[at:]


def awaited_arms(names: Sequence[str]) -> list[str]:
    """The arms whose commanders are among ``names``: what a planner started before them waits for
    (``$HYDROSOFT_AWAIT_ARMS``)."""
    return [name.partition("-")[2] for name in names if module_for(name) == "arm_commander"]


def stop_phases(names: Sequence[str]) -> list[list[str]]:
    """The shutdown order of services started in the order ``names``: the planner, then every arm commander
    (stopped together), then each of the rest alone in reverse start order. Empty phases are left out."""
    planner = [name for name in names if name == "planner"]
    arms = [name for name in names if module_for(name) == "arm_commander"]
    rest = [[name] for name in reversed(names) if name not in planner and name not in arms]
    return [phase for phase in (planner, arms) if phase] + rest


@dataclass(frozen=True)
class RestartDecision:
    """Whether to start an exited service again, after how long (s), and why (for the log)."""

    restart: bool
    delay_s: float
    reason: str


def restart_decision(policy: ServiceConfig, returncode: int, restarts: int) -> RestartDecision:
    """What to do about a service that exited with ``returncode`` (negative: killed by that signal) after
    ``restarts`` restarts, under ``policy``."""
    if policy.restart == "never":
        return RestartDecision(False, 0.0, "restart policy is never")
    if policy.restart == "on-failure" and returncode == 0:
        return RestartDecision(False, 0.0, "it exited cleanly and the restart policy is on-failure")
    if restarts >= policy.max_restarts:
        return RestartDecision(False, 0.0, f"gave up after {restarts} restarts (max_restarts {policy.max_restarts})")
    delay_s = min(policy.backoff_s * 2**restarts, MAX_BACKOFF_S)
    return RestartDecision(True, delay_s, f"restart {restarts + 1} of {policy.max_restarts} in {delay_s:.2f} s")


def describe_exit(returncode: int | None) -> str:
    """``exit 1``, ``killed by SIGKILL`` or ``running``."""
    if returncode is None:
        return "running"
    if returncode < 0:
        try:
            return f"killed by {signal.Signals(-returncode).name}"
        except ValueError:
            return f"killed by signal {-returncode}"
    return f"exit {returncode}"


def ready_pid(line: str, name: str) -> int | None:
    """The pid in a ``READY NAME PID`` line of service ``name``, or None for any other line."""
    parts = line.split()
    if len(parts) == 3 and parts[0] == "READY" and parts[1] == name and parts[2].isdigit():
        return int(parts[2])
    return None


def ipc_paths(config: StackConfig, names: Sequence[str]) -> list[Path]:
    """The socket files of every ipc:// endpoint the services ``names`` bind."""
    endpoints = [config.endpoint(name, kind) for name in names for kind in ("data", "status")]
    if "planner" in names:
        endpoints.append(config.endpoint("planner", "cmd"))
    return [Path(endpoint.removeprefix("ipc://")) for endpoint in endpoints if endpoint.startswith("ipc://")]


def check_ipc_paths(paths: Sequence[Path]) -> None:
    """Raise LaunchError for a socket path too long for a Unix socket (the service would fail to bind it)."""
    for path in paths:
        if len(os.fsencode(path)) > IPC_PATH_MAX_BYTES:
            raise LaunchError(f"ipc socket path {path} is {len(os.fsencode(path))} bytes, longer than the "
                              f"{IPC_PATH_MAX_BYTES} a Unix socket allows: choose a shorter run_dir")


def remove_stale_sockets(paths: Sequence[Path]) -> list[Path]:
    """Remove those of ``paths`` that are socket files left by an earlier run (call only while holding the run
    directory's lock); return the removed ones. Anything that is not a socket is left alone."""
    removed = []
    for path in paths:
        try:
            if stat.S_ISSOCK(path.lstat().st_mode):
                path.unlink()
                removed.append(path)
        except FileNotFoundError:
            continue
    return removed


def lock_run_dir(run_dir: Path) -> IO[str]:
    """Create ``run_dir`` and take its launcher lock (``run_dir/launcher.lock``, holding this pid); keep the
    returned file open for as long as the stack runs. Raises LaunchError when another launcher holds it."""
    run_dir.mkdir(parents=True, exist_ok=True)
    lock = open(run_dir / LOCK_FILE, "a+")  # noqa: SIM115 - held open for the launcher's life
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        lock.seek(0)
        holder = lock.read().strip() or "unknown"
        lock.close()
        raise LaunchError(f"another launcher (pid {holder}) is running with run_dir {run_dir}; stop it first") from None
    lock.seek(0)
    lock.truncate()
    lock.write(f"{os.getpid()}\n")
    lock.flush()
    return lock


# --- one service process -----------------------------------------------------------------------------------------


class LogSink:
    """Where lines go: stdout (``[NAME] line``, ``[launcher] text``), and with a log directory also
    ``LOG_DIR/NAME.log`` and ``LOG_DIR/launcher.log`` (appended, unprefixed)."""

    def __init__(self, log_dir: Path | None = None) -> None:
        self._log_dir = log_dir
        self._files: dict[str, IO[str]] = {}
        if log_dir is not None:
            log_dir.mkdir(parents=True, exist_ok=True)

    def service(self, name: str, line: str) -> None:
        """One output line of service ``name``."""
        print(f"[{name}] {line}", flush=True)
        self._to_file(name, line)

    def launcher(self, text: str) -> None:
        """One line of the launcher's own log."""
        print(f"{LAUNCHER_TAG} {text}", flush=True)
        self._to_file("launcher", text)

    def _to_file(self, name: str, line: str) -> None:
        if self._log_dir is None:
            return
        if name not in self._files:
            self._files[name] = open(self._log_dir / f"{name}.log", "a", buffering=1)  # noqa: SIM115 - kept open
        self._files[name].write(line + "\n")

    def close(self) -> None:
        for file in self._files.values():
            file.close()
        self._files.clear()


class _OutputProtocol(asyncio.SubprocessProtocol):
    """Splits a child's output into lines and notes its exit. (``asyncio.subprocess.Process.wait`` would also wait
    until every holder of the pipe closed it, e.g. a grandchild; ``exited`` is set when the child itself ends.)"""

    def __init__(self, on_line: Callable[[str], None]) -> None:
        self._on_line = on_line
        self._buffer = bytearray()
        self.exited = asyncio.Event()
        self.closed = asyncio.Event()

    def pipe_data_received(self, fd: int, data: bytes) -> None:
        self._buffer += data
        while True:
            end = self._buffer.find(b"\n")
            if end < 0 and len(self._buffer) < MAX_LINE_BYTES:
                return
            cut = end if 0 <= end < MAX_LINE_BYTES else MAX_LINE_BYTES
            self._on_line(self._buffer[:cut].decode(errors="replace").rstrip("\r"))
            del self._buffer[:cut + 1 if cut == end else cut]

    def pipe_connection_lost(self, fd: int, exc: Exception | None) -> None:
        if self._buffer:
            self._on_line(self._buffer.decode(errors="replace"))
            self._buffer.clear()

    def process_exited(self) -> None:
        self.exited.set()

    def connection_lost(self, exc: Exception | None) -> None:
        self.closed.set()


def die_with_parent(parent_pid: int) -> Callable[[], None] | None:
    """A ``preexec_fn`` that makes the child receive SIGTERM when its parent ``parent_pid`` (the launcher, a benchmark
    that launched a stack) dies, even by SIGKILL (Linux), or None elsewhere."""
    if not sys.platform.startswith("linux"):
        return None
    libc = ctypes.CDLL(None, use_errno=True)

    def preexec() -> None:
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)
        if os.getppid() != parent_pid:  # the parent died before prctl took effect
            os.kill(os.getpid(), signal.SIGTERM)

    return preexec


class ServiceProcess:
    """One run of one service: its process (leader of its own process group), its output and its readiness."""

    def __init__(self, name: str, transport: asyncio.SubprocessTransport, protocol: _OutputProtocol,
                 ready: asyncio.Event) -> None:
        self.name = name
        self.pid = transport.get_pid()
        self.started_ns = time.monotonic_ns()
        self._transport = transport
        self._protocol = protocol
        self._ready = ready

    @classmethod
    async def start(cls, name: str, command: Sequence[str], env: dict[str, str], sink: LogSink) -> ServiceProcess:
        """Start ``command`` in a new session; its output lines go to ``sink`` as service ``name``."""
        ready = asyncio.Event()

        def on_line(line: str) -> None:
            if ready_pid(line, name) is not None:
                ready.set()
            sink.service(name, line)

        loop = asyncio.get_running_loop()
        transport, protocol = await loop.subprocess_exec(
            lambda: _OutputProtocol(on_line), *command, stdin=asyncio.subprocess.DEVNULL,
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.STDOUT, env=env, start_new_session=True,
            preexec_fn=die_with_parent(os.getpid()))
        return cls(name, transport, protocol, ready)

    @property
    def returncode(self) -> int | None:
        """The exit code (negative: the signal that killed it), or None while it runs."""
        return self._transport.get_returncode()

    async def wait_exit(self, timeout_s: float | None = None) -> bool:
        """Wait until the process exited (at most ``timeout_s`` s); whether it did."""
        try:
            await asyncio.wait_for(self._protocol.exited.wait(), timeout_s)
        except TimeoutError:
            return False
        return True

    async def wait_ready(self, timeout_s: float) -> None:
        """Wait for its ``READY`` line. Raises LaunchError naming the service when it exits first or stays silent
        for ``timeout_s`` s."""
        ready = asyncio.ensure_future(self._ready.wait())
        exited = asyncio.ensure_future(self._protocol.exited.wait())
        try:
            await asyncio.wait({ready, exited}, timeout=timeout_s, return_when=asyncio.FIRST_COMPLETED)
        finally:
            ready.cancel()
            exited.cancel()
        if self._ready.is_set():
            return
        if self.returncode is not None:
            raise LaunchError(f"{self.name} ended ({describe_exit(self.returncode)}) before it reported READY")
        raise LaunchError(f"{self.name} did not report READY within {timeout_s:g} s (services.{self.name}."
                          "ready_timeout_s)")

    def signal_group(self, sig: signal.Signals) -> bool:
        """Send ``sig`` to the service's process group; False when no process is left in it."""
        try:
            os.killpg(self.pid, sig)
        except ProcessLookupError:
            return False
        return True

    async def stop(self, wait_s: float) -> str:
        """SIGINT, up to ``wait_s`` s for the exit, then SIGKILL of the group; then sweep the group and release
        the pipes. Returns how it ended, for the log (``exit 0``, ``SIGKILL after 3.0 s, killed by SIGKILL``)."""
        how = ""
        if self.returncode is None:
            self.signal_group(signal.SIGINT)
            if not await self.wait_exit(max(wait_s, 0.0)):
                how = f"SIGKILL after {max(wait_s, 0.0):.1f} s, "
                self.signal_group(signal.SIGKILL)
                await self.wait_exit(KILL_WAIT_S)
        await self.release()
        return how + describe_exit(self.returncode)

    async def release(self) -> None:
        """After the exit: SIGKILL whatever is left in its process group, let the last output arrive, close the
        pipes."""
        self.signal_group(signal.SIGKILL)
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._protocol.closed.wait(), OUTPUT_DRAIN_S)
        self._transport.close()


# --- the launcher ------------------------------------------------------------------------------------------------


class Launcher:
    """Starts, supervises and stops the services ``names`` of ``config`` (see the module docstring)."""

    def __init__(self, config: StackConfig, config_path: str, names: Sequence[str], sink: LogSink,
                 command: CommandFor = command_for) -> None:
        self.config = config
        self.config_path = config_path
        self.names = list(names)
        self.sink = sink
        self.command = command
        self.processes: dict[str, ServiceProcess] = {}
        self.restarts = dict.fromkeys(self.names, 0)
        self.given_up: set[str] = set()
        self.stopping = asyncio.Event()
        self.none_left = asyncio.Event()
        self.instance = new_instance_id()
        self._keepers: dict[str, asyncio.Task[None]] = {}

    def log(self, text: str) -> None:
        self.sink.launcher(text)

    async def _start(self, name: str) -> ServiceProcess:
        env = {**os.environ, RESTARTS_ENV: str(self.restarts[name]), INSTANCE_ENV: self.instance}
        if self.config.host is not None:
            env[HOST_ENV] = self.config.host
        if name == PLANNER and self.restarts[name] == 0:  # started before the arm commanders (``start_order``)
            env[AWAIT_ARMS_ENV] = ",".join(awaited_arms(self.names))
        process = await ServiceProcess.start(name, self.command(name, self.config_path), env, self.sink)
        self.processes[name] = process
        return process

    async def start_all(self) -> None:
        """Start every service in ``start_order``, each after the previous one is READY, but for those in
        ``STARTS_ALONGSIDE``, whose READY is waited for beside the next services' starts; then supervise them.
        Raises LaunchError naming the first service that did not get ready."""
        self.log(f"launch instance {self.instance}")
        alongside: list[asyncio.Task[None]] = []
        try:
            for name in start_order(self.names):
                if self.stopping.is_set():
                    return
                process = await self._start(name)
                if name in STARTS_ALONGSIDE:
                    self.log(f"{name} started (pid {process.pid}); the next services start while it gets ready")
                    alongside.append(asyncio.create_task(self._ready(name, process), name=f"ready {name}"))
                else:
                    await self._ready(name, process)
            await asyncio.gather(*alongside)
        finally:
            for task in alongside:
                task.cancel()
            await asyncio.gather(*alongside, return_exceptions=True)
        if not self.stopping.is_set():
            self.log(f"stack ready: {', '.join(self.names)}")

    async def _ready(self, name: str, process: ServiceProcess) -> None:
        """Wait for ``name``'s READY, log it and supervise it from then on (raises LaunchError when it fails)."""
        await process.wait_ready(self.config.service(name).ready_timeout_s)
        self.log(f"{name} ready (pid {process.pid})")
        self._keepers[name] = asyncio.create_task(self._keep(name), name=f"keep {name}")

    async def _keep(self, name: str) -> None:
        """Restart ``name`` by its policy whenever it exits, until the stack stops or it is given up."""
        policy = self.config.service(name)
        while True:
            process = self.processes[name]
            await process.wait_exit()
            if self.stopping.is_set():
                return
            decision = restart_decision(policy, process.returncode, self.restarts[name])
            await process.release()
            if not decision.restart:
                self.log(f"gave up on {name}: it ended ({describe_exit(process.returncode)}); {decision.reason}; "
                         "the rest stay up")
                self._note_gone(name)
                return
            self.log(f"{name} ended ({describe_exit(process.returncode)}); {decision.reason}")
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self.stopping.wait(), decision.delay_s)
                return  # the stack is stopping
            self.restarts[name] += 1
            process = await self._start(name)
            if self.stopping.is_set():
                return  # the shutdown may have passed this service already: its final sweep stops this run
            try:
                await process.wait_ready(policy.ready_timeout_s)
            except LaunchError as err:
                if not self.stopping.is_set():
                    self.log(str(err))
                    process.signal_group(signal.SIGKILL)  # a silent run is a failed run; the loop decides again
                continue
            self.log(f"{name} ready again (pid {process.pid}, restart {self.restarts[name]})")

    def _note_gone(self, name: str) -> None:
        self.given_up.add(name)
        if len(self.given_up) == len(self.names):
            self.log("no service is left running")
            self.none_left.set()

    async def shut_down(self) -> None:
        """Stop every running service in ``stop_phases`` order within ``SHUTDOWN_BOUND_S``."""
        self.stopping.set()
        deadline_s = time.monotonic() + SHUTDOWN_BOUND_S
        phases = stop_phases(self.names)
        for index, phase in enumerate(phases):
            if deadline_s - time.monotonic() <= KILL_WAIT_S + OUTPUT_DRAIN_S:
                self.log("out of shutdown time: killing the remaining services together")
                phase = [name for later in phases[index:] for name in later]
                await asyncio.gather(*(self._stop_one(name, deadline_s) for name in phase))
                break
            await asyncio.gather(*(self._stop_one(name, deadline_s) for name in phase))
        if self._keepers:
            await asyncio.wait(self._keepers.values(), timeout=KILL_WAIT_S)
        for process in self.processes.values():  # a run a keeper started while the shutdown passed it
            if process.returncode is None:
                self.log(f"killing {process.name} (pid {process.pid}), started during the shutdown")
                process.signal_group(signal.SIGKILL)
                await process.wait_exit(KILL_WAIT_S)
            await process.release()

    async def _stop_one(self, name: str, deadline_s: float) -> None:
        process = self.processes.get(name)
        if process is None:
            return
        if process.returncode is not None:
            await process.release()
            self.log(f"{name} was not running ({describe_exit(process.returncode)})")
            return
        self.log(f"stopping {name} (pid {process.pid})")
        limit_s = ARM_STOP_WAIT_S if module_for(name) == "arm_commander" else STOP_WAIT_S
        wait_s = min(limit_s, deadline_s - time.monotonic() - KILL_WAIT_S - OUTPUT_DRAIN_S)
        how = await process.stop(wait_s)
        note = ""
        if module_for(name) == "arm_commander":
            note = " (arm stopped)" if process.returncode == 0 else " (arm stop NOT confirmed)"
        self.log(f"stopped {name}{note}: {how}")


async def serve_stack(config: StackConfig, config_path: str, names: Sequence[str], sink: LogSink,
                      command: CommandFor = command_for) -> int:
    """Launch ``names`` of ``config``, run until SIGINT/SIGTERM (or until no service is left), shut down; the exit
    code. Expects the run directory to be locked already."""
    launcher = Launcher(config, config_path, names, sink, command)
    loop = asyncio.get_running_loop()

    def on_signal(sig: signal.Signals) -> None:
        if launcher.stopping.is_set():
            launcher.log(f"{sig.name} again; the shutdown is under way (at most {SHUTDOWN_BOUND_S:g} s)")
            return
        launcher.log(f"{sig.name} received: stopping the stack")
        launcher.stopping.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, on_signal, sig)
    code = EXIT_OK
    try:
        starting = asyncio.create_task(launcher.start_all())
        stop = asyncio.create_task(launcher.stopping.wait())
        await asyncio.wait({starting, stop}, return_when=asyncio.FIRST_COMPLETED)
        if not starting.done():
            starting.cancel()
            await asyncio.gather(starting, return_exceptions=True)
        elif starting.exception() is not None:
            launcher.log(f"launch failed: {starting.exception()}")
            code = EXIT_FAILED
        else:
            none_left = asyncio.create_task(launcher.none_left.wait())
            await asyncio.wait({stop, none_left}, return_when=asyncio.FIRST_COMPLETED)
            none_left.cancel()
            if launcher.none_left.is_set():
                code = EXIT_FAILED
        stop.cancel()
    finally:
        tic_s = time.monotonic()
        await launcher.shut_down()
        launcher.log(f"stack stopped in {time.monotonic() - tic_s:.1f} s")
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)
    return code


def launch(config_path: str | Path, *, only: str | None = None, log_dir: str | Path | None = None,
           command: CommandFor = command_for, recorder: RecorderLaunch = RecorderLaunch(),
           host: str | None = None) -> int:
    """Run the stack of the config file ``config_path`` until SIGINT/SIGTERM (see the module docstring); the exit
    code (0 stopped on request, 1 launch failed or nothing left running, 2 bad config or ``only``).
    ``only``: comma-separated service names to run instead of all. ``log_dir``: also write each service's output
    to ``LOG_DIR/NAME.log``. ``command``: the command line of a service (name, config path), for tests.
    ``recorder``: add the recorder service (``--record``, ``--view``). ``host``: run that host's services only
    (``--host``; default ``$HYDROSOFT_HOST``)."""
    sink = LogSink(Path(log_dir) if log_dir is not None else None)
    try:
        config = load_config(config_path, host)
        if config.curve is not None:
            check_secret_key_file(Path(config.curve.secret_key_file))
        names = select_services(config, only)
        if recorder.wanted:
            names = [RECORDER, *names]
            command = recorder.with_recorder(command)
        sockets = ipc_paths(config, names)
        check_ipc_paths(sockets)
    except (ConfigError, LaunchError, BusConfigError) as err:
        print(f"hydrosoft-stack launch: {err}", file=sys.stderr, flush=True)
        return EXIT_USAGE
    try:
        lock = lock_run_dir(Path(config.run_dir))
    except LaunchError as err:
        print(f"hydrosoft-stack launch: {err}", file=sys.stderr, flush=True)
        return EXIT_FAILED
    try:
        removed = remove_stale_sockets(sockets)
        if removed:
            sink.launcher(f"removed {len(removed)} stale ipc socket file(s) in {config.run_dir}")
        if SERVICE_MODULE_ENV in os.environ:
            sink.launcher(f"${SERVICE_MODULE_ENV} is set: every service runs as {os.environ[SERVICE_MODULE_ENV]}")
        return asyncio.run(serve_stack(config, str(config_path), names, sink, command))
    finally:
        lock.close()
        sink.close()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments: CONFIG [--only NAMES] [--host NAME] [--log-dir DIR] [--record PATH.mcap] [--view [--view-port P]]."""
    parser.add_argument("config", help="the stack's TOML config (deploy/sim.toml, deploy/lab.toml)")
    parser.add_argument("--only", default=None, metavar="NAMES",
                        help="comma-separated services to run (e.g. sim_world,arm_commander-bubble); default all")
    parser.add_argument("--host", default=None, metavar="NAME",
                        help="run only the services of the config's [hosts.NAME] (a stack split across hosts)")
    parser.add_argument("--log-dir", default=None, metavar="DIR",
                        help="also append each service's output to DIR/NAME.log (and the launcher's to "
                        "DIR/launcher.log)")
    parser.add_argument("--record", type=Path, default=None, metavar="PATH.mcap",
                        help="record every bus message to this MCAP file (the recorder service starts first)")
    parser.add_argument("--view", action="store_true",
                        help="serve the live view over Foxglove's WebSocket on 127.0.0.1 (the recorder service)")
    parser.add_argument("--view-port", type=int, default=None, metavar="P",
                        help="the live view's port (default 8765)")


def run(args: argparse.Namespace) -> int:
    """Run ``hydrosoft-stack launch``; the exit code."""
    recorder = RecorderLaunch(args.record.resolve() if args.record is not None else None, args.view, args.view_port)
    return launch(args.config, only=args.only, log_dir=args.log_dir, recorder=recorder, host=args.host)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m hydrosoft.services.commands.launch",
                                     description=__doc__.split("\n", 1)[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
