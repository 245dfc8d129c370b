"""The planner's plain functions: goals resolved to target poses, plans turned into TCP targets, the model built
from the stack config, the client API's refusals."""

from __future__ import annotations

import asyncio
import collections
import math
import os
import subprocess
import sys
import time
import typing
from pathlib import Path

import msgspec
import numpy as np
import pytest
import torch

from hydrosoft.geometry import se3
from hydrosoft.scene import compile_scene
from hydrosoft.services.arm_commander import PLANNER_LOST
from hydrosoft.services.bus import messages as msg
from hydrosoft.services.bus.config import load_config, parse_config
from hydrosoft.services.bus.sockets import ErrorCounter
from hydrosoft.services.arm.progress import MIN_CYCLES
from hydrosoft.services.planner import (
    LEAD_CYCLES,
    LEAD_MARGIN_S,
    LATE_PERIODS,
    LEAD_WINDOW,
    NEXT_DUE_PERIODS,
    OBJECT_POSE_TOPIC,
    POSE_WAIT_PERIODS,
    Episode,
    Planner,
    PlannerCore,
    arm_end_positions,
    compute_niceness,
    compute_threads,
    device_unavailable,
    ended_by_commander,
    planner_scene,
    pose_wait_s,
    resolve_target,
    target_lead,
    targets_from_plan,
)
from hydrosoft.tasks import make_task
from service_process import ServiceProcess
from stack_process import quick_planner
from hydrosoft.services.bus.sockets import Bus, LatestSubscriber
from hydrosoft.services.client import ClientError, StackClient

SIM_TOML = Path(__file__).parents[2] / "deploy" / "sim.toml"
SIM_TEXT = quick_planner(SIM_TOML.read_text())  # deploy/sim.toml with the quick planner: no worker processes
NO_PRESET = SIM_TEXT.replace('preset = "quick"', "", 1)  # the planner's own defaults, no preset


@pytest.fixture(scope="module")
def core():
    return PlannerCore.build(parse_config(SIM_TEXT))


