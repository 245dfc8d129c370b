"""sim_world: the plant's tick and wrench (plain functions), then sim_world as a real process with a private config:
it becomes READY, publishes images, depth and truth at their rates, its UR simulator answers the real ur_rtde
client with the bubble's pose, its FT 300 pty streams the bubble's push to the real serial driver, and moving the
simulated TCP drags the cube.

The process is started with a private run_dir and a 127.0.0.N of its own, and stopped by its pid in teardown.
"""

from __future__ import annotations

import asyncio
import functools
import json
import math
import socket
import time
from dataclasses import replace

import cv2
import msgspec
import numpy as np
import pytest
import torch

from hydrosoft.drivers.ur.config import SIM_CONTROL_PORT
from hydrosoft.dynamics import CompiledStep, body_wrenches, packed_distances
from hydrosoft.geometry import se3
from hydrosoft.scene import compile_scene
from hydrosoft.services.bus import messages as msg
from hydrosoft.services.bus.sockets import Bus, LatestSubscriber
from hydrosoft.services import sim_world
from hydrosoft.services.bus.config import load_config, parse_config
from hydrosoft.services.sim.render import BubbleDepthCamera, tag_camera
from hydrosoft.services.sim_world import (
    DurationStats,
    PlantStepError,
    SimPlant,
    body_control,
    plant_model,
)
from hydrosoft.tasks import make_task
from hydrosoft.tasks.evaluation import with_contact
from loopback import free_ur_host
from service_process import ServiceProcess

READY_TIMEOUT_S = 90.0  # import torch, compile the plant, bind the devices: a few s, more on a busy machine
RECEIVE_WINDOW_S = 3.0
SOCKET_TIMEOUT_S = 2.0
DRAG_SETTLE_S = 3.0  # the cube may trail the bubble this long after it stopped
CAMERA_FPS = 15.0
DEPTH_FPS = 5.0
BUBBLE_POSE = np.array([0.0, 0.0, 0.074215, 1.0, 0.0, 0.0, 0.0])  # pushing.toml's bubble
CUBE_POSE = np.array([0.0, 0.0, 0.024215, 1.0, 0.0, 0.0, 0.0])  # pushing.toml's cube


def pushing_config(**tables: str):
    return parse_config('[[arms]]\nname = "bubble"\n' + "".join(tables.values()))


# --- the plant, without sockets -----------------------------------------------------------------------------------


def test_body_control_carries_each_body_to_its_target_in_one_retract():
    rng = np.random.default_rng(3)
    previous = torch.tensor(np.concatenate([rng.normal(0, 0.1, (4, 3)), rng.normal(0, 1, (4, 4))], axis=1))
    previous[:, 3:] = torch.nn.functional.normalize(previous[:, 3:], dim=-1)
    delta = torch.tensor(np.concatenate([rng.normal(0, 0.01, (4, 3)), rng.normal(0, 0.05, (4, 3))], axis=1))
    target = se3.retract(previous, delta)
    target[1, 3:] = -target[1, 3:]  # the same rotation written with the other quaternion sign
    u = body_control(previous, target)
    torch.testing.assert_close(u, delta, atol=1e-12, rtol=0)


def test_the_plant_ticks_at_the_sim_rate_with_the_scenes_mobility_and_shorter_sub_steps():
    model, _ = plant_model(pushing_config(sim="[sim]\nrate_hz = 50.0\nspacing_factor = 0.5\n"))
    scene = make_task("pushing").scene
    assert model.dt == pytest.approx(0.02)
    assert model.dt / model.epsilon == pytest.approx(scene.dt / scene.epsilon)
    scene_model, _, _ = compile_scene(with_contact(scene, "nh", 0.0125))
    assert model.dt / model.substeps <= scene.dt / (2 * scene_model.substeps) + 1e-12  # the evaluation plant's
    assert model.n_points > scene_model.n_points  # finer than the planner's surface


