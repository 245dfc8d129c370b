"""``URArm.servo_to`` checks the controller right before each servoL, in one hop to the control thread.

The ur_rtde clients are fakes here (no controller, no socket): they record which thread called them and in what
order, and can report a stale stamp, a stop of the controller's own, a closed stream, or hang. Each case must end as
``servo_to`` always ended it: the same error, the same counter, and no servoL sent.
"""

from __future__ import annotations

import asyncio
import threading
import time

import numpy as np
import pytest

from hydrosoft.drivers.errors import DeviceFault, NotConnected, Stale
from hydrosoft.drivers.ur.arm import REALTIME_CALL_TIMEOUT_S, URArm
from hydrosoft.drivers.ur.config import URArmConfig
from hydrosoft.drivers.ur.safety_status import RobotMode, RuntimeState

HOME = np.array([0.3, -0.2, 0.4, 0.0, 0.0, 1.0, 0.0])
HOME_UR = [0.3, -0.2, 0.4, 0.0, np.pi, 0.0]
PROTECTIVE_STOP_BITS = 1 | 1 << 2  # normal mode and protective stop
HANG_S = REALTIME_CALL_TIMEOUT_S + 0.3  # a hung call returns this long after it started
#: Scheduling allowance of the timing bounds on two shared cores, s.
SLACK_S = 0.25


class FakeReceive:
    """The receive client: a fresh stream by default (its stamp follows the host clock), its calls logged with
    their thread's name; ``hang`` makes ``getTimestamp`` block until that event is set."""

    def __init__(self, log: list[tuple[str, str]]) -> None:
        self.log = log
        self.connected = True
        self.frozen_stamp_s: float | None = None  # a stalled stream repeats this stamp
        self.safety_bits = 1
        self.robot_mode = int(RobotMode.RUNNING)
        self.runtime_state = int(RuntimeState.PLAYING)
        self.hang: threading.Event | None = None

    def _note(self, name: str) -> None:
        self.log.append((name, threading.current_thread().name))

    def isConnected(self) -> bool:
        self._note("isConnected")
        return self.connected

    def getTimestamp(self) -> float:
        self._note("getTimestamp")
        if self.hang is not None:
            self.hang.wait(5.0)
        return time.monotonic() - 1000.0 if self.frozen_stamp_s is None else self.frozen_stamp_s

    def getActualTCPPose(self) -> list[float]:
        self._note("getActualTCPPose")
        return list(HOME_UR)

    def getActualTCPSpeed(self) -> list[float]:
        self._note("getActualTCPSpeed")
        return [0.0] * 6

    def getRuntimeState(self) -> int:
        self._note("getRuntimeState")
        return self.runtime_state

    def getSafetyStatusBits(self) -> int:
        self._note("getSafetyStatusBits")
        return self.safety_bits

    def getRobotMode(self) -> int:
        self._note("getRobotMode")
        return self.robot_mode


class FakeControl:
    """The control client: servoL logged with its thread's name and accepted; ``hang`` blocks it until set."""

    def __init__(self, log: list[tuple[str, str]]) -> None:
        self.log = log
        self.hang: threading.Event | None = None
        self.servo_calls = 0

    def servoL(self, pose, speed, accel, period_s, lookahead_s, gain) -> bool:
        self.log.append(("servoL", threading.current_thread().name))
        self.servo_calls += 1
        if self.hang is not None:
            self.hang.wait(5.0)
        return True


class Hops:
    """Counts the calls handed to a worker thread."""

    def __init__(self, thread) -> None:
        self.count = 0
        self._submit = thread.submit
        thread.submit = self.submit

    def submit(self, *args, **kwargs):
        self.count += 1
        return self._submit(*args, **kwargs)


@pytest.fixture
def rig():
    """A ``URArm`` whose clients are the fakes, its link up; the log of their calls; the hops per thread."""
    log: list[tuple[str, str]] = []
    arm = URArm(URArmConfig(host="127.0.0.9"))
    arm._receive, arm._control, arm._link_up = FakeReceive(log), FakeControl(log), True
    hops = {"receive": Hops(arm._receive_thread), "control": Hops(arm._control_thread)}
    try:
        yield arm, log, hops
    finally:
        for fake in (arm._receive, arm._control):
            if fake is not None and fake.hang is not None:
                fake.hang.set()
        arm._control_thread.shutdown(wait=True)
        arm._receive_thread.shutdown(wait=True)


