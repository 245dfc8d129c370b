"""The real ur_rtde 1.6.5 client and ``URArm`` against the simulated controller (one per module, on its own 127.0.0.N).

The tests share one simulator and one connected arm, so they run in file order and each leaves the controller
healthy for the next; the last one closes the arm. They run twice: on a controller cycling at an e-Series' 500 Hz
and at a CB3's 125 Hz (the sim stack's ``sim.ur_tick_hz``), where every round trip through the script takes up to
four times longer.
"""

from __future__ import annotations

import asyncio
import os
import sys
import threading
import time

import numpy as np
import pytest
import rtde_control
import rtde_receive

from hydrosoft.drivers.errors import DeviceFault, NotConnected, Stale
from hydrosoft.drivers.ur.arm import POLL_SLACK_FRACTION, URArm
from hydrosoft.drivers.ur.config import URArmConfig
from hydrosoft.drivers.ur.probe import probe_rtde_stream
from hydrosoft.drivers.ur.pose import quat_conjugate, quat_from_rotvec, quat_multiply, rotvec_from_quat, ur_to_pose

CALL_TIMEOUT_S = 10.0
MAX_AGE_S = 0.1
SERVO_PERIOD_S = 1.0 / 125.0
POLL_S = 0.005


@pytest.fixture(scope="module", params=[500.0, 125.0], ids=["500hz", "125hz"])
def tick_hz(request) -> float:
    return request.param


@pytest.fixture(scope="module")
def arm(sim, loop_thread):
    config = URArmConfig(host=sim.host, max_age_s=MAX_AGE_S, reconnect_initial_s=0.1, reconnect_max_s=0.5)
    driver = URArm(config)
    loop_thread.run(driver.connect(), CALL_TIMEOUT_S)
    yield driver
    loop_thread.run(driver.close(), CALL_TIMEOUT_S)


def servo_count(sim) -> int:
    """servoL packages the simulated script has acted on."""
    return sim.state()["counters"].get("commands[24]", 0)


def settled_servo_count(sim) -> int:
    """``servo_count`` once a servoL sent earlier has been acted on: unchanged over 20 ms (two 125 Hz ticks)."""
    count = servo_count(sim)
    while True:
        time.sleep(0.02)
        if (now := servo_count(sim)) == count:
            return count
        count = now


def wait_servo_count(sim, expected: int, timeout_s: float = 0.5) -> int:
    """``servo_count`` once it reaches ``expected`` (the script acts on its next tick), or when time is up."""
    deadline = time.monotonic() + timeout_s
    while (count := servo_count(sim)) < expected and time.monotonic() < deadline:
        time.sleep(POLL_S)
    return count


async def servo_path(arm: URArm, target: np.ndarray, duration_s: float, hold_s: float) -> None:
    """servo_to at 125 Hz along a straight line (position lerp, orientation slerp) to ``target``, then hold it."""
    start = (await arm.read_state()).tcp_pose
    delta = quat_multiply(target[3:], quat_conjugate(start[3:]))
    delta_rotvec = rotvec_from_quat(delta)
    steps = round(duration_s / SERVO_PERIOD_S)
    loop = asyncio.get_running_loop()
    next_t = loop.time()
    for i in range(1, steps + round(hold_s / SERVO_PERIOD_S) + 1):
        f = min(1.0, i / steps)
        pose = np.concatenate((start[:3] + f * (target[:3] - start[:3]),
                               quat_multiply(quat_from_rotvec(f * delta_rotvec), start[3:])))
        await arm.servo_to(pose)
        next_t += SERVO_PERIOD_S
        await asyncio.sleep(max(0.0, next_t - loop.time()))


async def wait_for_state(arm: URArm, predicate, timeout_s: float, tolerate: tuple[type[Exception], ...] = ()):
    """Poll ``read_state`` until ``predicate(state)`` and return that state; ``tolerate``d errors are retried."""
    deadline = time.monotonic() + timeout_s
    last: object = None
    while time.monotonic() < deadline:
        try:
            last = await arm.read_state()
            if predicate(last):
                return last
        except tolerate as exc:
            last = exc
        await asyncio.sleep(POLL_S)
    raise TimeoutError(f"state never satisfied the condition within {timeout_s} s; last {last!r}")