def test_moving_the_tcp_drags_the_cube_and_the_bubble_lands_exactly_on_the_tcp():
    plant = SimPlant.from_config(pushing_config())
    tcp = BUBBLE_POSE.copy()
    for _ in range(30):
        tcp[0] += 0.0005  # 0.5 mm per 20 ms tick: 2.5 cm/s
        plant.step_to({"bubble": tcp})
        np.testing.assert_array_equal(plant.snapshot.tcp_poses["bubble"], tcp)
    cube = plant.snapshot.object_pose
    assert 0.005 < cube[0] < 0.015, cube  # it follows the 15 mm push, lagging while the shear builds up
    assert abs(cube[1]) < 1e-6 and cube[2] == pytest.approx(CUBE_POSE[2], abs=1e-6)



def test_a_plant_at_rest_is_recognised_without_a_step_and_keeping_still_only_advances_the_stamp():
    plant = SimPlant.from_config(pushing_config())
    rest = {"bubble": BUBBLE_POSE.copy()}
    assert not plant.rests_at(rest)  # nothing stepped yet
    plant.step_to(rest)
    assert plant.rests_at(rest)
    state, before = plant.state, plant.snapshot
    plant.keep_still()
    assert plant.state is state and plant.snapshot.stamp_ns >= before.stamp_ns
    np.testing.assert_array_equal(plant.snapshot.object_pose, before.object_pose)
    np.testing.assert_array_equal(plant.snapshot.tcp_wrenches["bubble"], before.tcp_wrenches["bubble"])
    moved = BUBBLE_POSE + [1e-9, 0, 0, 0, 0, 0, 0]
    assert not plant.rests_at({"bubble": moved})
    assert not plant.rests_at({}) and not plant.rests_at({"bubble": BUBBLE_POSE.tolist()})
    with pytest.raises(PlantStepError):
        plant.step_to({"bubble": np.full(7, np.nan)})
    assert not plant.rests_at(rest)  # after a failed tick only a completed one counts
    plant.step_to(rest)
    assert plant.rests_at(rest)
    plant.step_to({"bubble": moved})
    assert not plant.rests_at({"bubble": moved})  # the bubble moved in that tick: step again before resting


def test_a_cube_placed_off_the_bubble_is_untouched_until_the_bubble_comes_down_on_it():
    """``sim.object_offset_m``: the cube starts 6 cm to the side, so the bubble does not touch it; the plant is not
    pruned to the starting contacts, so the bubble presses it once moved up, across and down onto it."""
    plant = SimPlant.from_config(pushing_config(sim="[sim]\nobject_offset_m = [0.0, 0.06]\n"))
    np.testing.assert_allclose(plant.snapshot.object_pose, CUBE_POSE + [0.0, 0.06, 0, 0, 0, 0, 0], atol=1e-12)
    assert not plant.model.touchable  # unpruned
    plant.step_to({"bubble": BUBBLE_POSE})
    assert np.abs(plant.tcp_wrench("bubble")).max() == 0.0
    tcp = BUBBLE_POSE.copy()
    for axis, end in ((2, BUBBLE_POSE[2] + 0.02), (1, 0.06), (2, BUBBLE_POSE[2])):
        while abs(tcp[axis] - end) > 1e-12:
            tcp[axis] += float(np.clip(end - tcp[axis], -0.001, 0.001))
            plant.step_to({"bubble": tcp})
    force_z = plant.tcp_wrench("bubble")[2]
    assert abs(force_z) > 1.0, plant.tcp_wrench("bubble")  # the 5 mm press of the scene: about 1.9 N
    np.testing.assert_allclose(plant.snapshot.object_pose[:2], [0.0, 0.06], atol=1e-3)


def test_the_plant_keeps_each_ticks_signed_distances_and_they_are_the_states_own():
    """A tick caches the signed distances of its end (the next tick's stability check reuses them instead of
    solving every closest point again); they are those of the state's poses, and a plant that recomputes them every
    tick ends where this one does."""
    cached, recomputed = SimPlant.from_config(pushing_config()), SimPlant.from_config(pushing_config())
    tcp = BUBBLE_POSE.copy()
    for _ in range(15):
        tcp[0] += 0.0005
        tcp[2] -= 0.0001
        cached.step_to({"bubble": tcp})
        recomputed.state = recomputed.state._replace(phi=None)
        recomputed.step_to({"bubble": tcp})
        state = cached.state
        assert state.phi is not None
        truth = packed_distances(cached.model, state.object_pose, state.body_poses)
        np.testing.assert_allclose(state.phi.numpy(), truth.numpy(), atol=1e-12)
    np.testing.assert_allclose(cached.snapshot.object_pose, recomputed.snapshot.object_pose, atol=1e-12)

