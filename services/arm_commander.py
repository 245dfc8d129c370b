"""The arm commander service ``arm_commander-ARM`` (one per arm): it servoes the arm and owns its safe fallback.

Each period of ``limits.servo_rate_hz`` it reads the arm's state from its driver (``URArm`` on ``arm.ur_host``; in
sim mode sim_world's simulated controller answers there), takes the planner's newest ``arm_target/ARM``, the
planner's ``heartbeat/planner`` and the F/T reader's ``wrench/ARM``, and either sends the next servo pose
(``safety.interpolate``: straight towards the target within the speed limits) or stops the arm. It stops
(``driver.stop()`` once, and again whenever the stopped arm is seen moving) when the driver fails (Stale,
NotConnected, DeviceFault), on any ``safety.watchdog`` rule (no target, deadline passed, heartbeat old, state not
advancing, force unknown or too high) and on a refused target (``safety.check_target``: outside the workspace box,
malformed; counted as ``target_refused``, never moved towards). Holding the arm spends the target: servoing
resumes only with a fresh one (published after the last one seen) whose deadline lies ahead and which arrives
with a fresh heartbeat (one arriving during the stop itself waits for the stop's end).

It publishes ``ArmState`` on ``arm_state/ARM`` every period (with ``servo_active`` and ``stop_reason``) while the
driver delivers state. While it holds the arm at rest with no target (``ServoLogic.holding_at_rest``), its period
is that of ``limits.idle_rate_hz`` instead, and a target's arrival wakes it at once: an idle stack's commander and
the readers of its state do a fifth of the work (ur_rtde's receive threads poll on regardless). The wrenches (100
Hz) do not wake it: each tick reads those that came since the last one and keeps the newest. On shutdown
(SIGINT/SIGTERM) it stops the arm, confirms it is at rest, then closes the driver, which stops the controller's
script (stopScript).

The decisions live in ``ServoLogic`` (no sockets, no driver; unit tested); ``Commander`` is the thin I/O around it.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import time
from dataclasses import dataclass

import numpy as np

from hydrosoft.drivers.base import Arm, ArmState
from hydrosoft.drivers.errors import DriverError
from hydrosoft.services import messages as msg
from hydrosoft.services.bus import Received, Stale
from hydrosoft.services.config import LimitsConfig, StackConfig
from hydrosoft.services import arm_service_main, service_main
from hydrosoft.services.runtime import Service
from hydrosoft.services.safety import NO_TARGET, check_target, interpolate, is_moving, watchdog

MODULE = "arm_commander"
#: The newest wrench counts as a force reading for this long (s); older: "no fresh F/T reading", the arm stops.
#: The FT 300 streams at 100 Hz; this allows a few missed frames and a busy reader.
WRENCH_MAX_AGE_S = 0.25
#: Wrenches the F/T subscription queues between two ticks. Each tick reads them all and keeps the newest, so the
#: queue holds far more than a tick's worth (4 at 100 Hz and the idle rate's 25 Hz): a full queue would leave newer
#: wrenches waiting behind it in the OS buffers, unread by that tick.
WRENCH_QUEUE = 1000
#: Targets and heartbeats are read at any age here; ``safety.watchdog`` judges their age.
ANY_AGE_S = float("inf")
#: Longest the shutdown waits for the arm to be seen at rest after its stop, s (within the runtime's
#: shutdown_timeout_s of 2 s, with the driver's close after it).
REST_CONFIRM_TIMEOUT_S = 0.5
#: Least time between two restarts of the controller's program, s.
SCRIPT_RESTART_S = 1.0
#: The reason a fresh target is not servoed on while the previous stop is still in flight.
STOPPING = "stopping"
#: The loop skips ahead instead of bursting when it falls this many periods behind.
MAX_LAG_PERIODS = 2
#: Each servo step covers the time since the previous one at the speed limits, but at most this many periods (a
#: late tick moves no further than this; ticks that come in a burst move only as far as their spacing allows).
MAX_STEP_PERIODS = 2


@dataclass(frozen=True)
class Decision:
    """What to do this period. command: the servo pose ``(7,)`` [m, wxyz] to send, or None (hold stopped).
    stop: send ``driver.stop()`` now. reason: why the arm is stopped ("" while servoing)."""

    command: np.ndarray | None
    stop: bool
    reason: str


class ServoLogic:
    """The commander's decisions, one call of ``decide`` per servo period; no sockets, no driver, no clock.

    Args:
        limits: the workspace box, speed, force and timeout limits (``LimitsConfig``).
        arm: the arm's name (targets for another arm are refused).
    """

    def __init__(self, limits: LimitsConfig, arm: str) -> None:
        self.limits = limits
        self.arm = arm
        self.period_s = 1.0 / limits.servo_rate_hz
        self.target: msg.ArmTarget | None = None  # the accepted, unspent target
        self.servoing = False
        self.reason = NO_TARGET
        self._command: np.ndarray | None = None  # the last servo pose sent while servoing
        self._command_ns = 0  # when it was decided
        self._newest_target_ns = 0  # stamp of the newest target seen, accepted or refused
        self._refusal: str | None = None
        self._state_hw_ns: int | None = None
        self._state_advanced_ns: int | None = None

    def offer(self, target: msg.ArmTarget | None) -> str | None:
        """Consider the newest target message. A target not newer than the last one seen is ignored; a new valid
        one replaces the current target; a new invalid one is refused: the current target is dropped (the arm
        stops and holds) and the reason is returned for counting."""
        if target is None or target.stamp_ns <= self._newest_target_ns:
            return None
        self._newest_target_ns = target.stamp_ns
        reason = check_target(target.tcp_pose, self.limits)
        if reason is None and target.arm != self.arm:
            reason = f"target is for arm {target.arm!r}, not {self.arm!r}"
        if reason is not None:
            self.target, self._refusal = None, f"target refused: {reason}"
            return reason
        self.target, self._refusal = target, None
        return None

    def observe(self, state: ArmState) -> None:
        """Note a state read from the driver: when its controller stamp (or, without one, its host stamp) changed,
        the state advanced at ``state.stamp_ns``."""
        stamp = state.hw_stamp_ns if state.hw_stamp_ns is not None else state.stamp_ns
        if stamp != self._state_hw_ns:
            self._state_hw_ns, self._state_advanced_ns = stamp, state.stamp_ns

    def decide(self, now_ns: int, state: ArmState | None, driver_error: str | None, heartbeat_ns: int | None,
               force_n: float | None, stopping: bool = False) -> Decision:
        """This period's decision at ``now_ns``, from the driver's ``state`` (None when reading it failed with
        ``driver_error``), the planner heartbeat's stamp (ns), the contact force (N, None when unknown) and
        whether a stop is still in flight (then nothing is commanded until it ends)."""
        reason = driver_error or self._refusal or watchdog(
            now_ns, None if self.target is None else self.target.deadline_ns, heartbeat_ns,
            self._state_advanced_ns, force_n, self.limits)
        if reason is None and stopping:
            reason = STOPPING
        if reason is None and state is not None:
            if self.servoing:  # on from the last command, as far as the time since it allows
                start, dt_s = self._command, min((now_ns - self._command_ns) * 1e-9, MAX_STEP_PERIODS * self.period_s)
            else:
                start, dt_s = state.tcp_pose, self.period_s
            self._command = interpolate(start, self.target.tcp_pose, dt_s, self.limits)
            self._command_ns, self.servoing, self.reason = now_ns, True, ""
            return Decision(self._command, stop=False, reason="")
        was_servoing = self.servoing
        self.halt(reason or "no arm state")
        moving = state is not None and is_moving(state.tcp_speed)
        return Decision(None, stop=was_servoing or (moving and not stopping), reason=self.reason)

    def holding_at_rest(self, state: ArmState | None, stopping: bool) -> bool:
        """Whether the arm is held with nothing to do: not servoing, no target, no stop in flight, and ``state``
        (this period's, None when reading it failed) shows it at rest. Then nothing can change until a target
        arrives, and the commander may run at its idle rate."""
        return (not self.servoing and self.target is None and not stopping and state is not None
                and not is_moving(state.tcp_speed))

    def halt(self, reason: str) -> None:
        """Hold the arm for ``reason``. This spends the target (only a fresh target that can be servoed on when it
        arrives resumes), except while the previous stop is in flight (``STOPPING``): a target that arrives then
        waits for the stop's end, checked again each period. The reported ``reason`` stays that of the stop:
        "no target" and "stopping" (what every stop leaves behind) do not replace it."""
        if reason not in (NO_TARGET, STOPPING) or self.servoing:
            self.reason = reason
        if reason != STOPPING:
            self.target = None
        self.servoing, self._command = False, None


class Commander:
    """The commander's I/O: the driver, the subscriptions, the ArmState publisher and the stop task."""

    def __init__(self, service: Service, config: StackConfig, arm: str, driver: Arm) -> None:
        self.service, self.arm, self.driver = service, arm, driver
        self.logic = ServoLogic(config.limits, arm)
        self.inputs = service.subscriber([config.endpoint("planner"), config.endpoint("planner", "status")],
                                         topics=[f"arm_target/{arm}", "heartbeat/planner"], background=True)
        self.wrenches = service.subscriber(config.endpoint(f"ft_reader-{arm}"), [f"wrench/{arm}"],
                                           rcvhwm=WRENCH_QUEUE)
        self.out = service.publisher(config.endpoint(f"{MODULE}-{arm}"))
        self._stop_task: asyncio.Task[None] | None = None
        self._restart_task: asyncio.Task[None] | None = None
        self._script_restarted_s = -SCRIPT_RESTART_S
        self._target_arrived = self.inputs.arrival(f"arm_target/{arm}")
        self.idle = False  # the last tick found the arm held at rest with no target

    def _newest(self, topic: str, max_age_s: float, kind: type[msg.Message]) -> Received | None:
        """The newest target or heartbeat on ``topic`` within ``max_age_s`` (s) with its stamp, or None."""
        try:
            return self.inputs.latest(topic, max_age_s, kind)
        except Stale:
            return None

    def _force_n(self) -> float | None:
        """The contact force (N) of the newest wrench, read now, or None when there is none within
        ``WRENCH_MAX_AGE_S``."""
        try:
            received = self.wrenches.latest(f"wrench/{self.arm}", WRENCH_MAX_AGE_S, msg.Wrench)
        except Stale:
            return None
        return float(np.linalg.norm(received.value.wrench[:3]))

    async def tick(self) -> None:
        """One servo period: read, decide, command or stop, publish."""
        self._target_arrived.clear()
        target = self._newest(f"arm_target/{self.arm}", ANY_AGE_S, msg.ArmTarget)
        refusal = self.logic.offer(None if target is None else target.value)
        if refusal is not None:
            self.service.count_error("target_refused", refusal)
        state, driver_error = None, None
        try:
            state = await self.driver.read_state()
            self.logic.observe(state)
        except DriverError as err:
            driver_error = f"arm driver: {err}"
            self.service.count_error("arm_driver", str(err))
        if (state is not None and not state.running and not state.protective_stop and not state.emergency_stop
                and target is not None and target.value.deadline_ns > time.monotonic_ns()):
            self._restart_script()
        force_n = self._force_n()  # before the decision's time: reading the wrenches queued since the last tick
        heartbeat = self._newest("heartbeat/planner", ANY_AGE_S, msg.Heartbeat)
        decision = self.logic.decide(time.monotonic_ns(), state, driver_error,
                                     None if heartbeat is None else heartbeat.stamp_ns, force_n,
                                     stopping=self.stopping)
        if decision.command is not None:
            try:
                await self.driver.servo_to(decision.command)
            except (DriverError, ValueError) as err:
                self.service.count_error("arm_driver", str(err))
                self.logic.halt(f"arm driver: {err}")
                self._start_stop()
        elif decision.stop:
            self._start_stop()
        self.idle = self.logic.holding_at_rest(state, self.stopping)
        if state is not None:
            await self.out.send(msg.ArmState(
                arm=self.arm, tcp_pose=np.asarray(state.tcp_pose, dtype=np.float64),
                tcp_speed=np.asarray(state.tcp_speed, dtype=np.float64), running=state.running,
                protective_stop=state.protective_stop, emergency_stop=state.emergency_stop,
                servo_active=self.logic.servoing, stop_reason=self.logic.reason, hw_stamp_ns=state.hw_stamp_ns),
                f"arm_state/{self.arm}")

    async def rest(self, period_s: float) -> None:
        """Wait ``period_s`` (s), or less when a target arrives meanwhile (or arrived since this tick began)."""
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(period_s):
                await self._target_arrived.wait()

    def _restart_script(self) -> None:
        """Restart the controller's program (stopped by its watchdog when this process was starved, or by an
        operator) beside the loop, at most once per ``SCRIPT_RESTART_S``, and only while fresh targets arrive: the
        arm then resumes on the next fresh target through the normal checks. A protective or emergency stop is
        never cleared here."""
        now = time.monotonic()
        if now - self._script_restarted_s < SCRIPT_RESTART_S or (
                self._restart_task is not None and not self._restart_task.done()):
            return
        self._script_restarted_s = now

        async def restart() -> None:
            try:
                await self.driver.restart_script()
                self.service.log.info("restarted the controller's program")
            except DriverError as err:
                self.service.count_error("script_restart", str(err))

        self._restart_task = asyncio.create_task(restart(), name=f"{self.service.name}.restart_script")

    @property
    def stopping(self) -> bool:
        """A stop is in flight."""
        return self._stop_task is not None and not self._stop_task.done()

    def _start_stop(self) -> None:
        """Start ``driver.stop()`` beside the loop (it returns once the arm is at rest), so that ArmState keeps
        flowing meanwhile."""
        if not self.stopping:
            self.service.log.warning("stopping the arm: %s", self.logic.reason)
            self._stop_task = asyncio.create_task(self._stop(), name=f"{self.service.name}.stop")

    async def _stop(self) -> None:
        try:
            await self.driver.stop()
        except DriverError as err:
            self.service.count_error("stop_failed", str(err))

    async def stop_and_confirm(self) -> None:
        """Stop the arm and wait (at most ``REST_CONFIRM_TIMEOUT_S``) until its state shows it at rest; log which."""
        self.logic.halt("shutdown")
        if self.stopping:
            await self._stop_task
        await self._stop()
        deadline_ns = time.monotonic_ns() + int(REST_CONFIRM_TIMEOUT_S * 1e9)
        while True:
            try:
                if not is_moving((await self.driver.read_state()).tcp_speed):
                    self.service.log.info("arm stopped and at rest")
                    return
            except DriverError as err:
                self.service.count_error("arm_driver", str(err))
            if time.monotonic_ns() > deadline_ns:
                self.service.log.error("the arm was not seen at rest within %.1f s of its stop", REST_CONFIRM_TIMEOUT_S)
                return
            await asyncio.sleep(self.logic.period_s)


async def serve(service: Service, config: StackConfig, arm: str) -> None:
    """The service's main: connect the arm, then servo at ``limits.servo_rate_hz`` (``limits.idle_rate_hz`` while
    idle) until cancelled."""
    from hydrosoft.drivers.ur.arm import URArm
    from hydrosoft.drivers.ur.config import URArmConfig

    driver = URArm(URArmConfig(host=config.arm(arm).ur_host, servo_rate_hz=config.limits.servo_rate_hz,
                               state_rate_hz=config.limits.servo_rate_hz,
                               max_age_s=config.limits.state_timeout_s))
    await driver.connect()
    commander = Commander(service, config, arm, driver)

    async def shut_down() -> None:
        try:
            await commander.stop_and_confirm()
        finally:
            await driver.close()

    service.on_shutdown(shut_down)
    await service.ready()
    loop = asyncio.get_running_loop()
    period_s, idle_period_s = commander.logic.period_s, 1.0 / config.limits.idle_rate_hz
    next_s = loop.time()
    while True:
        await commander.tick()
        if commander.idle:
            await commander.rest(idle_period_s)
            next_s = loop.time()
            continue
        next_s += period_s
        if loop.time() - next_s > MAX_LAG_PERIODS * period_s:
            next_s = loop.time()
        await asyncio.sleep(max(0.0, next_s - loop.time()))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments: CONFIG [--name MODULE-ARM] (``arm_service_main``)."""
    arm_service_main.add_arguments(parser, MODULE)


def run(args: argparse.Namespace) -> int:
    """Run the service until SIGINT/SIGTERM; the exit code (2: a bad config or name)."""
    return arm_service_main.run(args, MODULE, serve)


def main(argv: list[str] | None = None) -> int:
    return service_main.main(MODULE, __doc__, argv, add_arguments, run)


if __name__ == "__main__":
    service_main.exit_process(main())