def test_connect_to_an_absent_controller_names_host_and_port(loop_thread, free_host):
    host = free_host
    driver = URArm(URArmConfig(host=host))
    with pytest.raises(NotConnected, match=rf"{host}.*RTDE port 30004.*refused"):
        loop_thread.run(driver.connect(), CALL_TIMEOUT_S)
    loop_thread.run(driver.close(), CALL_TIMEOUT_S)


def test_connect_in_local_mode_says_to_enable_remote_control(loop_thread, start_simulator, free_host):
    start_simulator(free_host, "--local-mode")
    driver = URArm(URArmConfig(host=free_host))
    with pytest.raises(NotConnected, match="control interface failed to start.*enable remote control"):
        loop_thread.run(driver.connect(), CALL_TIMEOUT_S)
    loop_thread.run(driver.close(), CALL_TIMEOUT_S)


def test_receive_interface_reads_the_simulated_pose(sim):
    pose = ur_to_pose([0.31, -0.21, 0.41, 0.1, 3.0, -0.05])
    sim.request("impose_pose", pose=pose.tolist())
    receive = rtde_receive.RTDEReceiveInterface(sim.host, -1.0, ["timestamp", "actual_TCP_pose", "runtime_state"])
    try:
        np.testing.assert_allclose(ur_to_pose(receive.getActualTCPPose()), pose, atol=1e-12)
        assert receive.getRuntimeState() == 1  # no program yet
        first = receive.getTimestamp()
        time.sleep(0.05)
        assert receive.getTimestamp() > first
    finally:
        receive.disconnect()
    with pytest.raises(RuntimeError, match="not found"):
        rtde_receive.RTDEReceiveInterface(sim.host, -1.0, ["timestamp", "no_such_variable"])
    assert sim.state()["counters"]["rtde_output_not_found"] == 1


def test_arm_state_matches_the_simulator_and_inputs_are_owned(sim, arm, loop_thread):
    state = loop_thread.run(arm.read_state(), CALL_TIMEOUT_S)
    assert state.running and not state.protective_stop and not state.emergency_stop
    np.testing.assert_allclose(state.tcp_pose, sim.state()["pose"], atol=1e-9)
    assert state.hw_stamp_ns is not None and state.hw_stamp_ns > 0
    assert sim.state()["watchdog_period_s"] == pytest.approx(0.25)
    with pytest.raises(RuntimeError, match="already in use"):
        rtde_control.RTDEControlInterface(sim.host)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="timer slack is a Linux prctl")
def test_the_clients_polling_threads_sleep_with_the_timer_slack_and_the_python_threads_keep_theirs(arm):
    def slack_ns(tid: int) -> int:
        with open(f"/proc/{tid}/timerslack_ns") as file:
            return int(file.read())

    default_ns = slack_ns(threading.main_thread().native_id)
    expected_ns = round(1e9 * POLL_SLACK_FRACTION / arm.config.state_rate_hz)
    assert arm.config.control_rate_hz == arm.config.state_rate_hz and expected_ns != default_ns
    python_ids = {thread.native_id for thread in threading.enumerate()}
    slack = {int(tid): slack_ns(int(tid)) for tid in os.listdir("/proc/self/task")}
    slacked = [tid for tid, ns in slack.items() if ns == expected_ns]
    assert len(slacked) >= 2  # the receive client's and the control client's polling threads (and any they made)
    assert not python_ids & set(slacked)
    assert all(slack[tid] == default_ns for tid in python_ids if tid in slack)  # the constructing threads restored