def test_a_compiled_plant_compiles_one_graph_and_ticks_as_the_eager_step_from_the_scenes_state(monkeypatch):
    """The plant's state is in a step's own form from the start (its signed distances cached, ``stepped_form``), so
    a compiled plant's warm-up compiles the step's one graph and none for a start state's signed distances; and
    its ticks, the first among them, are those of an eager plant that steps from the scene's state without cached
    distances (``step`` then evaluates them itself). Dynamo's ``eager`` backend stands in for inductor: the same
    traced graphs, without inductor's C++ compile."""
    graphs = []

    def counting_backend(graph, example_inputs):
        graphs.append(graph)
        return graph.forward

    monkeypatch.setattr(sim_world, "CompiledStep", functools.partial(CompiledStep, backend=counting_backend))
    compiled = SimPlant.from_config(pushing_config(sim="[sim]\ncompile = true\n"))
    try:
        assert compiled.compile() is None
        assert len(graphs) == 1, [g.code for g in graphs]  # the sub-step's
        eager = SimPlant.from_config(pushing_config())
        eager.state = eager.state._replace(phi=None)  # the scene's state, as the plant held it before
        tcp = BUBBLE_POSE.copy()
        for _ in range(12):
            tcp[0] += 0.0005
            tcp[2] -= 0.0001
            compiled.step_to({"bubble": tcp})
            eager.step_to({"bubble": tcp})
            for ours, theirs in zip(compiled.state[:3], eager.state[:3]):
                torch.testing.assert_close(ours, theirs, atol=1e-12, rtol=0)
        assert len(graphs) == 1
        assert abs(compiled.snapshot.object_pose[0]) > 1e-4  # the cube moved: the contact forces were at work
    finally:
        torch._dynamo.reset()


def test_a_plant_placed_in_a_task_frame_takes_and_gives_base_frame_poses_and_forces():
    """The same push with the scene at ``scene.task_frame`` (turned 90 deg, moved) and at the base origin: every
    pose, force and wrench that leaves the plant is the identity plant's, carried into the base frame."""
    frame = [0.5, -0.1, -0.02, math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5)]
    placed = SimPlant.from_config(pushing_config(scene=f"[scene]\ntask_frame = {frame}\n"))
    origin = SimPlant.from_config(pushing_config())
    to_base = placed.frame.to_base
    np.testing.assert_allclose(placed.snapshot.tcp_poses["bubble"], to_base(torch.tensor(BUBBLE_POSE)), atol=1e-15)
    tcp = BUBBLE_POSE.copy()
    for _ in range(20):
        tcp[0] += 0.0005  # +x of the task frame: +y of the base
        origin.step_to({"bubble": tcp})
        placed.step_to({"bubble": to_base(torch.tensor(tcp)).numpy()})
    cube = placed.snapshot.object_pose
    assert cube[1] - (-0.1) > 0.003 and abs(cube[0] - 0.5) < 1e-6, cube  # dragged along the base's +y
    np.testing.assert_allclose(cube, to_base(torch.tensor(origin.snapshot.object_pose)).numpy(), atol=1e-9)
    np.testing.assert_allclose(placed.tcp_wrench("bubble"), origin.tcp_wrench("bubble"), atol=1e-9)  # TCP frame
    (_, forces), (_, origin_forces) = placed.contact_forces(), origin.contact_forces()
    np.testing.assert_allclose(forces[..., 0], -origin_forces[..., 1], atol=1e-9)  # turned 90 deg about z
    np.testing.assert_allclose(forces[..., 1], origin_forces[..., 0], atol=1e-9)