def test_a_displacement_goal_moves_and_turns_the_start_pose():
    start = torch.tensor([0.01, 0.02, 0.024, 1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    goal = msg.Goal(task="pushing", dx_m=0.04, dy_m=-0.01, dyaw_rad=math.radians(30), tolerance_mm=5, timeout_s=10)
    target = resolve_target(goal, start)
    assert torch.allclose(target[:3], torch.tensor([0.05, 0.01, 0.024], dtype=torch.float64))
    assert math.degrees(float(se3.angle_between(target[3:], start[3:]))) == pytest.approx(30.0)
    absolute = msgspec.structs.replace(goal, target_pose=np.array([0.1, 0, 0.02, 1, 0, 0, 0.0]), dx_m=0.0, dy_m=0.0,
                                       dyaw_rad=0.0)
    assert resolve_target(absolute, start).tolist() == [0.1, 0, 0.02, 1, 0, 0, 0.0]
    rolled = resolve_target(msg.Goal(task="in_hand", droll_rad=math.radians(20), tolerance_mm=5, timeout_s=10), start)
    assert torch.equal(rolled[:3], start[:3])  # turned about the object's centre
    axis = se3.quat_to_matrix(se3.quat_multiply(rolled[3:], se3.quat_conjugate(start[3:])))
    assert torch.allclose(axis[:, 0], torch.tensor([1.0, 0, 0], dtype=torch.float64))  # about base x
    assert math.degrees(float(se3.angle_between(rolled[3:], start[3:]))) == pytest.approx(20.0)
    roll = msg.Goal(task="rolling", dx_m=0.03, dpitch_rad=0.03 / 0.025, tolerance_mm=5, timeout_s=10)
    rolling = resolve_target(roll, start)  # a 2.5 cm cylinder rolled 3 cm along x: moved 3 cm, turned 1.2 rad about y
    assert torch.allclose(rolling, se3.retract(start, torch.tensor([0.03, 0, 0, 0, 1.2, 0], dtype=torch.float64)))
    axis = se3.quat_to_matrix(se3.quat_multiply(rolling[3:], se3.quat_conjugate(start[3:])))
    assert torch.allclose(axis[:, 1], torch.tensor([0, 1.0, 0], dtype=torch.float64))  # about base y


def test_the_core_follows_the_config(core):
    assert core.model.dtype == torch.float32 and core.model.body_names == ("bubble", "table")
    assert core.arms == {"bubble": 0} and core.sensors.tolist() == [0]
    # re-approach presses the bubble down to the scene's pose over the cube: 5 cm above its centre
    torch.testing.assert_close(core.grasp_offset, torch.tensor([0.0, 0.0, 0.05], dtype=torch.float64))
    start = core.task.initial_pose()
    assert core.error_mm(start, start) == 0.0
    assert core.error_mm(start, resolve_target(msg.Goal(task="pushing", dx_m=0.04, tolerance_mm=5, timeout_s=1),
                                               start)) == pytest.approx(40.0, rel=1e-9)


def test_the_bubble_sdf_is_solved_as_the_config_says(core, tmp_path):
    """The quick preset's fixed 3-step bubble solve reaches the planner's model and its tactile membranes; without
    the key (and no preset) the planner solves to convergence."""
    config = parse_config(SIM_TEXT)
    assert config.planner.sdf_solver_steps == 3
    assert core.membranes["bubble"].solver_steps == 3 and core.model.bodies[0].solver_steps == 3
    path = tmp_path / "converged.toml"
    path.write_text(NO_PRESET)
    assert PlannerCore.build(load_config(path)).membranes["bubble"].solver_steps is None


def test_an_arm_that_is_not_a_scene_body_is_refused_by_name(tmp_path):
    text = SIM_TEXT.replace('name = "bubble"', 'name = "gripper"')
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ValueError, match="'gripper' is not a body of the pushing scene"):
        PlannerCore.build(load_config(path))


def test_the_workspace_check_follows_the_arm_from_where_it_is():
    """A cube already pushed 12 cm out: a further 3 cm takes the bubble to 15 cm (its own position plus the push),
    not to the scene's pose plus 3 cm; rolling's bubble travels twice the cylinder's distance."""
    start = torch.tensor([0.12, 0.0, 0.024, 1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    target = resolve_target(msg.Goal(task="pushing", dx_m=0.03, tolerance_mm=5, timeout_s=10), start)
    arms = {"bubble": torch.tensor([0.125, 0.002, 0.074, 1.0, 0.0, 0.0, 0.0], dtype=torch.float64)}
    ends = arm_end_positions(make_task("pushing"), arms, start, target)
    torch.testing.assert_close(ends["bubble"], torch.tensor([0.155, 0.002, 0.074], dtype=torch.float64))
    rolled = arm_end_positions(make_task("rolling"), arms, start, target)
    torch.testing.assert_close(rolled["bubble"], torch.tensor([0.185, 0.002, 0.074], dtype=torch.float64))


def test_targets_apply_the_first_plan_steps_to_the_current_tcp(core):
    tcp = core.fixed_poses[0].clone()
    plan = torch.zeros(6, 2, 6)
    plan[:, 0, 0] = 0.002
    plan[:, 0, 1] = -0.001
    targets = targets_from_plan(core, {"bubble": tcp}, plan, steps=3)
    assert torch.allclose(targets["bubble"][:3], tcp[:3] + torch.tensor([0.006, -0.003, 0.0], dtype=torch.float64))
    assert torch.allclose(targets_from_plan(core, {"bubble": tcp}, plan, steps=99)["bubble"][:2],
                          tcp[:2] + torch.tensor([0.012, -0.006], dtype=torch.float64))


def test_targets_leave_in_the_base_frame_of_a_turned_and_moved_task_frame(core, tmp_path):
    text = SIM_TEXT.replace('tag_size_m = 0.032', 'tag_size_m = 0.032\ntask_frame = [0.5, -0.1, -0.02, '
                                        f'{math.sqrt(0.5)}, 0.0, 0.0, {math.sqrt(0.5)}]', 1)
    path = tmp_path / "turned.toml"
    path.write_text(text)
    turned = PlannerCore.build(load_config(path))
    tcp = turned.fixed_poses[0].clone()  # task frame
    plan = torch.zeros(6, 2, 6)
    plan[:, 0, 0] = 0.002  # +x of the task frame
    target = targets_from_plan(turned, {"bubble": tcp}, plan, steps=3)["bubble"]
    expected = tcp[:3] + torch.tensor([0.006, 0.0, 0.0], dtype=torch.float64)
    expected = torch.tensor([0.5 - float(expected[1]), -0.1 + float(expected[0]), -0.02 + float(expected[2])],
                            dtype=torch.float64)  # 90 deg about z, then moved
    torch.testing.assert_close(target[:3], expected, atol=1e-9, rtol=0)
    torch.testing.assert_close(turned.frame.to_task(target)[:3], tcp[:3] + torch.tensor([0.006, 0, 0.0],
                               dtype=torch.float64), atol=1e-9, rtol=0)
    same = targets_from_plan(core, {"bubble": tcp}, plan, steps=3)["bubble"]  # sim.toml: the identity
    torch.testing.assert_close(same[:3], tcp[:3] + torch.tensor([0.006, 0, 0.0], dtype=torch.float64))


def test_the_solver_gets_the_configured_workers(core, tmp_path):
    """``planner.workers`` and ``planner.chunks`` reach the solver settings of every goal; one worker, its samples
    uncut, when the keys are left out."""
    path = tmp_path / "workers.toml"
    path.write_text(SIM_TEXT.replace("[planner]", "[planner]\nworkers = 2\nchunks = 4\n", 1))
    two = PlannerCore.build(load_config(path))
    assert core.settings.config(core.settings.horizon, 1).workers == 1
    assert core.settings.config(core.settings.horizon, 1).pieces == 1
    assert two.settings.config(two.settings.horizon, 1).workers == 2
    assert two.settings.config(two.settings.horizon, 1).pieces == 4


def test_the_planner_model_takes_the_configured_object_update(core, tmp_path):
    """The presets' ``planner.object_update = "linearly_implicit"`` gives the solver's model that update and one
    sub-step per step; left out (no preset), the scene's explicit update and its sub-steps."""
    path = tmp_path / "explicit.toml"
    path.write_text(NO_PRESET)
    explicit = PlannerCore.build(load_config(path))
    assert core.model.object_update == "linearly_implicit" and core.model.substeps == 1
    assert core.settings.object_update == "linearly_implicit"
    assert explicit.model.object_update == "explicit" and explicit.model.substeps > 1


def test_worker_processes_plan_what_threads_plan_and_stop_with_the_core(tmp_path):
    """``planner.worker_processes``: two solves of a goal on two worker processes, their samples in four chunks, give
    the plans of two worker threads on the same chunks (each process builds the config's core and the goal's costs
    itself); ``close`` stops the processes."""
    text = SIM_TEXT.replace("[planner]", "[planner]\nworkers = 2\nchunks = 4\n", 1)
    (tmp_path / "threads.toml").write_text(text)
    (tmp_path / "processes.toml").write_text(text.replace("[planner]", "[planner]\nworker_processes = true\n", 1))
    threads = PlannerCore.build(load_config(tmp_path / "threads.toml"))
    processes = PlannerCore.build(load_config(tmp_path / "processes.toml"))
    pids = processes.processes.pids
    try:
        assert threads.processes is None and len(pids) == 2
        _, initial, _ = compile_scene(planner_scene(threads.task, threads.config), dtype=threads.model.dtype)
        arms = {name: initial.body_poses[0, index].double() for name, index in threads.arms.items()}
        goal = threads.task.initial_pose().clone()
        goal[0] += 0.02
        plans = []
        for core in (threads, processes):
            solver = core.solver(goal, initial.object_pose[0].double(), arms)
            plans.append([solver.solve(initial).plan for _ in range(2)])
        for expected, got in zip(*plans, strict=True):
            torch.testing.assert_close(got, expected, rtol=0, atol=1e-6)
    finally:
        processes.close()
    for pid in pids:
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)


def test_a_planner_told_to_use_the_cpu_plans_what_the_default_plans(core, tmp_path):
    """``planner.device = "cpu"`` is the default: its core's model and solver are on the CPU and two solves of a goal
    give the default core's plans, bit for bit."""
    path = tmp_path / "cpu.toml"
    path.write_text(SIM_TEXT.replace("[planner]", '[planner]\ndevice = "cpu"\n', 1))
    explicit = PlannerCore.build(load_config(path))
    _, initial, _ = compile_scene(planner_scene(core.task, core.config), dtype=core.model.dtype)
    arms = {name: initial.body_poses[0, index].double() for name, index in core.arms.items()}
    goal = core.task.initial_pose().clone()
    goal[0] += 0.02
    plans = []
    for built in (core, explicit):
        solver = built.solver(goal, initial.object_pose[0].double(), arms)
        assert built.model.device == solver.device == torch.device("cpu")
        plans.append([solver.solve(initial).plan for _ in range(2)])
    for default, got in zip(*plans, strict=True):
        torch.testing.assert_close(got, default, rtol=0, atol=0)


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks a machine without CUDA")
def test_a_cuda_planner_on_a_machine_without_cuda_is_refused_with_the_reason(tmp_path):
    """``planner.device = "cuda"`` where torch has no CUDA: the core is not built on the CPU instead, it raises the
    reason, which names the key; the CPU is always available."""
    assert device_unavailable("cpu") is None
    for device in ("cuda", "cuda:1"):
        assert "planner.device" in device_unavailable(device) and "CUDA is not available" in device_unavailable(device)
    path = tmp_path / "cuda.toml"
    path.write_text(SIM_TEXT.replace("[planner]", '[planner]\ndevice = "cuda"\n', 1))
    with pytest.raises(RuntimeError, match=r"planner\.device = 'cuda', but CUDA is not available"):
        PlannerCore.build(load_config(path))


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks a machine without CUDA")
def test_a_planner_service_without_its_gpu_reports_it_refuses_goals_and_sends_no_target(tmp_path):
    """The planner service with ``planner.device = "cuda"`` on a machine without CUDA: it does not crash nor plan on
    the CPU; it reports READY (the launch goes on: the arms stay held by their commanders), its status reads
    ``degraded`` with the reason and a ``device_unavailable`` error, SetGoal and Start are refused with the reason,
    it publishes no arm target, and it stops cleanly (exit 0)."""
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    path = tmp_path / "cuda.toml"
    path.write_text(f'run_dir = "{run_dir}"\nmode = "sim"\n[[arms]]\nname = "bubble"\n[planner]\ndevice = "cuda"\n')
    config = load_config(path)

    async def scenario() -> dict:
        bus = Bus()
        targets = LatestSubscriber(bus, config.endpoint("planner"), topics=["arm_target/"])
        seen = {}
        try:
            async with StackClient(config) as client:
                seen["status"] = (await client.status()).status
                for name, request in (("set_goal", client.set_goal("pushing", dx_m=0.02)), ("start", client.start())):
                    try:
                        await request
                    except ClientError as err:
                        seen[name] = str(err)
                seen["targets"] = await targets.wait(1.0)  # the topics that got a message within 1 s
                seen["after"] = (await client.status()).status
        finally:
            bus.close()
        return seen

    process = ServiceProcess("planner", "planner", path, tmp_path / "planner.log")
    try:
        process.wait_ready()
        seen = asyncio.run(asyncio.wait_for(scenario(), 30.0))
    finally:
        rc = process.stop()
    assert rc == 0, process.log()
    status = seen["status"]
    assert status.state == "degraded" and "CUDA is not available" in status.note, status
    assert status.errors.get("device_unavailable") == 1, status
    for name in ("set_goal", "start"):
        assert "planner.device = 'cuda', but CUDA is not available" in seen.get(name, ""), seen
    assert seen["targets"] == set()
    assert seen["after"].errors["device_unavailable"] == 3, seen["after"]


class ServiceOfLaunch:
    """The part of a ``runtime.Service`` that the planner's SetGoal uses: its launch id and error counts."""

    def __init__(self, instance: str) -> None:
        self.instance, self.errors = instance, ErrorCounter()

    def count_error(self, kind: str, text: str) -> None:
        self.errors.count(kind, text)


def test_a_goal_set_for_another_launch_is_refused_and_counted():
    planner = Planner.__new__(Planner)  # the client API's SetGoal needs no model, inputs or sockets
    planner.service, planner.config, planner.goal = ServiceOfLaunch("a" * 32), load_config(SIM_TOML), None
    other = msg.Goal(task="pushing", dx_m=0.03, tolerance_mm=5.0, timeout_s=60.0, instance="b" * 32)
    reply = asyncio.run(planner.handle(msg.SetGoal(goal=other)))
    assert not reply.ok and "another launch" in reply.error and planner.goal is None
    assert planner.service.errors.counts == {"other_instance": 1}
    for instance in ("a" * 32, ""):  # its own launch, or a goal for whatever stack runs
        goal = msgspec.structs.replace(other, instance=instance)
        assert asyncio.run(planner.handle(msg.SetGoal(goal=goal))).ok and planner.goal == goal



def commander_state(arm: str, floor_ns: int, cause: str) -> msg.ArmState:
    """An arm commander's state with its goal floor (``floor_ns``, named ``cause``)."""
    return msg.ArmState(arm=arm, tcp_pose=np.array([0.0, 0.0, 0.1, 1.0, 0.0, 0.0, 0.0]), tcp_speed=np.zeros(6),
                        running=True, protective_stop=False, emergency_stop=False, servo_active=False,
                        goal_floor_ns=floor_ns, goal_floor_cause=cause)


def test_a_goal_ends_once_an_arm_commanders_goal_floor_reaches_its_start():
    started_ns = 5_000_000_000
    fine = commander_state("left", started_ns - 1, "the commander's start")
    assert ended_by_commander(started_ns, []) is None and ended_by_commander(started_ns, [fine]) is None
    lost = commander_state("right", started_ns + 1, PLANNER_LOST)
    why = ended_by_commander(started_ns, [fine, lost])
    assert why is not None and "arm right" in why and PLANNER_LOST in why and "start a new goal" in why

def idle_episode() -> Episode:
    """An episode for the input rules alone (no goal, target or solver needed)."""
    return Episode(goal=None, target=None, solver=None, started_s=0.0)


def test_inputs_stale_past_sensor_lost_s_end_the_goal_and_a_short_gap_does_not():
    episode = idle_episode()
    assert not episode.note_stale(10.0, "object pose 0.6 s old", 1.0)
    assert not episode.note_stale(10.9, "object pose 1.5 s old", 1.0) and episode.outcome == "running"
    assert not episode.note_fresh({OBJECT_POSE_TOPIC: 7})  # back in time: the gap only stopped the arm
    assert not episode.note_stale(11.0, "object pose 0.6 s old", 1.0)  # a new gap counts from its own start
    assert not episode.note_stale(12.0, "object pose 1.6 s old", 1.0)
    assert episode.note_stale(12.01, "object pose 1.61 s old", 1.0)
    assert episode.outcome == "interrupted" and "input lost: object pose 1.61 s old" in episode.reason
    assert "start a new goal" in episode.reason


def test_an_input_whose_publisher_restarted_ends_the_goal_even_without_a_gap():
    """A restarted tag tracker or camera numbers its messages from 1 again: the goal ends at once, so a sensor that
    comes back quickly does not move the arm again on that goal."""
    episode = idle_episode()
    topics = {OBJECT_POSE_TOPIC: 40, "arm_state/bubble": 900, "deformation/bubble": 30}
    assert not episode.note_fresh(topics)
    assert not episode.note_fresh({**topics, OBJECT_POSE_TOPIC: 45, "deformation/bubble": 30})  # none newer: fine
    assert episode.note_fresh({**topics, OBJECT_POSE_TOPIC: 46, "deformation/bubble": 1})
    assert episode.outcome == "interrupted" and "publisher of deformation/bubble restarted" in episode.reason


def test_the_target_lead_follows_the_slow_cycles_within_the_configured_floor_and_the_commanders_ceiling():
    assert target_lead(0.3, [], 1.0) == 0.3  # nothing measured yet: the configured lead
    fast = [0.06] * 18 + [0.08, 0.09]  # p90 0.08 s: 2 x 0.08 + 0.05 = 0.21 s, under the floor
    assert target_lead(0.3, fast, 1.0) == 0.3
    loaded = [0.15] * 17 + [0.3, 0.32, 0.34]  # p90 0.302 s: the lead grows past the floor to outlive two of them
    assert target_lead(0.3, loaded, 1.0) == pytest.approx(LEAD_CYCLES * 0.302 + LEAD_MARGIN_S)
    assert target_lead(0.3, [1.0, 2.6, 1.8], 1.0) == 1.0  # the quick planner under load: capped at the ceiling
    assert target_lead(1.0, fast, 0.5) == 0.5  # a floor above the ceiling is capped too
    assert LEAD_WINDOW >= 10  # a p90 over fewer cycles would be their maximum


def test_a_goal_end_sends_a_halt_naming_its_outcome_and_the_deadline_follows_the_cycles():
    """The planner's halt at a goal's end carries the outcome (the commander's stop cause "goal reached"); a plan's
    targets get a deadline of ``target_lead`` from now, the lead shown in the status note."""
    sent = []

    class Out:
        async def send(self, message, topic):
            sent.append((topic, message))

    planner = Planner.__new__(Planner)
    planner.service, planner.config = ServiceOfLaunch("a" * 32), load_config(SIM_TOML)
    planner.service.note = ""
    planner.out, planner.plan_seq, planner.episode, planner.last_outcome = Out(), 0, None, None
    planner.cycles_s = collections.deque([0.4] * 10, maxlen=LEAD_WINDOW)
    before_ns = time.monotonic_ns()
    deadline_ns = planner.target_deadline_ns()
    lead_s = (deadline_ns - before_ns) * 1e-9
    assert LEAD_CYCLES * 0.4 + LEAD_MARGIN_S <= lead_s < LEAD_CYCLES * 0.4 + LEAD_MARGIN_S + 0.05
    assert "target lead 0.85 s" in planner.service.note
    asyncio.run(planner.send_targets({"bubble": np.array([0.0, 0.0, 0.1, 0.0, 0.0, 1.0, 0.0])}, deadline_ns))
    asyncio.run(planner.send_targets({"bubble": np.array([0.0, 0.0, 0.1, 0.0, 0.0, 1.0, 0.0])}, time.monotonic_ns(),
                                     goal_end="reached"))
    (_, plan_target), (topic, halt) = sent
    assert topic == "arm_target/bubble" and plan_target.goal_end == "" and halt.goal_end == "reached"
    assert halt.plan_seq == plan_target.plan_seq + 1
    for outcome in typing.get_args(msg.Outcome):  # every way a goal ends makes a halt the commander can read
        if outcome not in ("", "running"):
            halt = msgspec.structs.replace(halt, goal_end=outcome, seq=1, stamp_ns=time.monotonic_ns())
            assert msg.decode(msg.encode(halt))[1].goal_end == outcome


def test_a_solve_waits_for_a_pose_newer_than_the_last_solves_within_a_limit():
    ms = 1_000_000  # ns
    period_s = 0.05  # 20 images/s
    # the newest pose (published at 1000 ms) is newer than the last solve's (900 ms), the next is due at 1050 ms
    assert pose_wait_s(1000 * ms, 900 * ms, 1010 * ms, 1010 * ms, period_s) == 0.0  # due in 40 ms: solve now
    assert pose_wait_s(1000 * ms, 900 * ms, 1010 * ms, 1030 * ms, period_s) == pytest.approx(
        0.02 + LATE_PERIODS * period_s)  # due in 20 ms, within NEXT_DUE_PERIODS: wait for it, a little past its time
    # 10 ms late, as detection's tail makes it (p99 44 against p50 20 ms): still waited for, it is the newer image
    assert pose_wait_s(1000 * ms, 900 * ms, 1010 * ms, 1060 * ms, period_s) == pytest.approx(0.015)
    assert pose_wait_s(1000 * ms, 900 * ms, 1010 * ms, 1080 * ms, period_s) == 0.0  # it came not: the newest then
    assert pose_wait_s(5000 * ms, 0, 0, 5001 * ms, period_s) == 0.0  # the goal's first solve
    # the last solve (ended at 1080 ms) planned on the newest pose: wait for the next, at most a period after it
    assert pose_wait_s(1000 * ms, 1000 * ms, 1080 * ms, 1090 * ms, period_s) == pytest.approx(
        POSE_WAIT_PERIODS * period_s - 0.01)
    assert pose_wait_s(1000 * ms, 1000 * ms, 1080 * ms, 1200 * ms, period_s) == 0.0  # none came: solve on it again
    assert pose_wait_s(0, 1000 * ms, 1080 * ms, 1090 * ms, period_s) == 0.0  # no pose (the input check says stale)
    assert NEXT_DUE_PERIODS <= 0.5 and LATE_PERIODS <= 0.5 and POSE_WAIT_PERIODS <= 1.5  # short against a solve


class PoseInputs:
    """The planner's subscriber as ``Planner.wait_for_new_pose`` reads it: the newest object pose's stamp and the
    event a new one sets."""

    def __init__(self, stamp_ns: int) -> None:
        self.stamp_ns, self.event = stamp_ns, asyncio.Event()

    def arrival(self, topic: str) -> asyncio.Event:
        assert topic == OBJECT_POSE_TOPIC
        return self.event

    def latest(self, topic: str, max_age_s: float):
        return collections.namedtuple("Received", "stamp_ns")(self.stamp_ns)

    def publish(self, stamp_ns: int) -> None:
        self.stamp_ns = stamp_ns
        self.event.set()


def test_the_planner_starts_a_solve_when_a_new_pose_arrives_or_the_wait_limit_passes():
    planner = Planner.__new__(Planner)
    planner.inputs, planner.camera_period_s = PoseInputs(1_000), 0.5
    episode = Episode(msg.Goal(task="pushing", tolerance_mm=3.0, timeout_s=60.0), torch.zeros(7), None,
                      time.monotonic(), solved_pose_ns=1_000, solved_at_ns=time.monotonic_ns())

    async def new_pose_after(delay_s: float) -> float:
        started = time.monotonic()
        loop = asyncio.get_running_loop()
        loop.call_later(delay_s, lambda: planner.inputs.publish(time.monotonic_ns()))
        await planner.wait_for_new_pose(episode)
        return time.monotonic() - started

    async def scenario() -> None:
        assert 0.05 <= await new_pose_after(0.05) < 0.3  # woken by the pose, well before the limit
        assert await new_pose_after(5.0) < 0.1  # a newer pose is there already and the next not due soon: no wait
        episode.solved_pose_ns, episode.solved_at_ns = planner.inputs.stamp_ns, time.monotonic_ns()
        assert 0.5 <= await new_pose_after(5.0) < 0.8  # none comes: it goes on after the limit

    asyncio.run(scenario())


def test_compute_threads_run_at_the_planner_niceness_and_leave_the_caller_at_its_own():
    """The planner's computing (its threads, and the worker processes they start) runs at ``planner.nice``; the
    thread that made them, the planner's event loop (inputs, state estimate, targets), keeps its niceness."""
    before = os.nice(0)
    expected = min(before + 3, 19)
    compute = compute_threads(3)
    try:
        in_thread = compute.submit(os.nice, 0).result(timeout=30)
        child = compute.submit(subprocess.run, [sys.executable, "-c", "import os; print(os.nice(0))"],
                               capture_output=True, text=True, timeout=60).result(timeout=90)
    finally:
        compute.shutdown()
    assert in_thread == expected
    assert int(child.stdout) == expected
    assert os.nice(0) == before


def test_the_computing_thread_keeps_the_services_niceness_only_where_worker_processes_solve():
    """With worker processes the heavy computing is theirs (reniced to ``planner.nice``), and the thread's work (the
    penetration, handing shares out and in) is on the camera-to-target path; without them the thread solves."""
    config = load_config(SIM_TOML)
    assert config.planner.nice == 10
    assert compute_niceness(config, worker_processes=True) == 0
    assert compute_niceness(config, worker_processes=False) == 10


class StackInputs:
    """The planner's subscriber for one still scene: the object at ``object_pose`` (published a second ago, so no
    solve waits for a newer one), the arm's state at ``tcp_pose`` (base frame) and a membrane image (only its
    ``seq`` is read before a solve)."""

    def __init__(self, object_pose: np.ndarray, tcp_pose: np.ndarray) -> None:
        self.object_pose, self.tcp_pose, self.seq = object_pose, tcp_pose, 0
        self.event = asyncio.Event()

    def arrival(self, topic: str) -> asyncio.Event:
        return self.event

    def latest(self, topic: str, max_age_s: float, kind=None):
        self.seq += 1
        now_ns = time.monotonic_ns()
        if topic == OBJECT_POSE_TOPIC:
            value = msg.ObjectPose(object="object", pose=self.object_pose, tags_used=(0,), quality=1.0, seq=self.seq,
                                   stamp_ns=now_ns - 1_000_000_000)
        elif topic.startswith("arm_state/"):
            value = msgspec.structs.replace(commander_state("bubble", 0, ""), tcp_pose=self.tcp_pose, seq=self.seq)
        else:
            value = collections.namedtuple("Deformation", "seq")(self.seq)
        stamp_ns = getattr(value, "stamp_ns", 0) or now_ns
        return collections.namedtuple("Received", "value stamp_ns age_s")(value, stamp_ns, (now_ns - stamp_ns) * 1e-9)


class StackService(ServiceOfLaunch):
    """A ``runtime.Service`` as the planner uses it: its subscriber and publisher (``Out``: every message kept),
    its error counts and its log's lines."""

    def __init__(self, inputs: StackInputs) -> None:
        super().__init__("a" * 32)
        self.inputs, self.sent, self.logged, self.note = inputs, [], [], ""
        self.log = self

    def subscriber(self, endpoints, topics, background):
        return self.inputs

    def publisher(self, endpoint):
        return self

    async def send(self, message, topic):
        self.sent.append((topic, message))

    def warning(self, text: str, *args) -> None:
        self.logged.append(text % args)

    info = warning

    def status(self):
        return None


def test_a_goal_that_makes_no_progress_ends_failed_naming_why_and_halts_the_arm(core):
    """The soak's stall: a push held 3.05 mm short of its 3 mm tolerance. Once the planner has planned for
    ``planner.stall_s`` (and ``MIN_CYCLES`` cycles) without the error falling, its next cycle ends the goal
    ``failed``, the reason naming the error, the best, the tolerance and the key; the error is counted
    (``goal_stalled``) and logged, and each commander gets the halt naming the outcome (the arm's stop cause "goal
    failed"), not another plan, long before the goal's 120 s timeout. Time with the bubble off the cube does not
    count."""
    stall_s = 0.4
    config = parse_config(SIM_TEXT.replace("[planner]", f"[planner]\nstall_s = {stall_s}\n", 1))
    assert config.planner.stall_s == stall_s and parse_config(SIM_TEXT).planner.stall_s == 10.0
    frame = core.frame
    cube = frame.to_base(core.task.initial_pose()).numpy()
    tcp = frame.to_base(core.fixed_poses[core.arms["bubble"]]).numpy()
    service = StackService(StackInputs(cube, tcp))
    planner = Planner(service, config, core)
    planner.goal = msg.Goal(task="pushing", dx_m=0.00305, tolerance_mm=3.0, timeout_s=120.0)
    assert planner.start().ok
    episode = planner.episode
    assert episode.outcome == "running" and episode.error_mm == pytest.approx(3.05)
    for _ in range(MIN_CYCLES):  # cycles that planned on the cube where it started
        assert not episode.note_progress(time.monotonic())
    episode.contact.out_of_contact_since = time.monotonic()  # the bubble off the cube: no planning, no clock
    assert not episode.note_progress(time.monotonic())
    time.sleep(stall_s)
    episode.contact.out_of_contact_since = None  # back in contact: that time did not count
    assert not episode.note_progress(time.monotonic()) and episode.outcome == "running"

    async def cycle_after_stall_s() -> None:
        await asyncio.sleep(stall_s)
        await planner.tick()
        await planner._halting

    asyncio.run(cycle_after_stall_s())
    assert planner.episode is None and episode.outcome == "failed", (episode.outcome, episode.reason)
    assert episode.reason.startswith("no progress: error 3.05 mm (best 3.05 mm, tolerance 3 mm)"), episode.reason
    assert f"planner.stall_s = {stall_s}" in episode.reason
    assert service.errors.counts == {"goal_stalled": 1} and any(episode.reason in line for line in service.logged)
    ((topic, halt),) = service.sent  # the halt alone: no plan was sent on the stalled cycle
    assert topic == "arm_target/bubble" and halt.goal_end == "failed" and halt.deadline_ns <= time.monotonic_ns()
    np.testing.assert_array_equal(halt.tcp_pose, tcp)
    reply = planner.status_reply()
    assert reply.outcome == "failed" and reply.outcome_reason == episode.reason and not reply.running
    assert reply.elapsed_s < 10.0
