"""A stand-in for a running stack's publishers, for the recorder and replay tests: one process that publishes, on
the endpoints the config gives the real services, messages whose contents follow from their ``seq``.

``python bus_publisher.py CONFIG`` runs as the service ``ft_reader-ARM`` (first arm; status and heartbeat on its
status endpoint), binds its endpoints, waits ``CONNECT_S`` and publishes until SIGINT, each topic on its own
schedule (``RATES_HZ``):

- ``wrench/ARM`` (ft_reader-ARM), ``arm_state/ARM`` (arm_commander-ARM);
- ``image/tag_camera`` (sim_world): the scene's object rendered by sim_world's tag camera at one of
  ``IMAGE_POSES`` in turn (rendered once at start), stamped ``hw_stamp_ns`` = the send time;
- ``depth/ARM``, ``eval/object_pose``, ``eval/contact_forces`` (sim_world) and ``plan/TASK`` (planner), the plan's
  forces shaped for the planner's scene (``SceneGeometry``).

``expected(topic, seq, config)`` rebuilds what was sent as message ``seq`` of ``topic`` (header and, for images,
``hw_stamp_ns`` aside), so a test can check recorded contents without a log of what was sent.
"""

from __future__ import annotations

import asyncio
import sys
import time

import numpy as np

from hydrosoft.services.bus import messages as msg
from hydrosoft.services.bus.sockets import Publisher
from hydrosoft.services.bus.config import StackConfig, load_config
from hydrosoft.services.bus.runtime import Service, run_service
from hydrosoft.services.sim.render import tag_camera

RATES_HZ = {"wrench": 100.0, "arm_state": 50.0, "image": 10.0, "depth": 10.0, "eval": 10.0, "plan": 5.0}
#: Object poses (base frame) the tag camera images show, one after the other.
IMAGE_POSES = (np.array([0.0, 0.0, 0.024215, 1.0, 0.0, 0.0, 0.0]),
               np.array([0.02, -0.01, 0.024215, np.cos(0.15), 0.0, 0.0, np.sin(0.15)]))
DEPTH_SHAPE = (120, 160)
PLANNER_POINTS = 64  # the pushing scene at the default planner spacing
#: The publishers queue this many messages per subscriber (the stack's 16 can drop messages to a subscriber whose
#: process the two busy cores leave unscheduled for a moment; the tests count every message).
SNDHWM = 1000
#: Between binding and READY, s: subscribers waiting for the endpoints connect meanwhile, so they get seq 1.
CONNECT_S = 1.0


def _pose(seq: int) -> np.ndarray:
    angle = 0.001 * seq
    return np.array([0.001 * seq, -0.0005 * seq, 0.1, np.cos(angle), 0.0, 0.0, np.sin(angle)])