def test_the_state_streams_at_the_configured_rate_not_the_controllers_fastest(sim, arm, loop_thread):
    """URArmConfig.state_rate_hz (125 Hz by default) is what the receive interface asks for: the controller's
    timestamps of successive states are 8 ms apart, not the 2 ms of its 500 Hz cycle. The control interface asks
    for control_rate_hz (125 Hz by default) too."""

    async def stamps(seconds: float) -> list[int]:
        seen = []
        until = time.monotonic() + seconds
        while time.monotonic() < until:
            stamp = (await arm.read_state()).hw_stamp_ns
            if not seen or stamp != seen[-1]:
                seen.append(stamp)
            await asyncio.sleep(0.001)
        return seen

    gaps_ms = np.diff(loop_thread.run(stamps(0.5), CALL_TIMEOUT_S)) / 1e6
    assert len(gaps_ms) >= 20 and np.median(gaps_ms) == pytest.approx(8.0, abs=0.5), gaps_ms
    assert sim.state()["output_rates_hz"] == [125.0, 125.0]  # the arm's two clients
    with pytest.raises(ValueError, match="state_rate_hz must be at most 500"):
        URArmConfig(host="127.0.0.9", state_rate_hz=1000.0)
    with pytest.raises(ValueError, match="control_rate_hz must be at most 500"):
        URArmConfig(host="127.0.0.9", control_rate_hz=501.0)


def test_servo_reaches_the_target(sim, arm, loop_thread):
    start = loop_thread.run(arm.read_state(), CALL_TIMEOUT_S).tcp_pose
    target = start.copy()
    target[:3] += [0.04, -0.03, 0.02]
    target[3:] = quat_multiply(quat_from_rotvec([0.0, 0.0, 0.2]), start[3:])
    loop_thread.run(servo_path(arm, target, duration_s=0.5, hold_s=0.5), CALL_TIMEOUT_S)
    final = np.array(sim.state()["pose"])
    assert np.linalg.norm(final[:3] - target[:3]) < 1e-3
    assert abs(abs(float(np.dot(final[3:], target[3:]))) - 1.0) < 1e-5  # within about 0.5 deg
    assert arm.counters["servo_commands"] == 124  # 62 steps along the path, 62 holding


def test_stop_brings_the_tcp_to_rest(sim, arm, loop_thread):
    start = loop_thread.run(arm.read_state(), CALL_TIMEOUT_S).tcp_pose
    far = start.copy()
    far[0] += 0.2
    moving = asyncio.run_coroutine_threadsafe(servo_path(arm, far, duration_s=2.0, hold_s=0.0), loop_thread.loop)
    time.sleep(0.3)
    moving.cancel()
    assert np.linalg.norm(sim.state()["twist"][:3]) > 0.02
    loop_thread.run(arm.stop(), CALL_TIMEOUT_S)
    at_stop = sim.state()
    assert np.linalg.norm(at_stop["twist"]) == 0.0
    time.sleep(0.1)
    np.testing.assert_allclose(sim.state()["pose"], at_stop["pose"], atol=1e-12)
    assert arm.counters["stops"] == 1
    loop_thread.run(arm.stop(), CALL_TIMEOUT_S)  # repeatable


def test_stream_stall_raises_stale_within_max_age(sim, arm, loop_thread):
    """The stall starts once the client has seen the script ready again after the last test's stop (a watchdog kick
    went out after it). A stall that starts before is another case: ur_rtde then spins on its stale copy of the
    handshake register for every kick, none goes out, and the script's own watchdog stops the program, which is
    the safe end (at 125 Hz the script's ready comes up to 16 ms after the stop's clear: the test's stall request
    used to land first, every time)."""

    async def stall_and_watch():
        await wait_for_state(arm, lambda s: True, 1.0)
        kicks = arm.counters["watchdog_kicks"]
        while arm.counters["watchdog_kicks"] == kicks:
            await asyncio.sleep(POLL_S)
        before = servo_count(sim)
        sim.request("stall", duration_s=0.6)
        t0 = time.monotonic()
        while True:
            try:
                await arm.read_state()
            except Stale:
                break
            await asyncio.sleep(POLL_S)
        detected_s = time.monotonic() - t0
        with pytest.raises(NotConnected, match="stalled"):  # a reconnect now would not start a client
            await probe_rtde_stream(sim.host, 0.2)
        with pytest.raises(Stale):
            await arm.servo_to(np.array(sim.state()["pose"]))
        assert wait_servo_count(sim, before + 1, timeout_s=0.1) == before  # nothing commanded on stale data
        recovered = await wait_for_state(arm, lambda s: s.running, 2.0, tolerate=(Stale,))
        return detected_s, time.monotonic() - t0, recovered

    detected_s, recovered_s, _ = loop_thread.run(stall_and_watch(), CALL_TIMEOUT_S)
    assert detected_s < MAX_AGE_S + 0.05  # not ur_rtde's 2.5 s
    assert recovered_s < 1.5
    assert sim.state()["faults"]["stall"] == 1
    assert arm.counters["stale"] >= 2  # read_state and servo_to
    assert arm.counters["link_lost"] == 0


