"""The arm commander service ``arm_commander-ARM`` (one per arm): it servoes the arm and owns its safe fallback.

Each period of ``limits.servo_rate_hz`` it reads the arm's state from its driver (``URArm`` on ``arm.ur_host``; in
sim mode sim_world's simulated controller answers there), takes the planner's newest ``arm_target/ARM``, the
planner's ``heartbeat/planner`` and the F/T reader's ``wrench/ARM``, and either sends the next servo pose
(``safety.interpolate``: straight towards the target within the speed limits) or stops the arm (``driver.stop()``
once, and again whenever the stopped arm is seen moving).

Every stop has a named cause (``ArmState.stop_reason``) and an owner (``ArmState.stop_owner``):

- ``external``: the controller reports a stop of its own (``ArmState.controller_stop``: pendant or dashboard stop
  or pause, a protective, safeguard or emergency stop, a safety fault, an unpowered arm, a program stopped by
  anyone or anything but this commander, the controller's watchdog included). It latches (``ArmState.latched``):
  no servoing and no program restart, even once the controller runs again, until a person runs ``hydrosoft-stack
  arm enable ARM`` (an ``EnableArm`` request on ``cmd`` of this service, logged; refused while the controller
  still reports a safety stop or an unpowered arm; the program is restarted then if it is not running).
- ``stack``: the commander's own rules. The transient ones clear on the next fresh target: the driver failing
  (Stale, NotConnected, DeviceFault), the target's deadline (clamped to ``limits.max_target_lead_s`` after its
  arrival; a hold, see below), no planner heartbeat seen yet, the plan's age (``ArmTarget.plan_done_ns`` older than
  ``limits.max_plan_age_s``: a hung solve), the state not advancing, no fresh F/T reading, the force limit. A
  refused target (``safety.check_target``: outside the workspace box or the orientation limits, malformed, another
  arm's; or a straight path that starts outside them) holds the arm for the rest of its goal.

Hold: a target's deadline that passes while the arm servoes, every other rule met, means only that the planner's
next target is late. The arm stops as for any stop (``driver.stop()``: it decelerates to rest at the driver's stop
deceleration and goes no further than its servo command), but the stop is a hold: ``ArmState.holding`` says so, the
cause reads ``HOLD`` ("hold: target deadline passed ..."), it is counted once as ``deadline_hold`` (not as a
fault), and the next fresh target resumes. The planner sizes its targets' deadlines to its own measured cycle
(``planner.target_lead``), so holds are rare. A goal's end (the planner's halt, ``ArmTarget.goal_end``) stops the
arm with the cause "goal OUTCOME" ("goal reached"), which stays the arm's reported cause until a fresh target.

No motion the person did not start: a target is acted on only when its goal (``ArmTarget.goal_started_ns``) started
after this commander's start, its last reconnect to the controller, its last ``arm enable`` and the last loss of the
planner (a heartbeat that was fresh and went older than ``limits.planner_lost_s``: a dead, frozen or cut-off
planner ends its goal, counted once as ``planner_lost``; one that runs on does not resume it; a shorter gap past
``limits.heartbeat_timeout_s`` only stops the arm until the goal's next fresh target) and the last loss of the F/T
readings (none for longer than ``limits.sensor_lost_s`` after a fresh one: a dead reader or an unplugged sensor,
counted once as ``ft_lost``; a reader that comes back does not resume the goal); the others are
counted (``old_goal``) and the arm holds. ``ArmState.goal_floor_ns`` and ``goal_floor_cause`` publish that floor, so
the planner ends a goal the commander no longer acts on.

Force limit: above ``limits.max_force_n`` only a retreat is servoed (``safety.retreat_refusal``: a move within 60
deg of the contact force on the bubble, the F/T sensor's axes being the TCP's, with almost no turn); a push is
refused. Normal servoing resumes once the force has fallen below ``limits.release_force_n``.

Holding the arm spends the target: servoing resumes only with a fresh one (published after the last one seen) whose
deadline lies ahead and which arrives with a fresh heartbeat (one arriving during the stop itself waits for the
stop's end).

It publishes ``ArmState`` on ``arm_state/ARM`` every period while the driver delivers state. While it holds the arm
at rest with no target (``ServoLogic.holding_at_rest``), its period is that of ``limits.idle_rate_hz`` instead, and
a target's arrival wakes it at once: an idle stack's commander and the readers of its state do a fifth of the work
(ur_rtde's receive threads poll on regardless). The wrenches (100 Hz) do not wake it: each tick reads those that
came since the last one and keeps the newest. An external stop is counted once as the error ``external_stop`` and
the service reports ``degraded`` while it latches, so ``hydrosoft-stack status`` names it. On shutdown
(SIGINT/SIGTERM) it stops the arm, confirms it is at rest, then closes the driver, which sends servoStop and stops
the controller's script (stopScript). Exit codes: 0 stopped and seen at rest, 1 the service or its shutdown failed,
2 a bad config or name, 3 the arm was never seen at rest after its stop (``EXIT_STOP_UNCONFIRMED``).

The decisions live in ``ServoLogic`` (no sockets, no driver; unit tested); ``Commander`` is the thin I/O around it.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import functools
import math
import time
from dataclasses import dataclass

import numpy as np

from hydrosoft.drivers.base import Arm, ArmState
from hydrosoft.drivers.errors import DriverError
from hydrosoft.drivers.ur.config import URArmConfig
from hydrosoft.services.bus import messages as msg
from hydrosoft.services.bus.sockets import Received, Stale
from hydrosoft.services.bus.config import LimitsConfig, StackConfig
from hydrosoft.services.bus import service_cli
from hydrosoft.services.bus.runtime import Service
from hydrosoft.services.arm.safety import (NO_TARGET, check_path, check_target, clamped_deadline_ns, interpolate,
                                       is_moving, retreat_refusal, watchdog)

MODULE = "arm_commander"
#: Why the arm holds while the F/T reader publishes untared wrenches (no stored bias): their force is off by the
#: sensor's unknown offset, so ``limits.max_force_n`` cannot be judged on them.
UNTARED_FT = ("F/T sensor not tared: its force is off by an unknown offset (move the bubble clear of contact, then "
              "run `hydrosoft-stack ft tare ARM`)")
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
#: How long ``arm enable`` waits for the restarted program to show as running, s.
ENABLE_RUNNING_TIMEOUT_S = 1.0
#: The exit code when the shutdown never saw the arm at rest after its stop.
EXIT_STOP_UNCONFIRMED = 3
#: The reason a fresh target is not servoed on while the previous stop is still in flight.
STOPPING = "stopping"
#: The goal floor's cause after the planner's heartbeat went stale (or gone) from fresh.
PLANNER_LOST = "the loss of the planner's heartbeat"
#: The goal floor's cause after the F/T readings went missing (from fresh) for longer than ``limits.sensor_lost_s``.
FT_LOST = "the loss of the F/T readings"
#: The cause a hold names: a target's deadline passed while the arm servoed and no other rule stopped it.
HOLD = "hold: target deadline passed"
#: The loop skips ahead instead of bursting when it falls this many periods behind.
MAX_LAG_PERIODS = 2
#: Each servo step covers the time since the previous one at the speed limits, but at most this many periods (a
#: late tick moves no further than this; ticks that come in a burst move only as far as their spacing allows).
MAX_STEP_PERIODS = 2


@dataclass(frozen=True)
class Decision:
    """What to do this period. command: the servo pose ``(7,)`` [m, wxyz] to send, or None (hold stopped).
    stop: send ``driver.stop()`` now. reason: why the arm is stopped ("" while servoing). refusal: a target refused
    this period for its path (to be counted), or "". planner_lost: why the planner counts as lost this period and
    every goal started before it ended (to be counted once), or "". ft_lost: the same for the F/T readings.
    hold_started: the stop begun this period is a hold (to be counted as one)."""

    command: np.ndarray | None
    stop: bool
    reason: str
    refusal: str = ""
    planner_lost: str = ""
    ft_lost: str = ""
    hold_started: bool = False


class ServoLogic:
    """The commander's decisions, one call of ``decide`` per servo period; no sockets, no driver, no clock.

    Stop authority: every stop has an owner. An ``external`` stop (the controller reports a stop of its own: a
    safety stop, a paused or stopped program, an unpowered arm) latches: nothing is servoed until ``enable``
    (a person's ``arm enable``), even once the controller runs again. A ``stack`` stop is one of the commander's
    own rules; the transient ones (deadline, a heartbeat not seen yet, state, F/T, driver errors, the force limit)
    clear on the next fresh target, a refused target holds the arm for the rest of its goal, a lost planner (its
    heartbeat fresh at one decision, gone or older than ``limits.planner_lost_s`` at a later one) and lost F/T
    readings (fresh at one decision, none for longer than ``limits.sensor_lost_s`` since) end every goal started
    before the loss: a planner or F/T reader that comes back (restarted, reconnected) does not resume it. A stop
    for the servoed target's passed deadline alone is a hold (``holding``): a late planner, not a fault (the module
    docstring).

    No motion the person did not start: only targets of a goal started (``ArmTarget.goal_started_ns``) after the
    commander's start, its last reconnect to the controller (``ArmState.link_since_ns``), its last ``enable``, the
    goal of its last refused target and the last loss of the planner or of the F/T readings are servoed on.

    Args:
        limits: the workspace box, orientation, speed, force and timeout limits (``LimitsConfig``).
        arm: the arm's name (targets for another arm are refused).
        nominal_tcp: the arm's nominal TCP orientation ``(4,)`` wxyz (``ArmConfig.nominal_tcp``).
        started_ns: the commander's start (``time.monotonic_ns()``).
    """

    def __init__(self, limits: LimitsConfig, arm: str, nominal_tcp=(1.0, 0.0, 0.0, 0.0), started_ns: int = 0) -> None:
        self.limits = limits
        self.arm = arm
        self.nominal_tcp = np.asarray(nominal_tcp, dtype=np.float64)
        self.period_s = 1.0 / limits.servo_rate_hz
        self.target: msg.ArmTarget | None = None  # the accepted, unspent target
        self.deadline_ns = 0  # its deadline, clamped to limits.max_target_lead_s after its arrival
        self.servoing = False
        self.holding = False  # the arm is held because a target's deadline passed, waiting for the next one
        self.reason = NO_TARGET
        self.owner: msg.StopOwner = "stack"
        self.external: str | None = None  # the latched external stop, until enable()
        self.force_limited = False  # above max_force_n, and not yet back below the release level
        self.goal_floor_ns = started_ns  # only goals started after this move the arm
        self.goal_floor_cause = "the commander's start"
        self._command: np.ndarray | None = None  # the last servo pose sent while servoing
        self._command_ns = 0  # when it was decided
        self._newest_target_ns = 0  # stamp of the newest target seen, accepted or refused
        self._refusal: str | None = None
        self._goal_end: str | None = None  # the cause of the planner's last goal-end halt, until a fresh target
        self._link_since_ns = 0
        self._enabled_ns = 0  # the last enable: states read before it do not latch
        self._state_hw_ns: int | None = None
        self._state_advanced_ns: int | None = None
        self._planner_alive = False  # the planner's heartbeat was fresh at the last decision
        self._ft_seen_ns: int | None = None  # the last decision with a fresh F/T reading since the last loss
        self._ft_seq = 0  # the seq of the newest F/T reading decided on (a lower one: its reader restarted)

    def offer(self, target: msg.ArmTarget | None, now_ns: int) -> tuple[str, str] | None:
        """Consider the newest target message at ``now_ns``; returns ``(error kind, text)`` to count, or None.

        A target not newer than the last one seen is ignored. A new invalid one is refused (``target_refused``):
        the current target is dropped (the arm stops and holds) and the rest of its goal is not acted on. A valid
        one of a goal started too early (see the class) is not acted on (``old_goal``). Otherwise it replaces the
        current target, its deadline clamped to ``limits.max_target_lead_s`` after ``now_ns``; a goal's end
        (``ArmTarget.goal_end``) drops the target instead, and the arm stops with the cause "goal OUTCOME"."""
        if target is None or target.stamp_ns <= self._newest_target_ns:
            return None
        self._newest_target_ns = target.stamp_ns
        reason = check_target(target.tcp_pose, self.limits, self.nominal_tcp)
        if reason is None and target.arm != self.arm:
            reason = f"target is for arm {target.arm!r}, not {self.arm!r}"
        if reason is not None:
            self._refuse(target, reason)
            return "target_refused", reason
        if target.goal_started_ns <= self.goal_floor_ns:
            text = f"target of a goal started before {self.goal_floor_cause}: not acted on; start a new goal"
            self.target = None
            if not self.servoing and self.external is None:
                self.reason, self.owner = text, "stack"
            return "old_goal", text
        if target.goal_end:
            self.target, self._goal_end = None, f"goal {target.goal_end}"
            return None
        self.target, self._refusal, self._goal_end = target, None, None
        self.deadline_ns = clamped_deadline_ns(target.deadline_ns, now_ns, self.limits)
        return None

    def _refuse(self, target: msg.ArmTarget, reason: str) -> None:
        self.target, self._refusal = None, f"target refused: {reason}"
        if target.goal_started_ns > self.goal_floor_ns:
            self.goal_floor_ns, self.goal_floor_cause = target.goal_started_ns, "a refused target of that goal"

    def observe(self, state: ArmState) -> None:
        """Note a state read from the driver: when its controller stamp (or, without one, its host stamp) changed,
        the state advanced at ``state.stamp_ns``; a controller stop of its own latches as external; a new link to
        the controller (a reconnect) voids the goals started before it."""
        stamp = state.hw_stamp_ns if state.hw_stamp_ns is not None else state.stamp_ns
        if stamp != self._state_hw_ns:
            self._state_hw_ns, self._state_advanced_ns = stamp, state.stamp_ns
        if state.controller_stop and self.external is None and state.stamp_ns > self._enabled_ns:
            self.external = external_cause(state.controller_stop)
        if state.link_since_ns > self._link_since_ns:
            self._link_since_ns = state.link_since_ns
            if state.link_since_ns > self.goal_floor_ns:
                self.goal_floor_ns, self.goal_floor_cause = state.link_since_ns, "the reconnect to the controller"
                self.target = None

    def _planner_lost(self, now_ns: int, heartbeat_ns: int | None) -> str:
        """Why the planner counts as lost at ``now_ns``, or "": its heartbeat (stamp ``heartbeat_ns``, ns; None:
        none) was fresh (within ``limits.heartbeat_timeout_s``) at an earlier decision and is now gone or older than
        ``limits.planner_lost_s`` (a dead or frozen planner, a cut link). Then every goal started before ``now_ns``
        has ended: a planner that runs on does not resume it. A shorter gap only stops the arm (the watchdog) until
        the goal's next fresh target, and a heartbeat never seen since the start ends nothing."""
        age_s = None if heartbeat_ns is None else (now_ns - heartbeat_ns) * 1e-9
        if age_s is not None and age_s <= self.limits.heartbeat_timeout_s:
            self._planner_alive = True
            return ""
        if not self._planner_alive or (age_s is not None and age_s <= self.limits.planner_lost_s):
            return ""
        self._planner_alive = False
        if now_ns > self.goal_floor_ns:
            self.goal_floor_ns, self.goal_floor_cause = now_ns, PLANNER_LOST
        self.target = None
        seen = "gone" if age_s is None else f"{age_s:.3f} s old"
        return (f"planner lost: its heartbeat is {seen} (limit {self.limits.planner_lost_s} s); its goal ended, "
                "a new goal must be started")

    def _ft_lost(self, now_ns: int, reading: bool, seq: int | None) -> str:
        """Why the F/T readings count as lost at ``now_ns``, or "": a decision had a fresh reading (``reading``:
        a finite wrench within ``WRENCH_MAX_AGE_S``, tared or not) and none came for longer than
        ``limits.sensor_lost_s`` since (a dead or unplugged reader), or this reading's ``seq`` is lower than the
        last one's (a restarted reader numbers from 1). Then every goal started before ``now_ns`` has ended, so a
        reader that comes back does not resume it. A shorter gap only stops the arm (the watchdog's "no fresh F/T
        reading") until the goal's next fresh target; readings never seen since the start end nothing."""
        if reading:
            restarted = seq is not None and seq < self._ft_seq
            self._ft_seen_ns, self._ft_seq = now_ns, self._ft_seq if seq is None else seq
            if not restarted:
                return ""
            why = "its reader restarted (its wrenches are numbered from 1 again)"
        elif self._ft_seen_ns is None or (now_ns - self._ft_seen_ns) * 1e-9 <= self.limits.sensor_lost_s:
            return ""
        else:
            why = f"none for {(now_ns - self._ft_seen_ns) * 1e-9:.3f} s (limit {self.limits.sensor_lost_s} s)"
            self._ft_seen_ns = None
        if now_ns > self.goal_floor_ns:
            self.goal_floor_ns, self.goal_floor_cause = now_ns, FT_LOST
        self.target = None
        return f"F/T readings lost: {why}; its goal ended, a new goal must be started"

    @staticmethod
    def enable_refusal(state: ArmState | None) -> str | None:
        """Why a person's ``arm enable`` must be refused with the controller in ``state`` (None: unreadable), or
        None: no state, a safety stop the controller still reports, an unpowered arm."""
        if state is None:
            return "no arm state: the controller's stop cannot be checked"
        if state.safety_flags:
            return (f"the controller still reports a {state.safety_flags[0]}: inspect its cause and clear it on the "
                    "pendant first")
        if state.controller_stop.startswith("robot mode"):
            return f"the controller reports {state.controller_stop}: power the arm on first"
        return None

    def enable(self, now_ns: int) -> str:
        """A person re-enabled the arm at ``now_ns`` (after ``enable_refusal`` allowed it): the latched external
        stop is cleared (returned; "" when none was latched) and only goals started after ``now_ns`` move the
        arm."""
        cleared, self.external, self._enabled_ns = self.external or "", None, now_ns
        self.goal_floor_ns, self.goal_floor_cause = max(self.goal_floor_ns, now_ns), "the last arm enable"
        self._refusal = None
        self.halt(NO_TARGET)
        self.reason, self.owner, self.holding = NO_TARGET, "stack", False
        return cleared

    def decide(self, now_ns: int, state: ArmState | None, driver_error: str | None, heartbeat_ns: int | None,
               force: np.ndarray | None, stopping: bool = False, untared: bool = False,
               ft_seq: int | None = None) -> Decision:
        """This period's decision at ``now_ns``, from the driver's ``state`` (None when reading it failed with
        ``driver_error``), the planner heartbeat's stamp (ns), the contact force on the bubble ``(3,)`` (N, TCP
        frame; None when unknown), whether a stop is still in flight (then nothing is commanded until it ends) and
        whether that force is ``untared``: the F/T reader has no bias to remove, so the force is off by the
        sensor's unknown offset and the force limit cannot be kept (the arm holds, cause ``UNTARED_FT``). ft_seq: the
        ``seq`` of the wrench message behind ``force`` (None: not known), so a restarted reader is noticed."""
        ft_lost = self._ft_lost(now_ns, force is not None and bool(np.isfinite(force).all()), ft_seq)
        if untared:
            force = None
        force_n = None if force is None else float(np.linalg.norm(force))
        if force_n is not None and not math.isfinite(force_n):  # no reading to keep the limit by
            force, force_n = None, None
        if force_n is not None and force_n > self.limits.max_force_n:
            self.force_limited = True
        elif force_n is not None and force_n < self.limits.release_level_n:
            self.force_limited = False
        refusal = ""
        untared_reason = UNTARED_FT if untared else None
        planner_lost = self._planner_lost(now_ns, heartbeat_ns)
        early = (self._external_reason() or planner_lost or ft_lost or driver_error or self._refusal or untared_reason
                 or self._goal_end)
        reason = early or watchdog(
            now_ns, None if self.target is None else self.deadline_ns, heartbeat_ns, self._state_advanced_ns,
            force_n, self.limits, None if self.target is None else self.target.plan_done_ns)
        hold = reason is not None and early is None and self._only_late(now_ns, state, heartbeat_ns, force_n)
        if hold:
            reason = f"{HOLD} {(now_ns - self.deadline_ns) * 1e-9:.3f} s ago (waiting for the planner's next target)"
        if reason is None and stopping:
            reason = STOPPING
        if reason is None and state is not None and not self.servoing:
            path = check_path(state.tcp_pose, self.target.tcp_pose, self.limits, self.nominal_tcp)
            if path is not None:
                refusal = path
                self._refuse(self.target, path)
                reason = self._refusal
        if reason is None and state is not None and self.force_limited:
            away = retreat_refusal(state.tcp_pose, self.target.tcp_pose, force)
            if away is not None:
                reason = (f"contact force {force_n:.1f} N over the limit {self.limits.max_force_n} N (until below "
                          f"{self.limits.release_level_n} N only a retreat is servoed): {away}")
        if reason is None and state is not None:
            if self.servoing:  # on from the last command, as far as the time since it allows
                start, dt_s = self._command, min((now_ns - self._command_ns) * 1e-9, MAX_STEP_PERIODS * self.period_s)
            else:
                start, dt_s = state.tcp_pose, self.period_s
            self._command = interpolate(start, self.target.tcp_pose, dt_s, self.limits)
            self._command_ns, self.servoing, self.reason, self.owner = now_ns, True, "", ""
            self.holding = False
            return Decision(self._command, stop=False, reason="")
        was_servoing = self.servoing
        self.halt(reason or "no arm state", hold=hold)
        moving = state is not None and is_moving(state.tcp_speed)
        return Decision(None, stop=was_servoing or (moving and not stopping), reason=self.reason, refusal=refusal,
                        planner_lost=planner_lost, ft_lost=ft_lost, hold_started=hold)

    def _only_late(self, now_ns: int, state: ArmState | None, heartbeat_ns: int | None, force_n: float | None) -> bool:
        """Whether the only stop at ``now_ns`` is the servoed target's passed deadline (then the stop is a hold): the
        arm servoes, its state was read, the force is not over the limit, and with the deadline still ahead the
        watchdog would let it servo on."""
        if (not self.servoing or self.target is None or state is None or self.force_limited
                or now_ns <= self.deadline_ns):
            return False
        return watchdog(now_ns, now_ns, heartbeat_ns, self._state_advanced_ns, force_n, self.limits,
                        self.target.plan_done_ns) is None

    def _external_reason(self) -> str | None:
        if self.external is None:
            return None
        return f"external stop: {self.external} (latched until `hydrosoft-stack arm enable {self.arm}`)"

    def holding_at_rest(self, state: ArmState | None, stopping: bool) -> bool:
        """Whether the arm is held with nothing to do: not servoing, no target, no stop in flight, and ``state``
        (this period's, None when reading it failed) shows it at rest. Then nothing can change until a target
        arrives, and the commander may run at its idle rate."""
        return (not self.servoing and self.target is None and not stopping and state is not None
                and not is_moving(state.tcp_speed))

    def halt(self, reason: str, hold: bool = False) -> None:
        """Hold the arm for ``reason`` (``hold``: a hold, the target's deadline passed; see the class). This spends
        the target (only a fresh target that can be servoed on when it arrives resumes), except while the previous
        stop is in flight (``STOPPING``): a target that arrives then waits for the stop's end, checked again each
        period. The reported ``reason`` stays that of the stop: "no target" and "stopping" (what every stop leaves
        behind) do not replace it; an external stop replaces any other."""
        if reason not in (NO_TARGET, STOPPING) or self.servoing:
            self.reason, self.holding = reason, hold
            self.owner = "external" if reason == self._external_reason() else "stack"
        if reason != STOPPING:
            self.target = None
        self.servoing, self._command = False, None