def test_the_depth_camera_draws_a_new_press_and_puts_fresh_noise_on_a_repeated_one():
    still = BubbleDepthCamera.from_config(pushing_config(sim="[sim]\ndepth_noise_m = 0.0\n"), "bubble", 0)
    pressed = BUBBLE_POSE - np.array([0.0, 0.0, 0.002, 0.0, 0.0, 0.0, 0.0])
    first = still.render(BUBBLE_POSE, CUBE_POSE)
    deeper = still.render(pressed, CUBE_POSE)
    assert np.count_nonzero(deeper != first) > 0 and deeper[deeper > 0].mean() < first[first > 0].mean()
    np.testing.assert_array_equal(still.render(BUBBLE_POSE, CUBE_POSE), first)
    noisy = BubbleDepthCamera.from_config(pushing_config(), "bubble", 0)
    a, b = noisy.render(BUBBLE_POSE, CUBE_POSE), noisy.render(BUBBLE_POSE, CUBE_POSE)
    assert np.any(a != b)
    both = (a > 0) & (b > 0)
    assert abs(float(np.mean(a[both].astype(float) - b[both].astype(float)))) < 0.5  # counts: the same picture


def test_a_late_tick_catches_up_with_the_steps_it_is_due():
    """step_to(tcp, ticks=3) is three ticks over equal thirds of the motion: simulated time keeps up with the
    simulated arm's real time when the physics loop runs late."""
    late, on_time = SimPlant.from_config(pushing_config()), SimPlant.from_config(pushing_config())
    start = BUBBLE_POSE.copy()
    for k in (1, 2, 3):
        tcp = start.copy()
        tcp[0] += 0.0015 * k / 3
        on_time.step_to({"bubble": tcp})
    tcp = start.copy()
    tcp[0] += 0.0015
    late.step_to({"bubble": tcp}, ticks=3)
    np.testing.assert_allclose(late.snapshot.object_pose, on_time.snapshot.object_pose, atol=1e-12)
    np.testing.assert_array_equal(late.snapshot.tcp_poses["bubble"], tcp)
    once = SimPlant.from_config(pushing_config())
    once.step_to({"bubble": tcp})  # the same motion in one step moves the cube differently
    assert abs(once.snapshot.object_pose[0] - late.snapshot.object_pose[0]) > 1e-6


def test_the_tcp_wrench_is_the_objects_push_on_the_bubble_in_the_tcp_frame():
    plant = SimPlant.from_config(pushing_config())
    world = body_wrenches(plant.model, plant.state)[0, plant.arm_index["bubble"]].numpy()
    np.testing.assert_allclose(plant.tcp_wrench("bubble"), world)  # TCP axes = world axes here
    assert plant.tcp_wrench("bubble")[2] > 1.0  # the cube pushes the pressing bubble up: +Fz (about 1.9 N)

    scene = make_task("pushing").scene
    flipped_bubble = msgspec.structs.replace(scene.bodies[0], pose=[*BUBBLE_POSE[:3].tolist(), 0.0, 1.0, 0.0, 0.0])
    flipped_scene = msgspec.structs.replace(scene, bodies=[flipped_bubble, *scene.bodies[1:]])  # 180 deg about x
    model, state, _ = compile_scene(with_contact(flipped_scene, "nh", 0.00625))
    flipped = SimPlant(model, state, ["bubble"])  # the ellipsoid is symmetric: the same contact, TCP z down
    np.testing.assert_allclose(flipped.tcp_wrench("bubble")[2], -plant.tcp_wrench("bubble")[2], rtol=1e-6)


def test_a_failed_tick_is_reported_by_kind_and_keeps_the_state():
    plant = SimPlant.from_config(pushing_config())
    before = plant.snapshot
    bad = BUBBLE_POSE.copy()
    bad[0] = math.nan
    for tcp, kind in (({"bubble": bad}, "bad_tcp_pose"), ({}, "bad_tcp_pose")):
        with pytest.raises(PlantStepError) as caught:
            plant.step_to(tcp)
        assert caught.value.kind == kind
    unstable = SimPlant(replace(plant.model, max_substeps=1), plant.state, ["bubble"])
    with pytest.raises(PlantStepError) as caught:
        unstable.step_to({"bubble": BUBBLE_POSE})
    assert caught.value.kind == "unstable_step"
    forces = plant.state.forces.clone()
    forces[0, 0, 0, 0] = math.nan
    plant.state = plant.state._replace(forces=forces)
    with pytest.raises(PlantStepError) as caught:
        plant.step_to({"bubble": BUBBLE_POSE})
    assert caught.value.kind == "non_finite_step"
    assert plant.snapshot is before and plant.state.forces is forces