def test_protective_stop_refuses_commands_until_unlocked(sim, arm, loop_thread, dashboard):
    before = servo_count(sim)
    sim.request("protective_stop")
    state = loop_thread.run(wait_for_state(arm, lambda s: s.protective_stop, 1.0), CALL_TIMEOUT_S)
    with pytest.raises(DeviceFault, match="protective stop"):
        loop_thread.run(arm.servo_to(state.tcp_pose), CALL_TIMEOUT_S)
    loop_thread.run(arm.stop(), CALL_TIMEOUT_S)  # the controller already stopped the arm: nothing to send
    assert wait_servo_count(sim, before + 1, timeout_s=0.1) == before
    assert sim.state()["faults"]["protective_stop"] == 1
    assert arm.counters["refused_safety_stop"] == 1
    assert dashboard(sim.host, "unlock protective stop") == "Protective stop releasing"
    state = loop_thread.run(wait_for_state(arm, lambda s: not s.protective_stop, 1.0), CALL_TIMEOUT_S)
    loop_thread.run(arm.servo_to(state.tcp_pose), CALL_TIMEOUT_S)
    assert wait_servo_count(sim, before + 1) == before + 1


def test_a_safeguard_stop_and_a_pause_are_named_in_the_state_and_refuse_commands(sim, arm, loop_thread, dashboard):
    before = servo_count(sim)
    sim.request("safeguard_stop")
    state = loop_thread.run(wait_for_state(arm, lambda s: s.controller_stop, 1.0), CALL_TIMEOUT_S)
    assert state.controller_stop == "safeguard stop" and state.safety_flags == ("safeguard stop",)
    with pytest.raises(DeviceFault, match="safeguard stop"):
        loop_thread.run(arm.servo_to(state.tcp_pose), CALL_TIMEOUT_S)
    with pytest.raises(DeviceFault, match="safeguard stop"):
        loop_thread.run(arm.restart_script(), CALL_TIMEOUT_S)
    sim.request("release_safety_stop")
    loop_thread.run(wait_for_state(arm, lambda s: not s.controller_stop, 1.0), CALL_TIMEOUT_S)
    assert dashboard(sim.host, "pause") == "Pausing program"
    state = loop_thread.run(wait_for_state(arm, lambda s: s.controller_stop, 1.0), CALL_TIMEOUT_S)
    assert state.controller_stop == "program paused" and not state.running and state.safety_flags == ()
    with pytest.raises(DeviceFault, match="program paused"):
        loop_thread.run(arm.servo_to(state.tcp_pose), CALL_TIMEOUT_S)
    assert wait_servo_count(sim, before + 1, timeout_s=0.1) == before
    loop_thread.run(arm.restart_script(), CALL_TIMEOUT_S)
    state = loop_thread.run(wait_for_state(arm, lambda s: not s.controller_stop, 1.0), CALL_TIMEOUT_S)
    assert state.link_since_ns > 0


def test_stopped_script_is_detected_and_restarted(sim, arm, loop_thread):
    before = servo_count(sim)
    refused_before = arm.counters["refused_script_not_running"]
    sim.request("stop_script")
    state = loop_thread.run(wait_for_state(arm, lambda s: not s.running, 1.0), CALL_TIMEOUT_S)
    with pytest.raises(DeviceFault, match="not running"):
        loop_thread.run(arm.servo_to(state.tcp_pose), CALL_TIMEOUT_S)
    assert wait_servo_count(sim, before + 1, timeout_s=0.1) == before
    assert sim.state()["faults"]["stop_script"] == 1
    assert arm.counters["refused_script_not_running"] == refused_before + 1
    loop_thread.run(arm.restart_script(), CALL_TIMEOUT_S)
    assert sim.state()["watchdog_period_s"] == pytest.approx(0.25)  # re-armed in the new program
    loop_thread.run(arm.servo_to(state.tcp_pose), CALL_TIMEOUT_S)
    assert wait_servo_count(sim, before + 1) == before + 1


