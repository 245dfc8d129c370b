"""The live view: ``hydrosoft-stack view`` (the recorder with only its Foxglove WebSocket sink) on the fake
publisher's bus; a WebSocket client on loopback gets the scene's channels advertised, subscribes, and decodes the
scene updates with the schemas the server sent. Every process is stopped by its pid; every wait has a timeout.
"""

from __future__ import annotations

import asyncio
import base64
import json
import re
import struct
import sys
import time

import websockets
from mcap.records import Schema
from mcap_protobuf.decoder import DecoderFactory
from recording_processes import Proc, publisher, remove_root, short_root, write_config

VIEW_TIMEOUT_S = 60.0
SUBPROTOCOL = "foxglove.sdk.v1"
EXPECTED = {"/tf", "/scene/bubbles", "/scene/object", "/scene/plan", "/scene/forces/predicted", "/scene/forces/true",
            "/image/tag_camera", "/depth/bubble", "ft_reader-bubble/wrench/bubble", "planner/plan/pushing"}
MESSAGE_DATA = 0x01  # the server's binary opcode for a message on a subscription
FRAMES = {"tag_camera", "depth_bubble", "bubble", "object_true"}  # static, arm_state, eval/object_pose


def view_port(proc: Proc) -> int:
    deadline_s = time.monotonic() + VIEW_TIMEOUT_S
    while time.monotonic() < deadline_s:
        found = re.search(r"live view: ws://127\.0\.0\.1:(\d+)", proc.log())
        if found:
            return int(found.group(1))
        time.sleep(0.1)
    raise AssertionError(f"no live view address in the log:\n{proc.log()}")


async def watch(port: int) -> tuple[dict[str, dict], dict[str, list]]:
    """Advertised channels by topic, and the decoded messages received on a few scene subscriptions."""
    channels: dict[str, dict] = {}
    decoded: dict[str, list] = {}
    subscribed: dict[int, str] = {}
    decoders = DecoderFactory()

    def done() -> bool:
        frames = {t.child_frame_id for update in decoded.get("/tf", []) for t in update.transforms}
        return FRAMES <= frames and all(decoded.get(t) for t in ("/scene/forces/predicted", "/scene/bubbles"))

    async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL]) as ws:
        assert ws.subprotocol == SUBPROTOCOL
        deadline_s = time.monotonic() + VIEW_TIMEOUT_S
        while not done():
            if time.monotonic() > deadline_s:
                frames = {t.child_frame_id for update in decoded.get("/tf", []) for t in update.transforms}
                raise AssertionError(f"within {VIEW_TIMEOUT_S} s: frames {frames}, decoded "
                                     f"{ {k: len(v) for k, v in decoded.items()} }, channels {sorted(channels)}")
            frame = await asyncio.wait_for(ws.recv(), VIEW_TIMEOUT_S)
            if isinstance(frame, str):
                op = json.loads(frame)
                if op["op"] == "advertise":
                    for channel in op["channels"]:
                        known = channel["topic"] in channels  # subscribe once per channel
                        channels[channel["topic"]] = channel
                        if not known and channel["topic"] in ("/scene/forces/predicted", "/tf", "/scene/bubbles"):
                            subscribed[len(subscribed) + 1] = channel["topic"]
                            await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                                {"id": len(subscribed), "channelId": channel["id"]}]}))
                continue
            assert frame[0] == MESSAGE_DATA
            subscription, _ = struct.unpack_from("<IQ", frame, 1)
            topic = subscribed[subscription]
            channel = channels[topic]
            schema = Schema(id=channel["id"], name=channel["schemaName"], encoding=channel["schemaEncoding"],
                            data=base64.b64decode(channel["schema"]))
            decode = decoders.decoder_for(channel["encoding"], schema)
            decoded.setdefault(topic, []).append(decode(frame[13:]))
        end_s = time.monotonic() + 2.0
        while not EXPECTED <= set(channels) and time.monotonic() < end_s:
            frame = await asyncio.wait_for(ws.recv(), 1.0)
            if isinstance(frame, str) and json.loads(frame)["op"] == "advertise":
                channels.update({c["topic"]: c for c in json.loads(frame)["channels"]})
    return channels, decoded


def test_a_websocket_client_gets_the_scene_channels_and_decodes_their_updates():
    root = short_root()
    config = write_config(root)
    source = publisher(config, root)
    view = Proc([sys.executable, "-m", "hydrosoft.services.commands.view", config, "--port", "0"], "view", root / "view.log")
    try:
        source.wait_ready()
        view.wait_ready()
        try:
            channels, decoded = asyncio.run(watch(view_port(view)))
        except AssertionError as error:
            raise AssertionError(f"{error}\n{view.log()}") from None
    finally:
        view_exit = view.stop()
        source.stop()
        remove_root(root)
    assert EXPECTED <= set(channels), sorted(channels)
    assert channels["/scene/forces/predicted"]["schemaName"] == "foxglove.SceneUpdate"
    assert channels["/image/tag_camera"]["schemaName"] == "foxglove.CompressedImage"
    assert channels["sim_world/image/tag_camera"]["encoding"] == "msgpack"  # an image kind's raw channel
    wrench = channels["ft_reader-bubble/wrench/bubble"]
    assert wrench["encoding"] == "json" and wrench["schemaName"] == "Wrench"
    forces = decoded["/scene/forces/predicted"][-1]
    assert {entity.id for entity in forces.entities} == {"predicted/bubble", "predicted/table"}
    assert sum(len(entity.arrows) for entity in forces.entities) > 0
    bubbles = decoded["/scene/bubbles"][-1].entities[0]
    assert bubbles.frame_id == "bubble" and round(bubbles.spheres[0].size.x, 6) == 0.12
    assert view_exit == 0