def external_cause(controller_stop: str) -> str:
    """The named cause of an external stop from the controller's ``ArmState.controller_stop``. A stopped program
    is not told apart from its cause: the pendant, the dashboard, or the controller's watchdog after a starved
    commander all leave the same state, and none of them is undone without a person."""
    if controller_stop == "program stopped":
        return "program stopped (not by the stack: pendant, dashboard, or the controller's watchdog)"
    return controller_stop


class Commander:
    """The commander's I/O: the driver, the subscriptions, the ArmState publisher, the ``arm enable`` requests and
    the stop task."""

    def __init__(self, service: Service, config: StackConfig, arm: str, driver: Arm) -> None:
        self.service, self.arm, self.driver = service, arm, driver
        self.logic = ServoLogic(config.limits, arm, config.arm(arm).nominal_tcp, started_ns=time.monotonic_ns())
        self.inputs = service.subscriber([config.endpoint("planner"), config.endpoint("planner", "status")],
                                         topics=[f"arm_target/{arm}", "heartbeat/planner"], background=True)
        self.wrenches = service.subscriber(config.endpoint(f"ft_reader-{arm}"), [f"wrench/{arm}"],
                                           rcvhwm=WRENCH_QUEUE)
        self.out = service.publisher(config.endpoint(f"{MODULE}-{arm}"))
        self.requests = service.request_server(config.endpoint(f"{MODULE}-{arm}", "cmd"), self.handle)
        self._stop_task: asyncio.Task[None] | None = None
        self._target_arrived = self.inputs.arrival(f"arm_target/{arm}")
        self._latched_reported: str | None = None
        self.stop_confirmed = False  # the shutdown saw the arm at rest after its stop
        self.idle = False  # the last tick found the arm held at rest with no target

    def _newest(self, topic: str, max_age_s: float, kind: type[msg.Message]) -> Received | None:
        """The newest target or heartbeat on ``topic`` within ``max_age_s`` (s) with its stamp, or None."""
        try:
            return self.inputs.latest(topic, max_age_s, kind)
        except Stale:
            return None

    def _wrench(self) -> msg.Wrench | None:
        """The newest wrench (force in N, TCP frame), read now, or None when there is none within
        ``WRENCH_MAX_AGE_S``."""
        try:
            return self.wrenches.latest(f"wrench/{self.arm}", WRENCH_MAX_AGE_S, msg.Wrench).value
        except Stale:
            return None

    async def tick(self) -> None:
        """One servo period: read, decide, command or stop, publish."""
        self._target_arrived.clear()
        target = self._newest(f"arm_target/{self.arm}", ANY_AGE_S, msg.ArmTarget)
        counted = self.logic.offer(None if target is None else target.value, time.monotonic_ns())
        if counted is not None:
            self.service.count_error(*counted)
        state, driver_error = None, None
        try:
            state = await self.driver.read_state()
            self.logic.observe(state)
        except DriverError as err:
            driver_error = f"arm driver: {err}"
            self.service.count_error("arm_driver", str(err))
        await self._report_latch()
        wrench = self._wrench()  # before the decision's time: reading the wrenches queued since the last tick
        force = None if wrench is None else np.asarray(wrench.wrench[:3], dtype=np.float64)
        heartbeat = self._newest("heartbeat/planner", ANY_AGE_S, msg.Heartbeat)
        decision = self.logic.decide(time.monotonic_ns(), state, driver_error,
                                     None if heartbeat is None else heartbeat.stamp_ns, force, stopping=self.stopping,
                                     untared=wrench is not None and not wrench.tared,
                                     ft_seq=None if wrench is None else wrench.seq)
        if decision.refusal:
            self.service.count_error("target_refused", decision.refusal)
        if decision.planner_lost:
            self.service.count_error("planner_lost", decision.planner_lost)
        if decision.ft_lost:
            self.service.count_error("ft_lost", decision.ft_lost)
        if decision.hold_started:
            self.service.count_error("deadline_hold", decision.reason)
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
                servo_active=self.logic.servoing, holding=self.logic.holding, stop_reason=self.logic.reason,
                stop_owner=self.logic.owner,
                controller_stop=state.controller_stop, safety_flags=state.safety_flags,
                latched=self.logic.external is not None, hw_stamp_ns=state.hw_stamp_ns,
                goal_floor_ns=self.logic.goal_floor_ns, goal_floor_cause=self.logic.goal_floor_cause),
                f"arm_state/{self.arm}")

    async def _report_latch(self) -> None:
        """Make a latched external stop visible to ``hydrosoft-stack status``: counted once as ``external_stop``
        (its text the newest error) and the service ``degraded`` while it lasts, ``ready`` again after ``arm
        enable``."""
        external = self.logic.external
        if external is not None and external != self._latched_reported:
            self.service.count_error("external_stop", f"{external}: the arm is held until a person runs "
                                                      f"`hydrosoft-stack arm enable {self.arm}`")
            await self.service.set_state("degraded")
        elif external is None and self._latched_reported is not None and self.service.state == "degraded":
            await self.service.set_state("ready")
        self._latched_reported = external

    async def handle(self, request: msg.Request) -> msg.Reply:
        """Answer an ``EnableArm`` request (every other request is refused): check the controller, restart its
        program when it is not running, then clear the latched stop. Logged either way."""
        if not isinstance(request, msg.EnableArm):
            return request.reply(ok=False, error=f"unsupported request {type(request).__name__}")
        if request.arm != self.arm:
            return msg.ArmEnableReply(ok=False, error=f"this is the commander of arm {self.arm!r}, not {request.arm!r}")
        try:
            state = await self.driver.read_state()
        except DriverError as err:
            state = None
            self.service.count_error("arm_driver", str(err))
        refusal = self.logic.enable_refusal(state)
        if refusal is None and state.controller_stop:
            refusal = await self._restart_program()
        if refusal is not None:
            self.service.log.warning("arm enable by %r refused: %s", request.by or request.source, refusal)
            return msg.ArmEnableReply(ok=False, error=refusal)
        cleared = self.logic.enable(time.monotonic_ns())
        self.service.log.warning("arm enabled by %r (cleared: %s); only a goal started from now moves it",
                                 request.by or request.source, cleared or "no latched stop")
        return msg.ArmEnableReply(ok=True, cleared=cleared)

    async def _restart_program(self) -> str | None:
        """Restart the controller's program for ``arm enable`` and wait (``ENABLE_RUNNING_TIMEOUT_S``) until the
        state shows it running; why not, or None."""
        try:
            await self.driver.restart_script()
            deadline_ns = time.monotonic_ns() + int(ENABLE_RUNNING_TIMEOUT_S * 1e9)
            while (state := await self.driver.read_state()).controller_stop:
                if time.monotonic_ns() > deadline_ns:
                    return f"the controller still reports {state.controller_stop} after the program's restart"
                await asyncio.sleep(self.logic.period_s)
        except DriverError as err:
            return f"the controller's program did not restart: {err}"
        self.service.log.info("restarted the controller's program for arm enable")
        return None

    async def rest(self, period_s: float) -> None:
        """Wait ``period_s`` (s), or less when a target arrives meanwhile (or arrived since this tick began)."""
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(period_s):
                await self._target_arrived.wait()

    @property
    def stopping(self) -> bool:
        """A stop is in flight."""
        return self._stop_task is not None and not self._stop_task.done()

    def _start_stop(self) -> None:
        """Start ``driver.stop()`` beside the loop (it returns once the arm is at rest), so that ArmState keeps
        flowing meanwhile."""
        if not self.stopping:
            self.service.log.warning("stopping the arm (%s): %s", self.logic.owner or "stack", self.logic.reason)
            self._stop_task = asyncio.create_task(self._stop(), name=f"{self.service.name}.stop")

    async def _stop(self) -> None:
        try:
            await self.driver.stop()
        except DriverError as err:
            self.service.count_error("stop_failed", str(err))

    async def stop_and_confirm(self) -> None:
        """Stop the arm and wait (at most ``REST_CONFIRM_TIMEOUT_S``) until its state shows it at rest; log which,
        and set ``stop_confirmed``."""
        self.logic.halt("shutdown")
        if self.stopping:
            await self._stop_task
        await self._stop()
        deadline_ns = time.monotonic_ns() + int(REST_CONFIRM_TIMEOUT_S * 1e9)
        while True:
            try:
                if not is_moving((await self.driver.read_state()).tcp_speed):
                    self.stop_confirmed = True
                    self.service.log.info("arm stopped and at rest")
                    return
            except DriverError as err:
                self.service.count_error("arm_driver", str(err))
            if time.monotonic_ns() > deadline_ns:
                self.service.log.error("the arm was not seen at rest within %.1f s of its stop", REST_CONFIRM_TIMEOUT_S)
                return
            await asyncio.sleep(self.logic.period_s)