def test_an_arm_must_be_an_actuated_body_of_the_plant():
    model, state = plant_model(pushing_config())
    with pytest.raises(ValueError, match="not bodies"):
        SimPlant(model, state, ["left"])
    with pytest.raises(ValueError, match="does not actuate"):
        SimPlant(model, state, ["table"])


def test_the_renderers_give_the_same_images_on_sim_worlds_opencv_threads_as_on_opencvs_default():
    """sim_world renders on ``OPENCV_THREADS`` (one: less CPU per image); the images are those of OpenCV's default
    thread count, bit for bit, noise included (fresh cameras, same seeds)."""
    config = pushing_config(camera='[camera]\nfps = 20.0\n')
    poses = [CUBE_POSE, CUBE_POSE + np.array([0.01, -0.005, 0.0, 0.0, 0.0, 0.0, 0.0])]

    def images() -> list[np.ndarray]:
        camera = tag_camera(config, lambda: CUBE_POSE)
        depth = BubbleDepthCamera.from_config(config, "bubble", 0)
        return [camera.render(pose) for pose in poses] + [depth.render(BUBBLE_POSE, pose) for pose in poses]

    default_threads = cv2.getNumThreads()
    try:
        cv2.setNumThreads(sim_world.OPENCV_THREADS)
        on_sim_worlds = images()
    finally:
        cv2.setNumThreads(default_threads)
    for got, want in zip(on_sim_worlds, images(), strict=True):
        np.testing.assert_array_equal(got, want)


def test_duration_stats_give_rate_mean_and_max_then_start_over():
    stats = DurationStats("physics")
    for duration_s in (0.002, 0.004, 0.009):
        stats.add(duration_s)
    assert stats.summary(0.5) == "physics 6.0 Hz, 5.0 ms mean, 9.0 ms max"
    assert stats.summary(1.0) == "physics 0.0 Hz, 0.0 ms mean, 0.0 ms max"


# --- sim_world as a process ---------------------------------------------------------------------------------------


def free_loopback_host() -> str:
    """A free 127.0.0.N for this module's simulated UR controllers (``loopback.free_ur_host``)."""
    return free_ur_host(100, 150)


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("sim_world")
    run_dir = tmp / "run"
    run_dir.mkdir()
    host = free_loopback_host()
    config_path = tmp / "sim.toml"
    config_path.write_text(f'run_dir = "{run_dir}"\nmode = "sim"\n[scene]\ntask = "pushing"\n'
                           f'[camera]\nfps = {CAMERA_FPS}\n[sim]\nrate_hz = 50.0\n'
                           f'[[arms]]\nname = "bubble"\nur_host = "{host}"\nft_port = "{run_dir}/ft300-bubble"\n'
                           f'depth = {{ fps = {DEPTH_FPS} }}\n')
    process = ServiceProcess("sim_world", "sim_world", config_path, tmp / "sim_world.log")
    try:
        process.wait_ready(READY_TIMEOUT_S)
        yield load_config(config_path), process
    finally:
        rc = process.stop()
    assert rc == 0, process.log()


def receive(config, topics: tuple[str, ...], window_s: float) -> dict[str, list[msg.Message]]:
    """Every message on ``topics`` from sim_world during ``window_s`` s (after the first one arrived)."""

    async def collect() -> dict[str, list[msg.Message]]:
        got: dict[str, list[msg.Message]] = {topic: [] for topic in topics}
        with Bus() as bus:
            sub = LatestSubscriber(bus, config.endpoint("sim_world"), topics)
            deadline_s = None
            while deadline_s is None or time.monotonic() < deadline_s:
                updated = await sub.wait(window_s)
                if not updated:
                    break
                deadline_s = deadline_s or time.monotonic() + window_s
                for topic in updated:
                    got[topic].append(sub.latest(topic, max_age_s=window_s).value)
        return got

    return asyncio.run(asyncio.wait_for(collect(), 3 * window_s + 5.0))


def rate_hz(messages: list[msg.Message]) -> float:
    """The publisher's rate from the first and last message's seq and stamp (robust to messages we missed)."""
    first, last = messages[0], messages[-1]
    return (last.seq - first.seq) / ((last.stamp_ns - first.stamp_ns) * 1e-9)


