"""Run in a private network namespace (``unshare -n``): two links over that namespace's own 127.0.0.1, an
inter-host one (CURVE forced on loopback, so it gets ``INTER_HOST_TCP_OPTIONS``) and a plain one, each a publisher
sending 100 messages/s to a ``LatestSubscriber``. Once both carry messages, the loopback interface goes down (every
packet lost, as with a pulled cable); for ``WATCH_S`` the script notes when each subscriber counts its link as
dropped (``link_dropped``) and when each publisher's socket monitor sees its link closed. Prints one JSON object:
``{"inter_host": {"subscriber": s, "publisher": s}, "plain": {...}}``, seconds after the cut (null: not closed).

Used by tests/services/test_bus.py; nothing here reaches beyond the namespace."""

from __future__ import annotations

import asyncio
import json
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np
import zmq
import zmq.auth
from zmq.utils.monitor import parse_monitor_message

from hydrosoft.services.bus import sockets as b
from hydrosoft.services.bus import messages as m

WATCH_S = 8.0
CONNECT_TIMEOUT_S = 5.0
PERIOD_S = 0.01
WRENCH = m.Wrench(sensor="ft", wrench=np.zeros(6), tared=True)


async def main() -> dict:
    subprocess.run(["ip", "link", "set", "lo", "up"], check=True)
    with tempfile.TemporaryDirectory() as folder:
        public, secret = zmq.auth.create_certificates(folder, "host")
        Path(secret).chmod(0o600)
        curve = b.CurveKeys(Path(secret), Path(public).parent, loopback=True)
        with b.Bus(curve=curve) as inter_host, b.Bus() as plain:
            links = {}
            for name, bus in (("inter_host", inter_host), ("plain", plain)):
                publisher = b.Publisher(bus, "tcp://127.0.0.1:*", source=name)
                subscriber = b.LatestSubscriber(bus, publisher.endpoint, ["wrench"])
                monitor = publisher._sock.get_monitor_socket(zmq.EVENT_DISCONNECTED)
                links[name] = (publisher, subscriber, monitor)
            deadline_s = time.monotonic() + CONNECT_TIMEOUT_S
            while not all(subscriber.received["wrench"] for _, subscriber, _ in links.values()):
                if time.monotonic() > deadline_s:
                    raise SystemExit("the links did not connect")
                for publisher, subscriber, _ in links.values():
                    await publisher.send(WRENCH, "wrench")
                    subscriber.drain()
                await asyncio.sleep(PERIOD_S)
            subprocess.run(["ip", "link", "set", "lo", "down"], check=True)
            cut_s = time.monotonic()
            closed: dict[str, dict[str, float | None]] = {name: {"subscriber": None, "publisher": None}
                                                          for name in links}
            while time.monotonic() - cut_s < WATCH_S:
                for name, (publisher, subscriber, monitor) in links.items():
                    await publisher.send(WRENCH, "wrench")
                    subscriber.drain()
                    if closed[name]["subscriber"] is None and subscriber.errors.counts["link_dropped"]:
                        closed[name]["subscriber"] = time.monotonic() - cut_s
                    while await monitor.poll(0):
                        event = parse_monitor_message(await monitor.recv_multipart())
                        if closed[name]["publisher"] is None and event["event"] == zmq.EVENT_DISCONNECTED:
                            closed[name]["publisher"] = time.monotonic() - cut_s
                await asyncio.sleep(PERIOD_S)
            for _, _, monitor in links.values():
                monitor.close(linger=0)
            return closed


if __name__ == "__main__":
    print(json.dumps(asyncio.run(main())))
