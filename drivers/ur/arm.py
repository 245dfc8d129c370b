"""``URArm``: the ``Arm`` interface of ``drivers/base.py`` on a UR e-Series controller through ``ur_rtde`` 1.6.5.

Two ur_rtde clients per arm: ``RTDEReceiveInterface`` streams the state (timestamp, TCP pose and speed, runtime
state, safety status bits) and ``RTDEControlInterface`` uploads ur_rtde's control script and sends commands through
RTDE registers (devices.md section 3). Poses cross this edge converted between UR's ``[x, y, z, rx, ry, rz]`` and
the stack's ``(7,)`` ``[x, y, z, qw, qx, qy, qz]`` (``pose.py``), in the robot base frame.

Threads. Every ur_rtde method blocks in C++ with the GIL released, so each client gets one dedicated worker thread
(the calls of one client are serialised; the event loop never waits on them). One exception: ``servo_to`` reads the
receive client's status words on the control thread, right before its servoL, in the same hop (one hop per command
instead of two); those getters only copy the newest values under ur_rtde's state lock and never wait on the network.
The constructors and destructors differ too: they hold the GIL. Before constructing, ``connect`` checks with asyncio
that the RTDE stream flows and that the dashboard and script ports answer (``probe.py``), so a controller that is
gone or stalled fails fast without freezing the loop; a successful construction still freezes the loop for its
duration (about 5 ms for the receive client and 20-40 ms for the control client on loopback, more when a script must
be replaced). A destructor sleeps 500 ms holding the GIL, so retired clients are disconnected on their worker thread
(the sleep there does not hold the GIL) and parked in ``_RETIRED_CLIENTS`` until the interpreter exits.

Safety behaviour:
- ``connect`` arms the controller's watchdog (``setWatchdog(watchdog_min_hz)``): when no command reaches the
  controller for ``1 / watchdog_min_hz`` s (this process died or hangs) the script stops and so does the arm. While
  connected, a supervisor task kicks the watchdog whenever no other command went out within a quarter period.
- ``servo_to`` reads the state first (the status words, on the control thread, with no event-loop turn between
  the read and the command) and never commands while the stream is stale, while the controller reports a
  stop of its own (any safety stop bit, a robot mode other than RUNNING, the program not playing: named in
  ``ArmState.controller_stop`` by ``safety_status.py``): it raises ``Stale`` or ``DeviceFault`` instead.
- ``read_state`` raises ``Stale`` when the newest state is older than ``max_age_s``, its age estimated from the
  controller's RTDE timestamp against the host clock (``stream_age.py``; ur_rtde keeps returning the last values
  for about 2.5 s after the stream stops, and says nothing about when they arrived).
- When the stream closes (controller gone, or stalled for 2.5 s), the supervisor disconnects both clients and
  reconnects with doubling back-off; calls raise ``NotConnected`` meanwhile (``ArmState.link_since_ns`` tells the
  caller a reconnect happened). A stopped script or a protective stop is not undone automatically: the caller
  decides (``restart_script``; a person unlocks protective stops).
- ``close`` stops the arm (servoStop, sent before the driver counts as closed), runs ``stopScript`` (a disconnect
  alone leaves the script running) and disconnects.

``counters`` counts by name what the driver refused or detected (``stale``, ``not_connected``,
``refused_safety_stop``, ``refused_script_not_running``, ``rejected_target``, ``command_rejected``,
``command_timeout``, ``link_lost``, ``reconnects``, ``reconnect_failures``) and what it did (``servo_commands``,
``stops``, ``watchdog_kicks``, ``script_stops``, ``script_restarts``).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable, TypeVar

import numpy as np

from hydrosoft.drivers.base import ArmState
from hydrosoft.drivers.errors import DeviceFault, NotConnected, Stale
from hydrosoft.drivers.ur.config import DASHBOARD_PORT, SCRIPT_PORT, URArmConfig
from hydrosoft.drivers.ur.pose import pose_to_ur, ur_to_pose
from hydrosoft.drivers.ur.probe import error_text, probe_port, probe_rtde_stream
from hydrosoft.drivers.ur.safety_status import RuntimeState, controller_stop, safety_flags
from hydrosoft.drivers.ur.stream_age import StreamAge
from hydrosoft.drivers.ur.timer_slack import started_with_slack

try:
    import rtde_control
    import rtde_receive
except ImportError as exc:  # pragma: no cover - the dependency is installed with the package
    raise ImportError("hydrosoft.drivers.ur.arm needs the 'ur-rtde' package (pip install ur-rtde==1.6.5)") from exc

log = logging.getLogger(__name__)

T = TypeVar("T")

RECEIVE_VARIABLES = ["timestamp", "actual_TCP_pose", "actual_TCP_speed", "runtime_state", "safety_status_bits",
                     "robot_mode"]
#: The safety bits that forbid motion (``safety_status.SAFETY_STATUS_BITS``): protective, safeguard and every
#: emergency stop, violation, fault, stopped due to safety, recovery mode.
SAFETY_BIT_PROTECTIVE_STOP = 1 << 2
EMERGENCY_STOP_BITS = (1 << 5) | (1 << 6) | (1 << 7)

# Limits of the waits on the worker threads. ur_rtde's own waits are longer (a real-time command spins up to ~4 s
# for "ready", a stop up to 300 s), so these bound how long a caller waits, not how long the thread is busy.
REALTIME_CALL_TIMEOUT_S = 0.5  # servoL, kickWatchdog: normally a few hundred microseconds
SETUP_CALL_TIMEOUT_S = 5.0  # setWatchdog, reuploadScript, stopScript
STOP_MARGIN_S = 1.0  # stop() waits the longest configured stop plus this
DISCONNECT_TIMEOUT_S = 3.0  # disconnect() sleeps 500 ms by itself
SUPERVISOR_FRACTION = 0.25  # the supervisor wakes every quarter watchdog period
#: Each ur_rtde client's polling thread sleeps with a timer slack of this fraction of its stream's period (125 Hz:
#: 1 ms; ``timer_slack.py``): a package is seen at most that much later. Both clients, since the kernel ends a
#: slack sleep early at another thread's wake-up: with the receive client's slack alone, the control client's
#: polling woke it as often as before. A servoL or watchdog kick is sent without waiting for the script's
#: confirmation (ur_rtde waits only for it to be ready, as it is in steady state); a stop's confirmation may take
#: up to the slack longer.
POLL_SLACK_FRACTION = 0.125

# Retired ur_rtde clients, kept alive so their GIL-holding 500 ms destructors never run on the event loop's watch.
_RETIRED_CLIENTS: list[Any] = []


class URArm:
    """A UR e-Series arm behind ur_rtde, implementing ``hydrosoft.drivers.base.Arm``.

    Args:
        config: host and servo, stop, watchdog, staleness and reconnect settings (``URArmConfig``).
    """

    def __init__(self, config: URArmConfig) -> None:
        self.config = config
        self.counters: Counter = Counter()
        self._control: Any = None
        self._receive: Any = None
        self._control_thread = ThreadPoolExecutor(1, thread_name_prefix=f"ur-control-{config.host}")
        self._receive_thread = ThreadPoolExecutor(1, thread_name_prefix=f"ur-receive-{config.host}")
        self._control_calls_in_flight = 0
        self._last_command_ns = 0
        self._age = StreamAge()
        self._age_lock = threading.Lock()  # read_state (event loop) and servo_to (control thread) both observe
        self._supervisor: asyncio.Task | None = None
        self._link_up = False
        self._link_since_ns = 0
        self._closed = False

    def __str__(self) -> str:
        return f"URArm({self.config.host})"

    # -- Arm protocol ----------------------------------------------------------------------------------------

    async def connect(self) -> None:
        """Connect both clients, start the control script, arm the watchdog and start the supervisor.

        Raises ``NotConnected`` naming the host and what failed (a port that does not answer, a client that
        could not start), ``DeviceFault`` when the controller refuses the watchdog.
        """
        if self._closed:
            raise NotConnected(f"{self}: closed")
        if self._supervisor is not None:  # connected before: the supervisor owns reconnecting
            if self._link_up:
                return
            raise NotConnected(f"{self}: link lost; reconnecting in the background")
        await self._open()
        self._supervisor = asyncio.create_task(self._supervise(), name=f"{self}-supervisor")

    async def read_state(self) -> ArmState:
        """The newest controller state; raises ``NotConnected`` when the link is down, ``Stale`` when that state is
        older than ``max_age_s`` (judged from the controller's timestamp, see ``stream_age.py``)."""
        receive = self._require_link()
        try:
            connected, stamp_s, runtime_state, safety_bits, robot_mode, ur_pose, speed = await self._on_thread(
                self._receive_thread, lambda: _read_receive(receive), REALTIME_CALL_TIMEOUT_S
            )
        except asyncio.TimeoutError as exc:
            self.counters["stale"] += 1
            raise Stale(f"{self}: the receive client did not answer within {REALTIME_CALL_TIMEOUT_S} s") from exc
        now_ns = time.monotonic_ns()
        self._require_fresh(connected, stamp_s, self._stream_age_s(stamp_s, now_ns) if connected else 0.0)
        return ArmState(
            tcp_pose=ur_to_pose(ur_pose),
            tcp_speed=np.asarray(speed, dtype=np.float64),
            running=runtime_state == RuntimeState.PLAYING,
            protective_stop=bool(safety_bits & SAFETY_BIT_PROTECTIVE_STOP),
            emergency_stop=bool(safety_bits & EMERGENCY_STOP_BITS),
            stamp_ns=now_ns,
            hw_stamp_ns=round(stamp_s * 1e9),
            controller_stop=controller_stop(safety_bits, robot_mode, runtime_state),
            safety_flags=safety_flags(safety_bits),
            link_since_ns=self._link_since_ns,
        )

    async def servo_to(self, tcp_pose: np.ndarray) -> None:
        """Send one servoL toward ``tcp_pose (7,)`` [m, wxyz] in the base frame, for one servo period.

        One hop to the control thread reads the controller's status words (``_read_guard``), judges them as
        ``read_state`` does (link, age, any stop of the controller's own) and sends servoL only when they allow it:
        the check reads the state right before the command, with no event-loop turn between them. Raises
        ``ValueError`` for a malformed pose (shape, non-finite, quaternion not unit), ``NotConnected``, ``Stale``,
        and ``DeviceFault`` when protectively/emergency stopped, when the script is not running or when the
        controller does not accept the command. Nothing is sent in any of these cases but the last.
        """
        try:
            ur_pose = pose_to_ur(tcp_pose).tolist()
        except ValueError:
            self.counters["rejected_target"] += 1
            raise
        receive = self._require_link()
        control = self._control
        if control is None:
            self.counters["not_connected"] += 1
            raise NotConnected(f"{self}: not connected")
        cfg = self.config
        guard = _ServoGuard()

        def read_check_send() -> bool | None:
            guard.started = True
            connected, stamp_s, runtime_state, safety_bits, robot_mode = _read_guard(receive)
            guard.read(connected, stamp_s, time.monotonic_ns())
            if not connected:
                return None
            guard.age_s = self._stream_age_s(stamp_s, guard.read_ns)
            guard.stop = controller_stop(safety_bits, robot_mode, runtime_state)
            guard.flags = safety_flags(safety_bits)
            if guard.age_s > cfg.max_age_s or guard.stop:
                return None
            if not guard.may_send():
                return None
            return control.servoL(ur_pose, cfg.servo_speed_m_s, cfg.servo_accel_m_s2, cfg.servo_period_s,
                                  cfg.servo_lookahead_s, cfg.servo_gain)

        accepted = await self._guarded_call(read_check_send, guard)
        self._require_fresh(guard.connected, guard.stamp_s, guard.age_s)
        self._require_commandable(guard.flags, guard.stop, "servoL")
        if not accepted:
            self.counters["command_rejected"] += 1
            raise DeviceFault(f"{self}: the controller did not accept servoL (script not ready)")
        self.counters["servo_commands"] += 1

    async def stop(self) -> None:
        """Decelerate the TCP to rest at ``stop_decel_m_s2`` (servoStop) and return once it is at rest.

        Safe to repeat. When the controller reports a stop of its own (``ArmState.controller_stop``: a safety
        stop, the script not running or paused, the arm not powered), it has already stopped the arm and nothing
        is sent. Raises ``NotConnected`` when the controller cannot be reached (its watchdog then stops the arm)
        and ``DeviceFault`` when the running script refuses the stop.
        """
        state = await self._state_for_stop()
        if state is not None and state.controller_stop:
            return
        decel = self.config.stop_decel_m_s2
        stopped = await self._control_call(
            lambda c: c.servoStop(decel), self.config.max_stop_duration_s + STOP_MARGIN_S
        )
        if not stopped:
            after = await self._state_for_stop()
            if after is not None and after.controller_stop:
                return
            self.counters["command_rejected"] += 1
            raise DeviceFault(f"{self}: the controller did not complete servoStop")
        self.counters["stops"] += 1

    async def close(self) -> None:
        """Stop the arm (servoStop, sent while the link still counts as open), stop the control script
        (stopScript) and disconnect both clients. Idempotent."""
        if self._closed:
            return
        if self._supervisor is not None:
            self._supervisor.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._supervisor
        link_up = self._link_up
        if link_up:
            with contextlib.suppress(NotConnected, Stale, DeviceFault):
                await self.stop()
        self._closed = True
        if link_up:
            with contextlib.suppress(NotConnected, DeviceFault):
                await self._control_call(lambda c: c.stopScript(), SETUP_CALL_TIMEOUT_S)
                self.counters["script_stops"] += 1
        await self._retire_clients()
        self._control_thread.shutdown(wait=False)
        self._receive_thread.shutdown(wait=False)

    # -- extras ------------------------------------------------------------------------------------------------

    async def restart_script(self) -> None:
        """Upload and start the control script again (after a watchdog expiry or an operator's stop) and re-arm
        the watchdog. Raises ``DeviceFault`` while protectively stopped or when the controller refuses."""
        state = await self.read_state()
        if state.safety_flags:
            raise DeviceFault(f"{self}: cannot restart the script while the controller reports a "
                              f"{state.safety_flags[0]}")
        if not await self._control_call(lambda c: c.reuploadScript(), SETUP_CALL_TIMEOUT_S):
            raise DeviceFault(f"{self}: the controller did not restart the control script")
        await self._wait_running()
        await self._arm_watchdog()
        self.counters["script_restarts"] += 1

    @property
    def connected(self) -> bool:
        """True while both clients are up (a stale stream still counts as connected)."""
        return self._link_up

    # -- connection ------------------------------------------------------------------------------------------

    async def _open(self) -> None:
        cfg = self.config
        await probe_rtde_stream(cfg.host, cfg.connect_timeout_s)
        await probe_port(cfg.host, DASHBOARD_PORT, "dashboard", cfg.connect_timeout_s)
        await probe_port(cfg.host, SCRIPT_PORT, "script", cfg.connect_timeout_s)
        try:
            self._receive = await self._on_thread(
                self._receive_thread,
                lambda: started_with_slack(POLL_SLACK_FRACTION / cfg.state_rate_hz, lambda: (
                    rtde_receive.RTDEReceiveInterface(
                        cfg.host, cfg.state_rate_hz, RECEIVE_VARIABLES, False, cfg.upper_range_registers
                    ))),
                SETUP_CALL_TIMEOUT_S,
            )
        except (RuntimeError, asyncio.TimeoutError) as exc:
            raise NotConnected(f"{self}: RTDE receive interface failed to start: {error_text(exc)}") from exc
        flags = rtde_control.RTDEControlInterface.FLAG_UPLOAD_SCRIPT
        if cfg.upper_range_registers:
            flags |= rtde_control.RTDEControlInterface.FLAG_UPPER_RANGE_REGISTERS
        try:
            self._control = await self._on_thread(
                self._control_thread,
                lambda: started_with_slack(POLL_SLACK_FRACTION / cfg.control_rate_hz,
                                           lambda: rtde_control.RTDEControlInterface(cfg.host, cfg.control_rate_hz,
                                                                                     flags)),
                SETUP_CALL_TIMEOUT_S,
            )
        except (RuntimeError, asyncio.TimeoutError) as exc:
            await self._retire_clients()
            raise NotConnected(f"{self}: RTDE control interface failed to start: {error_text(exc)}") from exc
        self._link_up = True
        self._link_since_ns = time.monotonic_ns()
        with self._age_lock:
            self._age.reset()  # the controller may have restarted: its clock too
        try:
            await self._arm_watchdog()
        except (DeviceFault, NotConnected):
            await self._retire_clients()
            raise
        log.info("%s: connected, watchdog %.1f Hz", self, cfg.watchdog_min_hz)

    async def _arm_watchdog(self) -> None:
        min_hz = self.config.watchdog_min_hz
        if not await self._control_call(lambda c: c.setWatchdog(min_hz), SETUP_CALL_TIMEOUT_S):
            raise DeviceFault(f"{self}: the controller refused setWatchdog({min_hz})")

    async def _wait_running(self) -> None:
        """Wait until the control client sees the program running. Its RTDE stream is its own: the receive client
        may report PLAYING a few packages earlier, and a command sent in between returns False (``sendCommand``
        refuses while its own ``runtime_state`` still reads STOPPED)."""
        deadline_ns = time.monotonic_ns() + int(SETUP_CALL_TIMEOUT_S * 1e9)
        while time.monotonic_ns() < deadline_ns:
            if await self._control_call(lambda c: c.isProgramRunning(), REALTIME_CALL_TIMEOUT_S):
                return
            await asyncio.sleep(self.config.servo_period_s)
        raise DeviceFault(f"{self}: the control script did not start within {SETUP_CALL_TIMEOUT_S} s")

    async def _retire_clients(self) -> None:
        """Disconnect both clients on their own threads and park them (see ``_RETIRED_CLIENTS``)."""
        self._link_up = False
        control, receive = self._control, self._receive
        self._control = self._receive = None
        waits = []
        for client, thread in ((control, self._control_thread), (receive, self._receive_thread)):
            if client is not None:
                _RETIRED_CLIENTS.append(client)
                waits.append(self._on_thread(thread, client.disconnect, DISCONNECT_TIMEOUT_S))
        for result in await asyncio.gather(*waits, return_exceptions=True):
            if isinstance(result, BaseException):
                log.warning("%s: disconnect failed: %s", self, result)

    def _mark_link_lost(self, reason: str) -> None:
        if self._link_up:
            self._link_up = False
            self.counters["link_lost"] += 1
            log.warning("%s: link lost (%s)", self, reason)

    def _require_link(self) -> Any:
        receive = self._receive
        if self._closed or not self._link_up or receive is None:
            self.counters["not_connected"] += 1
            raise NotConnected(f"{self}: not connected" + (" (closed)" if self._closed else ""))
        return receive

    def _require_fresh(self, connected: bool, stamp_s: float, age_s: float) -> None:
        """Raise ``NotConnected`` (counted; the link marked lost) when the RTDE stream closed, ``Stale`` (counted)
        when the state stamped ``stamp_s`` (controller clock, s) is ``age_s`` old, over ``max_age_s``."""
        if not connected:
            self._mark_link_lost("the RTDE stream closed")
            self.counters["not_connected"] += 1
            raise NotConnected(f"{self}: the RTDE stream from the controller closed; reconnecting")
        if age_s > self.config.max_age_s:
            self.counters["stale"] += 1
            raise Stale(
                f"{self}: newest controller state (timestamp {stamp_s:.3f} s) is {age_s:.3f} s old "
                f"(max_age_s {self.config.max_age_s} s)"
            )

    def _require_commandable(self, flags: tuple[str, ...], stop: str, command: str) -> None:
        """Raise ``DeviceFault`` (counted) while the controller reports a safety stop (``flags``, as
        ``ArmState.safety_flags``), or any other stop of its own (``stop``, as ``ArmState.controller_stop``: the
        program not playing, the arm not powered)."""
        if flags:
            self.counters["refused_safety_stop"] += 1
            raise DeviceFault(f"{self}: {flags[0]} active; {command} not sent")
        if stop:
            self.counters["refused_script_not_running"] += 1
            raise DeviceFault(f"{self}: the control script is not running ({stop}); {command} not sent")

    def _stream_age_s(self, stamp_s: float, now_ns: int) -> float:
        """The age (s) of the controller state stamped ``stamp_s`` (controller clock, s) read at ``now_ns``
        (``stream_age.py``); safe from the event loop and the control thread."""
        with self._age_lock:
            return self._age.observe(stamp_s, now_ns)

    async def _state_for_stop(self) -> ArmState | None:
        """State for ``stop``: None when only staleness prevents reading it (the stop is sent anyway)."""
        try:
            return await self.read_state()
        except Stale:
            return None

    # -- supervisor: watchdog kicks and reconnects -------------------------------------------------------------

    async def _supervise(self) -> None:
        period_s = self.config.watchdog_period_s * SUPERVISOR_FRACTION
        while not self._closed:
            await asyncio.sleep(period_s)
            try:
                await self._supervise_once(period_s)
            except Exception:  # the supervisor must outlive any one failure: log it, count it, go on
                self.counters["supervisor_error"] += 1
                log.exception("%s: supervisor step failed", self)

    async def _supervise_once(self, period_s: float) -> None:
        if not self._link_up:
            await self._reconnect()
            return
        receive = self._receive
        if receive is None:
            return
        if not await self._on_thread(self._receive_thread, receive.isConnected, REALTIME_CALL_TIMEOUT_S):
            self._mark_link_lost("the RTDE stream closed")
            return
        idle_ns = time.monotonic_ns() - self._last_command_ns
        if self._control_calls_in_flight == 0 and idle_ns > period_s * 1e9:
            with contextlib.suppress(NotConnected, DeviceFault):
                await self._control_call(lambda c: c.kickWatchdog(), REALTIME_CALL_TIMEOUT_S)
                self.counters["watchdog_kicks"] += 1

    async def _reconnect(self) -> None:
        """Retire the dead clients, then try to connect again with doubling back-off until it works or close()."""
        await self._retire_clients()
        wait_s = self.config.reconnect_initial_s
        while not self._closed:
            try:
                await self._open()
            except (NotConnected, DeviceFault) as exc:
                self.counters["reconnect_failures"] += 1
                log.info("%s: reconnect failed (%s); next try in %.1f s", self, exc, wait_s)
                await asyncio.sleep(wait_s)
                wait_s = min(2.0 * wait_s, self.config.reconnect_max_s)
                continue
            self.counters["reconnects"] += 1
            log.info("%s: reconnected", self)
            return

    # -- worker threads --------------------------------------------------------------------------------------

    async def _control_call(self, call: Callable[[Any], T], timeout_s: float) -> T:
        """Run ``call(control_client)`` on the control thread; ``NotConnected`` when there is no client,
        ``DeviceFault`` when ur_rtde raises or the call outlasts ``timeout_s``."""
        control = self._control
        if control is None:
            self.counters["not_connected"] += 1
            raise NotConnected(f"{self}: not connected")
        self._control_calls_in_flight += 1
        self._last_command_ns = time.monotonic_ns()
        try:
            return await self._on_thread(self._control_thread, lambda: call(control), timeout_s)
        except asyncio.TimeoutError as exc:
            raise self._command_timeout(timeout_s) from exc
        except RuntimeError as exc:
            self.counters["command_rejected"] += 1
            raise DeviceFault(f"{self}: ur_rtde call failed: {exc}") from exc
        finally:
            self._control_calls_in_flight -= 1
            self._last_command_ns = time.monotonic_ns()

    async def _guarded_call(self, call: Callable[[], T], guard: _ServoGuard) -> T:
        """``call()`` (``servo_to``'s read-check-send) on the control thread, with the limits of the two calls it
        replaces: the read must be done within ``REALTIME_CALL_TIMEOUT_S`` (else ``Stale``, and the call sends
        nothing: ``guard.abandon``), servoL must return within ``REALTIME_CALL_TIMEOUT_S`` of its start (else
        ``DeviceFault``, counted ``command_timeout``, as a call that never started because the control thread was
        busy). ``DeviceFault`` (``command_rejected``) when servoL raises; a getter's error propagates as from
        ``read_state``. Once the caller stops waiting (an error, a timeout, a cancellation), a call still reading
        sends nothing. It counts as a control call in flight (no watchdog kick meanwhile) and as a command only
        when servoL was sent."""
        self._control_calls_in_flight += 1
        try:
            job = self._control_thread.submit(call)
            try:
                async with asyncio.timeout(REALTIME_CALL_TIMEOUT_S):
                    return await asyncio.wrap_future(job)
            except TimeoutError:
                sent_ns = guard.abandon()
                if job.done() and not job.cancelled():
                    return job.result()
                if sent_ns is None and guard.started:
                    self.counters["stale"] += 1
                    raise Stale(f"{self}: the receive client did not answer within {REALTIME_CALL_TIMEOUT_S} s") \
                        from None
                if sent_ns is None:
                    raise self._command_timeout(REALTIME_CALL_TIMEOUT_S) from None
            try:
                async with asyncio.timeout_at(sent_ns * 1e-9 + REALTIME_CALL_TIMEOUT_S):
                    return await asyncio.wrap_future(job)
            except TimeoutError:
                raise self._command_timeout(REALTIME_CALL_TIMEOUT_S) from None
        except RuntimeError as exc:
            if guard.sent_ns is None:
                raise
            self.counters["command_rejected"] += 1
            raise DeviceFault(f"{self}: ur_rtde call failed: {exc}") from exc
        finally:
            self._control_calls_in_flight -= 1
            if guard.abandon() is not None:  # cancelled or not: a call still reading sends nothing now
                self._last_command_ns = time.monotonic_ns()

    def _command_timeout(self, timeout_s: float) -> DeviceFault:
        """The ``DeviceFault`` of a control call that did not return within ``timeout_s`` (s), counted."""
        self.counters["command_timeout"] += 1
        return DeviceFault(f"{self}: ur_rtde call did not return within {timeout_s} s")

    async def _on_thread(self, thread: ThreadPoolExecutor, call: Callable[[], T], timeout_s: float) -> T:
        """``call()`` on ``thread``; TimeoutError after ``timeout_s`` s (the call itself runs on). A cancellation
        always propagates: Python 3.11's ``asyncio.wait_for`` returned the result instead when the call finished
        just as the task was cancelled, and a SIGINT that landed there left the commander's loop running."""
        loop = asyncio.get_running_loop()
        async with asyncio.timeout(timeout_s):
            return await loop.run_in_executor(thread, call)


def _read_receive(receive: Any) -> tuple[bool, float, int, int, int, list[float], list[float]]:
    """One consistent-enough read of the receive client (each getter locks ur_rtde's state separately): the status
    words of ``_read_guard``, then the TCP pose and speed."""
    return (*_read_guard(receive), receive.getActualTCPPose(), receive.getActualTCPSpeed())


def _read_guard(receive: Any) -> tuple[bool, float, int, int, int]:
    """The status words ``servo_to`` checks before each command: link, controller timestamp (s), runtime state,
    safety status bits, robot mode (not the pose and speed, which ``read_state`` converts)."""
    return (
        receive.isConnected(),
        receive.getTimestamp(),
        receive.getRuntimeState(),
        receive.getSafetyStatusBits(),
        receive.getRobotMode(),
    )


class _ServoGuard:
    """How far one ``servo_to``'s read-check-send on the control thread got, shared with the event loop: what it
    read (link, controller stamp in s, host read time in ns, age in s, safety flags, the controller's stop), when it
    sent servoL (``sent_ns``) and whether the loop gave up waiting (``abandoned``: then it sends nothing)."""

    __slots__ = ("lock", "started", "connected", "stamp_s", "read_ns", "age_s", "flags", "stop", "sent_ns",
                 "abandoned")

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.started = False
        self.connected = True
        self.stamp_s = 0.0
        self.read_ns = 0
        self.age_s = 0.0
        self.flags: tuple[str, ...] = ()
        self.stop = ""
        self.sent_ns: int | None = None
        self.abandoned = False

    def read(self, connected: bool, stamp_s: float, read_ns: int) -> None:
        """Note the link and the controller's stamp as read at ``read_ns`` (monotonic ns)."""
        self.connected, self.stamp_s, self.read_ns = connected, stamp_s, read_ns

    def may_send(self) -> bool:
        """On the control thread, right before servoL: whether the loop still waits (then note the send time)."""
        with self.lock:
            if self.abandoned:
                return False
            self.sent_ns = time.monotonic_ns()
            return True

    def abandon(self) -> int | None:
        """On the event loop, when it stops waiting: nothing is sent from now on; returns when servoL was sent
        (monotonic ns), or None when it was not."""
        with self.lock:
            self.abandoned = True
            return self.sent_ns
