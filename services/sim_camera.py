"""sim_camera (sim-hardware mode only): the simulated tag camera's images, rendered in a process of their own.

sim_world's shutter publishes the object's true pose on ``eval/object_pose`` at ``camera.fps``, each message
stamped with the time of the plant state it carries. This service renders each into the tag camera's image
(``services/sim/tag_camera.py``: the renderer, noise seed and calibration sim_world used before) and publishes it
on ``image/tag_camera`` (``CameraImage``), ``hw_stamp_ns`` = the truth's stamp: the exposure is the instant of the
world it shows. Rendering in sim_world, beside the plant's step, the simulated UR controller and the FT 300, the
renderer waited for that process's GIL (exposure to image 7-12 ms during goals against 2-3 ms at rest); a real
camera does not wait for a simulator.

It renders the newest truth not rendered yet; truths that came while it rendered are dropped (a real camera's frames
are, too), never rendered as a burst, so the images are those a camera at ``camera.fps`` takes. The noise of each
image is the generator's next (seed ``IMAGE_SEED``): the same poses in the same order give the same images, bit for
bit.

Health: it reports ready only once it has rendered and published its first image (it waits for sim_world's truth,
within the launcher's ready timeout). No new truth for ``STALE_TRUTH_PERIODS`` frame periods: counted as
``stale_truth``, and the service reports ``degraded`` with a note naming the missing input until truths come again;
nothing is published meanwhile. A truth that is not a pose (the bus checks its shape, finite values and the
quaternion's norm) or not a message at all is counted by kind and dropped before it reaches the renderer. The
exposure-to-image latency is logged every ``RATE_LOG_PERIOD_S``. The reader (``TruthFeed``) is plain logic over a
subscriber, tested without a process; ``serve`` is the loop.

Run: ``python -m hydrosoft.services.sim_camera CONFIG`` (the launcher starts it after sim_world in sim mode).
"""

from __future__ import annotations

import argparse
import asyncio
from dataclasses import dataclass

import numpy as np

from hydrosoft.drivers.errors import Stale
from hydrosoft.services.bus import messages as msg
from hydrosoft.services.bus import service_cli, sockets
from hydrosoft.services.bus.config import ConfigError, StackConfig
from hydrosoft.services.bus.runtime import Service
from hydrosoft.services.sim.devices import image_topic
from hydrosoft.services.sim.stats import DurationStats
from hydrosoft.services.sim.tag_camera import tag_camera
from hydrosoft.services.tag_tracker import TAG_CAMERA, report_health

SERVICE = "sim_camera"
#: The service whose shutter (``eval/object_pose``) this one renders.
TRUTH_SOURCE = "sim_world"
#: No new truth for this many frame periods: stale (the tracker's camera goes stale after as many).
STALE_TRUTH_PERIODS = 5.0
RATE_LOG_PERIOD_S = 10.0  # how often the exposure-to-image latency is logged


@dataclass(frozen=True)
class Truth:
    """One exposure: the object's pose ``(7,)`` float64 (base frame, m, wxyz) at ``stamp_ns`` (``time.monotonic_ns``
    of the plant state it is, the image's ``hw_stamp_ns``)."""

    pose: np.ndarray
    stamp_ns: int


class TruthFeed:
    """The newest object pose truth on a subscriber, each handed out once (the subscriber has checked it is a pose).

    Args:
        subscriber: a latest-value subscriber connected to sim_world's data endpoint and subscribed to
            ``eval/object_pose`` (its owner closes it).
        timeout_s: ``read`` raises ``Stale`` when no new truth arrives within this long (s); also the oldest truth
            it hands out.
    """

    topic = msg.EvalObjectPose.topic

    def __init__(self, subscriber: sockets.LatestSubscriber, timeout_s: float) -> None:
        if not timeout_s > 0:
            raise ValueError(f"TruthFeed: timeout_s must be > 0 s, got {timeout_s!r}")
        self.timeout_s = timeout_s
        self._subscriber = subscriber
        self._last_stamp_ns = 0

    async def read(self) -> Truth:
        """The newest truth published after the one returned last, waiting up to ``timeout_s`` for it.

        Raises:
            Stale: when no newer truth arrives within ``timeout_s``.
        """
        loop = asyncio.get_running_loop()
        deadline_s = loop.time() + self.timeout_s
        while True:
            received = self._newer()
            if received is not None:
                self._last_stamp_ns = received.stamp_ns
                return Truth(received.value.pose, received.stamp_ns)
            remaining_s = deadline_s - loop.time()
            if remaining_s <= 0:
                raise Stale(f"no object pose truth from {TRUTH_SOURCE} ({self.topic}) within {self.timeout_s:.3g} s")
            await self._subscriber.wait(remaining_s)

    def _newer(self) -> sockets.Received[msg.EvalObjectPose] | None:
        """The newest truth if it is younger than ``timeout_s`` and newer than the last one returned."""
        try:
            received = self._subscriber.latest(self.topic, self.timeout_s, msg.EvalObjectPose)
        except sockets.Stale:
            return None
        return received if received.stamp_ns > self._last_stamp_ns else None


async def _log_latency_forever(service: Service, stats: DurationStats) -> None:
    loop = asyncio.get_running_loop()
    since_s = loop.time()
    while True:
        await asyncio.sleep(RATE_LOG_PERIOD_S)
        now_s = loop.time()
        service.log.info("%s", stats.summary(now_s - since_s))
        since_s = now_s


async def serve(service: Service, config: StackConfig) -> None:
    """Render every exposure of sim_world's shutter until cancelled (see the module docstring)."""
    if config.mode != "sim":
        raise ConfigError(f"sim_camera runs only in mode = 'sim', the config says {config.mode!r}")
    camera = tag_camera(config, lambda: np.full(7, np.nan))  # the pose comes with each truth, not from the source
    subscriber = service.subscriber(config.endpoint(TRUTH_SOURCE), [TruthFeed.topic])
    feed = TruthFeed(subscriber, STALE_TRUTH_PERIODS / config.camera.fps)
    out = service.publisher(config.endpoint(service.name, "data"))
    topic = image_topic(TAG_CAMERA)
    stats = DurationStats("tag camera (exposure to image)")
    service.note = f"waiting for {TRUTH_SOURCE}'s object pose truth"
    await service.publish_status()
    async with asyncio.TaskGroup() as tasks:
        tasks.create_task(_log_latency_forever(service, stats))
        while True:
            try:
                truth = await feed.read()
            except Stale as error:
                if service.state != "starting":  # before the first image, sim_world may still be starting
                    service.count_error("stale_truth", str(error))
                    await report_health(service, str(error))
                continue
            sent = await out.send(msg.CameraImage.of(TAG_CAMERA, camera.render(truth.pose), truth.stamp_ns), topic)
            stats.add((sent.stamp_ns - truth.stamp_ns) * 1e-9)
            if service.state == "starting":
                service.note = ""
                await service.ready()
            else:
                await report_health(service, "")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments: CONFIG (mode = 'sim') [--name sim_camera] (``service_cli``)."""
    service_cli.add_arguments(parser, SERVICE)


def run(args: argparse.Namespace) -> int:
    """Run sim_camera until SIGINT/SIGTERM; the exit code (2 for a config that cannot be used)."""
    return service_cli.run(args, serve)


def main(argv: list[str] | None = None) -> int:
    return service_cli.main(SERVICE, __doc__, argv, add_arguments, run)


if __name__ == "__main__":
    service_cli.exit_process(main())
