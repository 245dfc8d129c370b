"""A stand-in for any stack service, run by the real launcher in its tests (``$HYDROSOFT_SERVICE_MODULE=fake_service``
with this folder on ``PYTHONPATH``).

``python -m fake_service CONFIG --name NAME`` runs through ``run_service`` like a real service: it binds its status
endpoint, publishes a ``Heartbeat`` on ``heartbeat/NAME-data`` at ``DATA_RATE_HZ`` on its data endpoint (so its status
shows a rate) and logs one line naming itself, its restart count and the arms the launcher told it to wait for
(``$HYDROSOFT_AWAIT_ARMS``, the planner's). What it does beyond that is chosen per service
name by ``$HYDROSOFT_FAKE_MODES`` (``"NAME=MODE,NAME=MODE"``; unnamed services are ``ok``):

- ``ok``: ready at once, runs until stopped.
- ``crash``: ready, then raises after ``CRASH_AFTER_S`` (exit 1).
- ``exit_clean``: ready, then returns after ``CRASH_AFTER_S`` (exit 0).
- ``never_ready``: never reports READY.
- ``slow_ready``: reports READY after ``SLOW_READY_S`` (as the planner does after loading its solver).
- ``hang_on_stop``: ready; its shutdown hook blocks the loop for ``HANG_S`` (only SIGKILL ends it).
- ``errors``: ready, with one error counted (kind ``fake_input``), shown in its status.
- ``spawns_child``: ready, after starting a ``sleep`` in its process group that ignores SIGINT, so that it outlives
  the service unless its group is swept (logs ``child PID``).
"""

from __future__ import annotations

import argparse
import asyncio
import os
import subprocess
import sys
import time

from hydrosoft.services.bus.config import load_config
from hydrosoft.services.bus.messages import Heartbeat
from hydrosoft.services.bus.runtime import AWAIT_ARMS_ENV, Service, run_service

MODES_ENV = "HYDROSOFT_FAKE_MODES"
DATA_RATE_HZ = 20.0
CRASH_AFTER_S = 0.2
HANG_S = 60.0
SLOW_READY_S = 2.0


def mode_for(name: str) -> str:
    """This service's mode from ``$HYDROSOFT_FAKE_MODES``."""
    for item in os.environ.get(MODES_ENV, "").split(","):
        key, _, mode = item.partition("=")
        if key.strip() == name:
            return mode.strip()
    return "ok"


async def fake_main(service: Service, data_endpoint: str, mode: str) -> None:
    publisher = service.publisher(data_endpoint)
    service.log.info("fake service %s in mode %s, awaits arms %r (restart %d)", service.name, mode,
                     os.environ.get(AWAIT_ARMS_ENV), service.restarts)
    if mode == "hang_on_stop":
        async def hang() -> None:
            time.sleep(HANG_S)  # blocks the loop on purpose: the runtime's shutdown bound cannot cut it off

        service.on_shutdown(hang)
    if mode == "errors":
        service.count_error("fake_input", "a malformed fake input")
    if mode == "spawns_child":
        child = subprocess.Popen(["sh", "-c", f"trap '' INT; exec sleep {HANG_S}"])  # ignores the group's SIGINT
        service.log.info("child %d", child.pid)
    if mode == "slow_ready":
        await asyncio.sleep(SLOW_READY_S)
    if mode != "never_ready":
        await service.ready()
    started_s = time.monotonic()
    while True:
        await publisher.send(Heartbeat(period_s=1.0 / DATA_RATE_HZ), f"heartbeat/{service.name}-data")
        await asyncio.sleep(1.0 / DATA_RATE_HZ)
        if mode in ("crash", "exit_clean") and time.monotonic() - started_s > CRASH_AFTER_S:
            if mode == "crash":
                raise RuntimeError("fake crash")
            return


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m fake_service")
    parser.add_argument("config")
    parser.add_argument("--name", required=True)
    args = parser.parse_args(argv)
    config = load_config(args.config)
    mode = mode_for(args.name)

    async def service_main(service: Service) -> None:
        await fake_main(service, config.endpoint(args.name, "data"), mode)

    return run_service(args.name, config.runtime(args.name), service_main)


if __name__ == "__main__":
    sys.exit(main())