def driver_config(config: StackConfig, arm: str) -> URArmConfig:
    """The UR driver's settings for ``arm`` from the stack's limits: its servo and state rates are
    ``limits.servo_rate_hz``, its fastest TCP speed (which bounds how long a stop takes) ``limits.max_speed_m_s``
    and its state's maximum age ``limits.state_timeout_s``."""
    limits = config.limits
    return URArmConfig(host=config.arm(arm).ur_host, servo_rate_hz=limits.servo_rate_hz,
                       state_rate_hz=limits.servo_rate_hz, max_tcp_speed_m_s=limits.max_speed_m_s,
                       max_age_s=limits.state_timeout_s)


@dataclass
class ShutdownResult:
    """What the shutdown confirmed, for the exit code: ``stop_confirmed``, the arm was seen at rest after its
    stop."""

    stop_confirmed: bool = False


async def serve(service: Service, config: StackConfig, arm: str, result: ShutdownResult | None = None) -> None:
    """The service's main: connect the arm, then servo at ``limits.servo_rate_hz`` (``limits.idle_rate_hz`` while
    idle) and answer ``arm enable`` until cancelled; the shutdown's confirmation goes to ``result``."""
    from hydrosoft.drivers.ur.arm import URArm

    driver = URArm(driver_config(config, arm))
    await driver.connect()
    commander = Commander(service, config, arm, driver)

    async def shut_down() -> None:
        try:
            await commander.stop_and_confirm()
        finally:
            await driver.close()
            if result is not None:
                result.stop_confirmed = commander.stop_confirmed

    service.on_shutdown(shut_down)
    serving = service.supervise(asyncio.create_task(commander.requests.serve(), name=f"{service.name}.requests"))
    await service.ready()
    loop = asyncio.get_running_loop()
    period_s, idle_period_s = commander.logic.period_s, 1.0 / config.limits.idle_rate_hz
    next_s = loop.time()
    try:
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
    finally:
        serving.cancel()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments: CONFIG [--name MODULE-ARM] (``service_cli``)."""
    service_cli.add_arm_arguments(parser, MODULE)


def run(args: argparse.Namespace) -> int:
    """Run the service until SIGINT/SIGTERM; the exit code: 0 stopped with the arm seen at rest, 1 the service or
    its shutdown failed, 2 a bad config or name, ``EXIT_STOP_UNCONFIRMED`` (3) the arm was never seen at rest after
    its stop (the controller's own watchdog is then what stops it)."""
    result = ShutdownResult()
    code = service_cli.run_arm(args, MODULE, functools.partial(serve, result=result))
    return EXIT_STOP_UNCONFIRMED if code == 0 and not result.stop_confirmed else code


def main(argv: list[str] | None = None) -> int:
    return service_cli.main(MODULE, __doc__, argv, add_arguments, run)


if __name__ == "__main__":
    service_cli.exit_process(main())