def test_servo_to_reads_the_controller_checks_it_and_sends_servol_in_one_hop_to_the_control_thread(rig):
    arm, log, hops = rig
    reads: list[int] = []
    read_state = arm.read_state

    async def counted_read_state():
        reads.append(1)
        return await read_state()

    arm.read_state = counted_read_state
    asyncio.run(arm.servo_to(HOME))
    assert arm._control.servo_calls == 1 and arm.counters["servo_commands"] == 1
    assert (hops["receive"].count, hops["control"].count) == (0, 1)  # was a read_state hop, then a servoL hop
    assert not reads  # the commander's read of its tick is the only full read_state
    names = [name for name, _ in log]
    assert names[-1] == "servoL" and {"isConnected", "getTimestamp", "getSafetyStatusBits", "getRobotMode",
                                      "getRuntimeState"} <= set(names[:-1])
    assert {thread for _, thread in log} == {next(thread for name, thread in log if name == "servoL")}
    assert log[0][1].startswith("ur-control-")


def stalled(receive: FakeReceive) -> None:
    receive.frozen_stamp_s = time.monotonic() - 1000.0


@pytest.mark.parametrize("fault, error, text, counter", [
    ("stale", Stale, r"s old \(max_age_s 0.1 s\)", "stale"),
    ("protective stop", DeviceFault, "protective stop active; servoL not sent", "refused_safety_stop"),
    ("paused", DeviceFault, r"not running \(program paused\); servoL not sent", "refused_script_not_running"),
    ("powered off", DeviceFault, r"not running \(robot mode POWER_OFF\)", "refused_script_not_running"),
    ("stream closed", NotConnected, "the RTDE stream from the controller closed", "not_connected"),
])
def test_a_stale_stopped_or_closed_controller_gets_no_servol_and_the_named_error(rig, fault, error, text, counter):
    arm, _, _ = rig
    receive = arm._receive

    async def scenario():
        await arm.read_state()  # the stream's offset, as the commander's tick reads it
        last_command_ns = arm._last_command_ns
        if fault == "stale":
            stalled(receive)
            await arm.read_state()
            await asyncio.sleep(0.15)
        elif fault == "protective stop":
            receive.safety_bits = PROTECTIVE_STOP_BITS
        elif fault == "paused":
            receive.runtime_state = int(RuntimeState.PAUSED)
        elif fault == "powered off":
            receive.robot_mode = int(RobotMode.POWER_OFF)
        else:
            receive.connected = False
        with pytest.raises(error, match=text):
            await arm.servo_to(HOME)
        return last_command_ns

    last_command_ns = asyncio.run(scenario())
    assert arm._control.servo_calls == 0 and arm.counters[counter] == 1
    assert arm.counters["servo_commands"] == 0
    assert arm._last_command_ns == last_command_ns  # nothing went out: the watchdog's kicks go on as before
    assert arm._control_calls_in_flight == 0
    if fault == "stream closed":
        assert arm.counters["link_lost"] == 1 and not arm.connected


def test_a_hung_status_read_is_stale_within_the_realtime_limit_and_never_sends_servol_later(rig):
    arm, _, _ = rig
    arm._receive.hang = threading.Event()

    async def scenario():
        t0 = time.monotonic()
        with pytest.raises(Stale, match="did not answer"):
            await arm.servo_to(HOME)
        raised_s = time.monotonic() - t0
        arm._receive.hang.set()  # the read returns now: its servoL must still not go out
        await asyncio.sleep(0.2)
        return raised_s

    raised_s = asyncio.run(scenario())
    assert REALTIME_CALL_TIMEOUT_S <= raised_s < REALTIME_CALL_TIMEOUT_S + SLACK_S
    assert arm._control.servo_calls == 0 and arm.counters["stale"] == 1
    assert arm._control_calls_in_flight == 0


def test_a_hung_servol_is_a_command_timeout_counted_from_its_start(rig):
    arm, _, _ = rig
    arm._control.hang = threading.Event()
    threading.Timer(HANG_S, arm._control.hang.set).start()

    async def scenario():
        t0 = time.monotonic()
        with pytest.raises(DeviceFault, match=f"did not return within {REALTIME_CALL_TIMEOUT_S} s"):
            await arm.servo_to(HOME)
        return time.monotonic() - t0

    raised_s = asyncio.run(scenario())
    assert REALTIME_CALL_TIMEOUT_S <= raised_s < REALTIME_CALL_TIMEOUT_S + SLACK_S
    assert arm._control.servo_calls == 1 and arm.counters["command_timeout"] == 1
    assert arm.counters["servo_commands"] == 0 and arm._control_calls_in_flight == 0
    assert arm._last_command_ns > 0  # servoL went out: it counts as a command for the watchdog's kicks


def test_a_servo_to_cancelled_while_waiting_is_cancelled_and_sends_nothing_after(rig):
    arm, _, _ = rig
    arm._receive.hang = threading.Event()

    async def scenario():
        task = asyncio.create_task(arm.servo_to(HOME))
        await asyncio.sleep(0.05)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        arm._receive.hang.set()
        await asyncio.sleep(0.2)

    asyncio.run(scenario())
    assert arm._control.servo_calls == 0 and arm._control_calls_in_flight == 0