def test_sim_world_publishes_images_depth_and_truth_at_their_rates(world):
    config, process = world
    got = receive(config, ("image/tag_camera", "depth/bubble", "eval/object_pose", "eval/contact_forces"),
                  RECEIVE_WINDOW_S)
    images, depths, poses = got["image/tag_camera"], got["depth/bubble"], got["eval/object_pose"]
    assert len(images) >= 5 and len(poses) >= 5 and len(depths) >= 2, {k: len(v) for k, v in got.items()}
    assert rate_hz(images) == pytest.approx(CAMERA_FPS, rel=0.35), process.log()
    assert rate_hz(poses) == pytest.approx(10.0, rel=0.3), process.log()
    assert rate_hz(depths) == pytest.approx(DEPTH_FPS, rel=0.5), process.log()
    image = images[-1]
    # a monochrome camera's grey image (one channel: a third of a BGR image's bytes)
    assert image.camera == "tag_camera" and image.image.shape == (480, 640, 1) and image.image.dtype == np.uint8
    assert image.frame.shape == (480, 640)
    assert image.hw_stamp_ns <= image.stamp_ns
    assert 50 < float(image.image.mean()) < 200  # a lit scene, not a blank frame
    np.testing.assert_allclose(poses[-1].pose, CUBE_POSE, atol=1e-4)
    depth = depths[-1]
    assert depth.depth.shape == (120, 160) and np.count_nonzero(depth.depth) > 0.9 * depth.depth.size
    forces = got["eval/contact_forces"][-1]
    assert forces.bodies == ("bubble", "table") and forces.forces[0, :, 2].sum() < -1.0  # the bubble presses down


def test_its_ur_simulator_answers_the_real_rtde_client_with_the_bubble_pose(world):
    import rtde_receive

    config, _ = world
    receiver = rtde_receive.RTDEReceiveInterface(config.arms[0].ur_host, -1.0, ["timestamp", "actual_TCP_pose"])
    try:
        np.testing.assert_allclose(receiver.getActualTCPPose(), [*BUBBLE_POSE[:3], 0.0, 0.0, 0.0], atol=1e-9)
    finally:
        receiver.disconnect()


def test_its_ft300_streams_the_bubbles_push_to_the_real_driver(world):
    from hydrosoft.drivers.robotiq_ft300.config import FT300Config
    from hydrosoft.drivers.robotiq_ft300.sensor import FT300Sensor

    config, _ = world

    async def read_force() -> np.ndarray:
        async with FT300Sensor(FT300Config(port=config.arms[0].ft_port)) as sensor:
            await asyncio.sleep(0.1)
            return (await sensor.read()).wrench

    wrench = asyncio.run(asyncio.wait_for(read_force(), 10.0))
    assert 1.0 < wrench[2] < 3.0, wrench  # about 1.9 N: the bubble pressing 5 mm into the cube
    assert np.all(np.abs(wrench[:2]) < 0.1), wrench


def control(host: str, **request) -> dict:
    with socket.create_connection((host, SIM_CONTROL_PORT), timeout=SOCKET_TIMEOUT_S) as conn:
        conn.sendall((json.dumps(request) + "\n").encode())
        reply = json.loads(conn.makefile().readline())
    assert reply["ok"], reply
    return reply


def test_moving_the_simulated_tcp_drags_the_cube(world):
    config, process = world
    host = config.arms[0].ur_host
    start = receive(config, ("eval/object_pose",), 0.3)["eval/object_pose"][-1].pose
    tcp = BUBBLE_POSE.copy()
    for _ in range(40):  # 20 mm in 0.8 s, through the controller's inspection port
        tcp[1] -= 0.0005
        control(host, op="impose_pose", pose=tcp.tolist())
        time.sleep(0.02)
    deadline_s = time.monotonic() + DRAG_SETTLE_S
    moved = np.zeros(3)
    while moved[1] > -0.008 and time.monotonic() < deadline_s:  # it lags the bubble while the shear builds up
        moved = receive(config, ("eval/object_pose",), 0.2)["eval/object_pose"][-1].pose[:3] - start[:3]
    assert moved[1] < -0.008, (moved, process.log())  # pushed along -y by most of the 20 mm
    assert abs(moved[0]) < 0.002 and abs(moved[2]) < 1e-4, moved