def test_restart_waits_until_the_control_client_sees_the_program_running(sim, arm, loop_thread):
    """The receive and control clients get the controller's stream on separate sockets. When the control client's
    copy lags, it still reads STOPPED after the receive client reads PLAYING, and it refuses setWatchdog. Here its
    stream is held back for the whole restart: ``restart_script`` must wait for it, not for the receive client."""
    sim.request("stop_script")
    state = loop_thread.run(wait_for_state(arm, lambda s: not s.running, 1.0), CALL_TIMEOUT_S)
    time.sleep(0.1)  # a dozen packages or more: the control client has seen the stop too
    lag_s = 0.4
    sim.request("stall_control", duration_s=lag_s)
    started = time.monotonic()
    loop_thread.run(arm.restart_script(), CALL_TIMEOUT_S)
    assert time.monotonic() - started >= 0.9 * lag_s
    assert sim.state()["faults"]["stall_control"] == 1
    assert sim.state()["watchdog_period_s"] == pytest.approx(0.25)
    before = servo_count(sim)
    loop_thread.run(arm.servo_to(state.tcp_pose), CALL_TIMEOUT_S)
    assert wait_servo_count(sim, before + 1) == before + 1


def test_controller_gone_raises_not_connected_then_reconnects(sim, arm, loop_thread):
    async def drop_and_recover():
        sim.request("drop", duration_s=1.0)
        t0 = time.monotonic()
        while True:
            try:
                await arm.read_state()
            except NotConnected:
                break
            except Stale:
                pass
            await asyncio.sleep(POLL_S)
        lost_s = time.monotonic() - t0
        with pytest.raises(NotConnected):
            await arm.servo_to(np.array([0.3, -0.2, 0.4, 0.0, 0.0, 1.0, 0.0]))
        state = await wait_for_state(arm, lambda s: s.running, 5.0, tolerate=(NotConnected, Stale))
        recovered_s = time.monotonic() - t0
        await arm.servo_to(state.tcp_pose)
        return lost_s, recovered_s

    lost_s, recovered_s = loop_thread.run(drop_and_recover(), CALL_TIMEOUT_S)
    assert lost_s < 0.5
    assert 1.0 <= recovered_s < 4.0
    assert sim.state()["faults"]["drop"] == 1
    assert arm.counters["link_lost"] == 1
    assert arm.counters["reconnects"] == 1
    assert arm.counters["reconnect_failures"] >= 1
    assert sim.state()["watchdog_period_s"] == pytest.approx(0.25)


def test_bad_targets_are_refused_and_counted(sim, arm, loop_thread):
    before = settled_servo_count(sim)
    with pytest.raises(ValueError, match="non-finite"):
        loop_thread.run(arm.servo_to(np.array([0.3, np.nan, 0.4, 1.0, 0.0, 0.0, 0.0])), CALL_TIMEOUT_S)
    with pytest.raises(ValueError, match="shape"):
        loop_thread.run(arm.servo_to(np.zeros(6)), CALL_TIMEOUT_S)
    assert arm.counters["rejected_target"] == 2
    assert wait_servo_count(sim, before + 1, timeout_s=0.1) == before


def test_close_sends_servo_stop_then_runs_stop_script(sim, arm, loop_thread):
    before = sim.state()["counters"]
    loop_thread.run(arm.close(), CALL_TIMEOUT_S)
    state = sim.state()
    assert state["counters"].get("commands[16]", 0) == before.get("commands[16]", 0) + 1  # servoStop
    assert arm.counters["stops"] >= 1
    assert state["counters"]["stop_script"] == before.get("stop_script", 0) + 1
    assert state["runtime_state"] == 1
    assert arm.counters["script_stops"] == 1
    with pytest.raises(NotConnected, match="closed"):
        loop_thread.run(arm.read_state(), CALL_TIMEOUT_S)
