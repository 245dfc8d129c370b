"""A simulated UR e-Series controller that the real ``ur_rtde`` 1.6.5 client connects to, on a loopback address.

``SimulatedURController`` serves, on ``config.host`` (127.0.0.N):

- RTDE on 30004 (``rtde_protocol``): ``V``, ``v``, ``O`` (``NOT_FOUND`` for unknown names), ``I`` (``IN_USE`` when
  another connection owns a field; recipe ids count from 1 per connection), ``S``, ``P``, ``U`` both ways; outputs
  stream at the rate each client asked for, capped at ``max_output_hz``;
- the dashboard on 29999 (``dashboard``);
- the script port on 30003: ur_rtde's control program starts the emulated script (``control_script``);
- the simulator's own JSON-lines endpoint on ``sim_control_port`` for fault knobs and inspection, which stays up
  while the controller is dropped.

Concurrency: one asyncio event loop runs everything (the sockets and a tick task at ``tick_hz``); the state lives in
``URControllerModel`` and is touched only from that loop. Never run a ur_rtde client in the same process: its
constructors hold the GIL while they wait for the controller, so the simulator could not answer them. Tests start
the simulator as a subprocess (``python -m hydrosoft.drivers.ur.simulator``).

Hooks for another simulator in the same process and loop (``sim_world``): ``tcp_pose()``/``tcp_twist()`` read the
TCP, ``add_tick_listener(fn)`` calls ``fn(now_ns, pose (7,), twist (6,))`` after every tick, ``impose_tcp_pose(pose)``
overwrites the TCP pose (the active command carries on from there). Call them from the simulator's loop.

Fault knobs, each counted in ``faults`` (injected) and mirrored on the control endpoint: ``stall_stream(duration_s)``
(RTDE outputs stop, connections stay open), ``stall_control_stream(duration_s)`` (only the outputs to connections
that own input registers stop: the control client falls behind the receive client), ``trigger_protective_stop()``,
``trigger_safeguard_stop()``, ``trigger_emergency_stop()`` (the program ends, the arm powers off),
``release_safety_stop()`` (sim only: a person resets the safeguard or emergency stop), ``stop_script()`` (the
program ends, as a pendant stop), ``drop(duration_s)`` (every socket closed, connections refused, then the
controller comes back). The dashboard's ``stop`` and ``pause`` act as on a real controller. ``counters``
``servol_received`` counts the servoL packages that reached the controller, whether or not it acted on them.

Control endpoint: one JSON object per line, one reply line ``{"ok": true, ...}`` or ``{"ok": false, "error": ...}``.
Requests: ``{"op": "state"}`` (pose, twist, runtime_state, protective_stop, watchdog_period_s, faults, counters),
``{"op": "stall", "duration_s": s}``, ``{"op": "stall_control", "duration_s": s}``, ``{"op": "protective_stop"}``,
``{"op": "safeguard_stop"}``, ``{"op": "emergency_stop"}``, ``{"op": "release_safety_stop"}``,
``{"op": "stop_script"}``, ``{"op": "drop", "duration_s": s}``, ``{"op": "impose_pose", "pose": [7 floats]}``.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import dataclasses
import json
import logging
import math
import signal
import sys
import time
from collections import Counter
from functools import partial
from typing import Any

import numpy as np

from hydrosoft.drivers.ur import rtde_protocol as rtde
from hydrosoft.drivers.ur.config import DASHBOARD_PORT, RTDE_PORT, SCRIPT_PORT, URSimulatorConfig
from hydrosoft.drivers.ur.control_script import split_scripts
from hydrosoft.drivers.ur.controller import ControllerIdentity, TickListener, URControllerModel
from hydrosoft.drivers.ur.dashboard import BANNER, QUIT_REPLY, dashboard_reply
from hydrosoft.drivers.ur.pose import check_pose, ur_to_pose
from hydrosoft.drivers.ur.rtde_session import RtdeSession

log = logging.getLogger(__name__)

READ_CHUNK_BYTES = 65536
MAX_LINE_BYTES = 1 << 16  # longest dashboard or control line; a longer one closes the connection
MAX_PROGRAM_BYTES = 1 << 20  # a script-port upload longer than this is dropped
TICK_CATCH_UP_LIMIT_NS = 50_000_000  # further behind than this, the tick schedule restarts from now
RELISTEN_RETRY_S = 0.1  # after a drop, how often to retry binding the ports
READY_LINE = "UR simulator ready"


class SimulatedURController:
    """The simulated controller; ``await start()`` to serve, ``await stop()`` to end (or ``async with``).

    Args:
        config: the simulator settings (``URSimulatorConfig``); ``host`` and ``tcp_pose`` override its fields.
    """

    def __init__(
        self, config: URSimulatorConfig | None = None, *, host: str | None = None, tcp_pose: np.ndarray | None = None
    ) -> None:
        config = config or URSimulatorConfig()
        overrides: dict[str, Any] = {}
        if host is not None:
            overrides["host"] = host
        if tcp_pose is not None:
            overrides["tcp_pose"] = np.asarray(tcp_pose, dtype=np.float64)
        if overrides:
            config = dataclasses.replace(config, **overrides)
        self.config = config
        self.model = URControllerModel(
            check_pose(config.tcp_pose),
            limits=config.limits,
            identity=ControllerIdentity(),
            remote_control=config.remote_control,
            stop_decel_m_s2=config.stop_decel_m_s2,
            unlock_delay_s=config.unlock_delay_s,
            now_ns=time.monotonic_ns(),
        )
        self.counters: Counter = self.model.counters
        self.faults: Counter = Counter()
        self.input_owners: dict[str, int] = {}
        self._sessions: dict[int, tuple[RtdeSession, asyncio.StreamWriter]] = {}
        self._writers: set[asyncio.StreamWriter] = set()
        self._servers: list[asyncio.base_events.Server] = []
        self._control_server: asyncio.base_events.Server | None = None
        self._tasks: set[asyncio.Task] = set()
        self._tick_task: asyncio.Task | None = None
        self._next_session_id = 1
        self._stall_until_ns = 0
        self._stall_control_until_ns = 0
        self._dropped = False

    # -- life cycle ------------------------------------------------------------------------------------------

    async def start(self) -> None:
        """Bind RTDE, dashboard, script and control ports on ``config.host`` and start ticking."""
        await self._listen()
        self._control_server = await asyncio.start_server(
            self._serve_control, self.config.host, self.config.sim_control_port, reuse_address=True,
            limit=MAX_LINE_BYTES,
        )
        self._tick_task = asyncio.create_task(self._run_ticks(), name="ur-sim-ticks")

    async def stop(self) -> None:
        """Close every socket and stop ticking."""
        if self._tick_task is not None:
            self._tick_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._tick_task
            self._tick_task = None
        if self._control_server is not None:
            self._control_server.close()
        await self._unlisten()
        for task in list(self._tasks):
            task.cancel()
        if self._tasks:
            await asyncio.gather(*self._tasks, return_exceptions=True)

    async def __aenter__(self) -> SimulatedURController:
        await self.start()
        return self

    async def __aexit__(self, *exc_info: object) -> None:
        await self.stop()

    async def _listen(self) -> None:
        """Bind the three controller ports; on failure none stays bound and the OSError propagates."""
        host = self.config.host
        for handler, port in ((self._serve_rtde, RTDE_PORT), (self._serve_dashboard, DASHBOARD_PORT),
                              (self._serve_script, SCRIPT_PORT)):
            try:
                self._servers.append(
                    await asyncio.start_server(handler, host, port, reuse_address=True, limit=MAX_LINE_BYTES)
                )
            except OSError:
                await self._unlisten()
                raise

    async def _unlisten(self) -> None:
        for server in self._servers:
            server.close()
        self._servers = []
        for writer in list(self._writers):
            writer.close()
        self._writers.clear()

    # -- hooks for sim_world ---------------------------------------------------------------------------------

    def tcp_pose(self) -> np.ndarray:
        """TCP pose ``(7,)`` [m, wxyz] in the robot base frame, as of the last tick."""
        return self.model.motion.pose()

    def tcp_twist(self) -> np.ndarray:
        """TCP twist ``(6,)`` [m/s, rad/s] in the base frame, as of the last tick."""
        return self.model.motion.twist()

    def impose_tcp_pose(self, pose: np.ndarray) -> None:
        """Overwrite the TCP pose ``(7,)`` [m, wxyz]; the active command continues from it."""
        self.model.motion.impose_pose(pose)

    def add_tick_listener(self, listener: TickListener) -> None:
        """Call ``listener(now_ns, pose (7,), twist (6,))`` after every controller tick."""
        self.model.add_tick_listener(listener)

    # -- fault knobs -----------------------------------------------------------------------------------------

    def stall_stream(self, duration_s: float) -> None:
        """Send no RTDE data packages for ``duration_s`` s; connections stay open and inputs are still read."""
        self.faults["stall"] += 1
        self._stall_until_ns = time.monotonic_ns() + int(duration_s * 1e9)

    def stall_control_stream(self, duration_s: float) -> None:
        """Send no RTDE data packages to connections that own input registers (ur_rtde's control client) for
        ``duration_s`` s; other streams go on. A real controller's streams reach the two clients on separate sockets
        and threads, so the control client's copy of the state can lag the receive client's by a few packages."""
        self.faults["stall_control"] += 1
        self._stall_control_until_ns = time.monotonic_ns() + int(duration_s * 1e9)

    def trigger_protective_stop(self) -> None:
        """Protective stop: the TCP stops, motion is refused until the dashboard unlocks it."""
        self.faults["protective_stop"] += 1
        self.model.trigger_protective_stop()

    def trigger_safeguard_stop(self) -> None:
        """Safeguard stop: the TCP stops, motion is refused until ``release_safety_stop``."""
        self.faults["safeguard_stop"] += 1
        self.model.trigger_safeguard_stop()

    def trigger_emergency_stop(self) -> None:
        """Emergency stop: the program ends and the arm powers off until ``release_safety_stop``."""
        self.faults["emergency_stop"] += 1
        self.model.trigger_emergency_stop()

    def release_safety_stop(self) -> None:
        """Sim only, a person's reset: clear a safeguard or emergency stop (the program stays stopped)."""
        self.model.release_safety_stop()

    def stop_script(self) -> None:
        """End the control program as a pendant stop would (runtime_state goes to STOPPED)."""
        self.faults["stop_script"] += 1
        self.model.stop_program()

    async def drop(self, duration_s: float) -> None:
        """Close every controller socket and refuse connections for ``duration_s`` s, then serve again."""
        self.faults["drop"] += 1
        self._dropped = True
        await self._unlisten()
        self._sessions.clear()
        self.input_owners.clear()
        await asyncio.sleep(duration_s)
        while True:
            try:
                await self._listen()
                break
            except OSError as exc:
                self.counters["relisten_error"] += 1
                log.warning("UR simulator cannot listen again on %s: %s", self.config.host, exc)
                await asyncio.sleep(RELISTEN_RETRY_S)
        self._dropped = False

    @property
    def streaming(self) -> bool:
        return time.monotonic_ns() >= self._stall_until_ns

    def snapshot(self) -> dict[str, Any]:
        """Inspectable state: pose (7,), twist (6,), runtime state, safety, watchdog, the output rates (Hz) the open
        RTDE sessions stream at, faults and counters."""
        model = self.model
        return {
            "pose": self.tcp_pose().tolist(),
            "twist": self.tcp_twist().tolist(),
            "runtime_state": int(model.runtime_state),
            "protective_stop": model.protective_stop,
            "safeguard_stop": model.safeguard_stop,
            "emergency_stop": model.emergency_stop,
            "watchdog_period_s": model.script.watchdog_period_s,
            "rtde_sessions": len(self._sessions),
            "output_rates_hz": sorted(1e9 / period_ns for session, _ in self._sessions.values()
                                      for _, period_ns in session.outputs),
            "dropped": self._dropped,
            "faults": dict(self.faults),
            "counters": dict(self.counters),
        }

    # -- the controller cycle ------------------------------------------------------------------------------

    async def _run_ticks(self) -> None:
        period_ns = int(1e9 / self.config.tick_hz)
        next_ns = time.monotonic_ns()
        while True:
            now_ns = time.monotonic_ns()
            self._tick(now_ns)
            next_ns += period_ns
            if now_ns - next_ns > TICK_CATCH_UP_LIMIT_NS:
                self.counters["tick_overrun"] += 1
                next_ns = now_ns + period_ns
            await asyncio.sleep(max(0.0, (next_ns - time.monotonic_ns()) / 1e9))

    def _tick(self, now_ns: int) -> None:
        try:
            self.model.tick(now_ns)
        except Exception:  # a tick listener or the model failed: count it, keep the controller alive
            self.counters["tick_error"] += 1
            log.exception("UR simulator tick failed")
        if not self.streaming:
            return
        values: dict[str, object] | None = None
        control_stalled = now_ns < self._stall_control_until_ns
        for session, writer in self._sessions.values():
            if control_stalled and session.inputs:
                continue
            if session.due(now_ns):
                if values is None:
                    values = self.model.output_values()
                session.stream(now_ns, values, writer.transport.get_write_buffer_size())

    # -- connections ---------------------------------------------------------------------------------------

    def _track(self, writer: asyncio.StreamWriter) -> bool:
        if self._dropped:
            writer.close()
            return False
        self._writers.add(writer)
        return True

    async def _serve_rtde(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if not self._track(writer):
            return
        session = RtdeSession(self._next_session_id, self.model, self.input_owners, self.counters,
                              self.config.max_output_hz, partial(_write, writer))
        self._next_session_id += 1
        self._sessions[session.session_id] = (session, writer)
        self.counters["rtde_connections"] += 1
        packets = rtde.PacketReader()
        try:
            while data := await reader.read(READ_CHUNK_BYTES):
                packets.feed(data)
                for packet in packets.packets():
                    try:
                        session.handle(packet, time.monotonic_ns())
                    except rtde.RtdeProtocolError as exc:
                        self.counters["rtde_bad_packet"] += 1
                        log.warning("RTDE session %d: %s", session.session_id, exc)
        except rtde.RtdeProtocolError as exc:  # unrecoverable framing: drop the connection
            self.counters["rtde_bad_framing"] += 1
            log.warning("RTDE session %d closed: %s", session.session_id, exc)
        except ConnectionError:
            pass
        finally:
            session.release()
            self._sessions.pop(session.session_id, None)
            self._close(writer)

    async def _serve_dashboard(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if not self._track(writer):
            return
        self.counters["dashboard_connections"] += 1
        try:
            writer.write(f"{BANNER}\n".encode())
            while line := await reader.readline():
                reply = dashboard_reply(self.model, line.decode("utf-8", errors="replace"))
                writer.write(f"{reply}\n".encode())
                await writer.drain()
                if reply == QUIT_REPLY:
                    break
        except ValueError:  # a line longer than MAX_LINE_BYTES
            self.counters["dashboard_bad_line"] += 1
        except ConnectionError:
            pass
        finally:
            self._close(writer)

    async def _serve_script(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if not self._track(writer):
            return
        self.counters["script_connections"] += 1
        buffer = ""
        try:
            while data := await reader.read(READ_CHUNK_BYTES):
                programs, buffer = split_scripts(buffer + data.decode("utf-8", errors="replace"))
                for program in programs:
                    self.model.load_program(program)
                if len(buffer) > MAX_PROGRAM_BYTES:
                    self.counters["script_too_long"] += 1
                    buffer = ""
        except ConnectionError:
            pass
        finally:
            self._close(writer)

    def _close(self, writer: asyncio.StreamWriter) -> None:
        self._writers.discard(writer)
        writer.close()

    # -- control endpoint ------------------------------------------------------------------------------------

    async def _serve_control(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while line := await reader.readline():
                reply = self._control_reply(line)
                writer.write((json.dumps(reply) + "\n").encode())
                await writer.drain()
        except ValueError:  # a line longer than MAX_LINE_BYTES
            self.counters["control_bad_request"] += 1
        except ConnectionError:
            pass
        finally:
            writer.close()

    def _control_reply(self, line: bytes) -> dict[str, Any]:
        try:
            request = json.loads(line)
            if not isinstance(request, dict):
                raise ValueError("request is not a JSON object")
            return {"ok": True, **self._control(request)}
        except (ValueError, TypeError, KeyError) as exc:
            self.counters["control_bad_request"] += 1
            return {"ok": False, "error": f"{type(exc).__name__}: {exc}"}

    def _control(self, request: dict[str, Any]) -> dict[str, Any]:
        op = request.get("op")
        if op == "state":
            return self.snapshot()
        if op == "stall":
            self.stall_stream(_duration(request))
        elif op == "stall_control":
            self.stall_control_stream(_duration(request))
        elif op == "protective_stop":
            self.trigger_protective_stop()
        elif op == "safeguard_stop":
            self.trigger_safeguard_stop()
        elif op == "emergency_stop":
            self.trigger_emergency_stop()
        elif op == "release_safety_stop":
            self.release_safety_stop()
        elif op == "stop_script":
            self.stop_script()
        elif op == "drop":
            duration_s = _duration(request)
            task = asyncio.create_task(self.drop(duration_s), name="ur-sim-drop")
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)
        elif op == "impose_pose":
            self.impose_tcp_pose(check_pose(request["pose"]))
        else:
            raise ValueError(f"unknown op {op!r}; expected state, stall, stall_control, protective_stop, "
                             "safeguard_stop, emergency_stop, release_safety_stop, stop_script, drop, impose_pose")
        return {}


def _write(writer: asyncio.StreamWriter, data: bytes) -> None:
    if not writer.is_closing():
        writer.write(data)


def _duration(request: dict[str, Any]) -> float:
    duration_s = float(request["duration_s"])
    if not (math.isfinite(duration_s) and duration_s >= 0.0):
        raise ValueError(f"duration_s must be a finite number >= 0, got {request['duration_s']!r}")
    return duration_s


# ---------------------------------------------------------------------------------------------------------------
# Command line: hydrosoft-stack simulate ur --host 127.0.0.N [--pose x,y,z,rx,ry,rz]
# ---------------------------------------------------------------------------------------------------------------


def _ur_pose_argument(text: str) -> np.ndarray:
    try:
        values = [float(v) for v in text.split(",")]
        return ur_to_pose(np.array(values))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"--pose wants x,y,z,rx,ry,rz (m, rotation vector rad): {exc}") from exc


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``hydrosoft-stack simulate ur``."""
    defaults = URSimulatorConfig()
    parser.add_argument("--host", default=defaults.host, help="loopback address to serve on (default %(default)s)")
    parser.add_argument(
        "--pose",
        type=_ur_pose_argument,
        default=None,
        help="initial TCP pose x,y,z,rx,ry,rz in the base frame (m, UR rotation vector in rad); "
        "default 0.3,-0.2,0.4,0,3.14159,0",
    )
    parser.add_argument("--tick-hz", type=float, default=defaults.tick_hz, help="controller cycle rate (Hz)")
    parser.add_argument(
        "--unlock-delay-s",
        type=float,
        default=defaults.unlock_delay_s,
        help="seconds before a protective stop can be unlocked (default %(default)s, as the real controller)",
    )
    parser.add_argument("--local-mode", action="store_true", help="answer 'false' to 'is in remote control'")
    parser.add_argument(
        "--control-port",
        type=int,
        default=defaults.sim_control_port,
        help="fault/inspection port (default %(default)s)",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log at debug level")


def run(args: argparse.Namespace) -> int:
    """Serve until SIGINT or SIGTERM; print one ready line to stdout once listening. Returns the exit code."""
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO, format="%(name)s: %(message)s")
    try:
        config = URSimulatorConfig(
            host=args.host,
            tick_hz=args.tick_hz,
            unlock_delay_s=args.unlock_delay_s,
            remote_control=not args.local_mode,
            sim_control_port=args.control_port,
            **({"tcp_pose": args.pose} if args.pose is not None else {}),
        )
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return asyncio.run(_serve_until_signalled(config))


async def _serve_until_signalled(config: URSimulatorConfig) -> int:
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for signum in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(signum, stop.set)
    sim = SimulatedURController(config)
    try:
        await sim.start()
    except OSError as exc:
        print(f"error: cannot serve on {config.host}: {exc}", file=sys.stderr)
        await sim.stop()
        return 1
    print(
        f"{READY_LINE} on {config.host}: RTDE {RTDE_PORT}, dashboard {DASHBOARD_PORT}, script {SCRIPT_PORT}, "
        f"sim control {config.sim_control_port}",
        flush=True,
    )
    await stop.wait()
    await sim.stop()
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m hydrosoft.drivers.ur.simulator", description=run.__doc__)
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