def expected(topic: str, seq: int, config: StackConfig, images: list[np.ndarray] | None = None) -> msg.Message:
    """Message ``seq`` of ``topic`` as this publisher builds it (before the publisher stamps it; an image's
    ``hw_stamp_ns`` is left None). ``images``: the rendered images (needed for ``image/tag_camera`` only)."""
    arm = config.arms[0].name
    kind, _, instance = topic.partition("/")
    if kind == "wrench":
        return msg.Wrench(sensor=arm, wrench=np.arange(6.0) * seq * 1e-3 + 1.0 / 3.0, tared=True, hw_stamp_ns=seq)
    if kind == "arm_state":
        return msg.ArmState(arm=arm, tcp_pose=_pose(seq), tcp_speed=np.full(6, seq * 1e-4), running=True,
                            protective_stop=False, emergency_stop=False, servo_active=seq % 7 != 0)
    if kind == "image":
        return msg.CameraImage.of(instance, images[seq % len(images)])
    if kind == "depth":
        depth = (np.arange(DEPTH_SHAPE[0] * DEPTH_SHAPE[1], dtype=np.uint32).reshape(DEPTH_SHAPE) * seq) % 65521
        return msg.DepthFrame(bubble=instance, depth=depth.astype(np.uint16), depth_scale_m=1e-4, fx_px=40.0,
                              fy_px=40.0, cx_px=79.5, cy_px=59.5, hw_stamp_ns=seq)
    if topic == "eval/object_pose":
        return msg.EvalObjectPose(object="object", pose=IMAGE_POSES[seq % len(IMAGE_POSES)])
    if topic == "eval/contact_forces":
        points = np.linspace(-0.025, 0.025, 30).repeat(3).reshape(30, 3)
        forces = np.sin(np.arange(2 * 30 * 3, dtype=np.float64) + seq).reshape(2, 30, 3)
        return msg.EvalContactForces(bodies=(arm, "table"), points=points, forces=forces)
    if kind == "plan":
        k = config.planner.horizon
        poses = np.tile(np.array([0.0, 0.0, 0.024215, 1.0, 0.0, 0.0, 0.0], dtype=np.float32), (k, 1))
        forces = np.cos(np.arange(2 * PLANNER_POINTS * 3, dtype=np.float32) * 0.1 + seq).reshape(2, PLANNER_POINTS, 3)
        return msg.Plan(task=instance, actions=np.full((k, 2, 6), seq * 1e-4, dtype=np.float32),
                        predicted_object_poses=poses, predicted_forces=forces, cost=seq * 0.5, solve_ms=100.0 + seq)
    raise ValueError(f"this publisher does not send {topic!r}")


def topics(config: StackConfig) -> dict[str, tuple[str, str]]:
    """Each topic this publisher sends -> (the service whose data endpoint it goes to, its RATES_HZ key)."""
    arm = config.arms[0].name
    return {f"wrench/{arm}": (f"ft_reader-{arm}", "wrench"), f"arm_state/{arm}": (f"arm_commander-{arm}", "arm_state"),
            "image/tag_camera": ("sim_world", "image"), f"depth/{arm}": ("sim_world", "depth"),
            "eval/object_pose": ("sim_world", "eval"), "eval/contact_forces": ("sim_world", "eval"),
            f"plan/{config.scene.task}": ("planner", "plan")}


def rendered_images(config: StackConfig) -> list[np.ndarray]:
    """The tag camera's image of each of ``IMAGE_POSES``."""
    return [tag_camera(config, lambda p=pose: p).render(pose) for pose in IMAGE_POSES]


async def _publish_forever(out: Publisher, topic: str, rate_hz: float, config: StackConfig,
                           images: list[np.ndarray]) -> None:
    loop = asyncio.get_running_loop()
    next_s = loop.time()
    seq = 0
    while True:
        seq += 1
        message = expected(topic, seq, config, images)
        if isinstance(message, msg.CameraImage):
            message = msg.CameraImage.of(message.camera, message.frame, hw_stamp_ns=time.monotonic_ns())
        await out.send(message, topic)
        next_s += 1.0 / rate_hz
        await asyncio.sleep(max(0.0, next_s - loop.time()))


async def serve(service: Service, config: StackConfig) -> None:
    loop = asyncio.get_running_loop()
    images = await loop.run_in_executor(None, rendered_images, config)
    publishers: dict[str, Publisher] = {}
    for source, _ in topics(config).values():
        if source not in publishers:
            publishers[source] = Publisher(service.bus, config.endpoint(source), source=source, sndhwm=SNDHWM)
    await asyncio.sleep(CONNECT_S)
    await service.ready()
    async with asyncio.TaskGroup() as tasks:
        for topic, (source, rate) in topics(config).items():
            tasks.create_task(_publish_forever(publishers[source], topic, RATES_HZ[rate], config, images))


def main() -> int:
    config = load_config(sys.argv[1])
    name = f"ft_reader-{config.arms[0].name}"

    async def service_main(service: Service) -> None:
        await serve(service, config)

    return run_service(name, config.runtime(name), service_main)


if __name__ == "__main__":
    sys.exit(main())
