"""The recording format (``services/recording/mcap_format.py``): what the recorder's own logging writes to a file reads back
exactly (depth frames and poses bit for bit, camera images as their JPEG or PNG holds them), images are stored
compressed and once, and recordings in the older all-JSON format still read."""

from __future__ import annotations

import json

import foxglove
import msgspec
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer
from test_recorder import assert_same

from hydrosoft.services.bus import messages as msg
from hydrosoft.services.recording.image_codec import ImageCodecError, encode_image
from hydrosoft.services.recorder import RecorderOptions, SceneLog, open_sinks
from hydrosoft.services.recording.mcap_format import (
    RawFormat,
    RecordingError,
    decode_raw,
    encode_raw,
    encoded_images,
    raw_channel_metadata,
    raw_channel_name,
    raw_schema,
    read_recording,
)
from hydrosoft.services.recording.foxglove_scene import SceneBuilder, SceneGeometry

POSE = np.array([0.1, -0.05, 0.02, np.cos(0.3), 0.0, 0.0, np.sin(0.3)])


def geometry() -> SceneGeometry:
    return SceneGeometry(bubbles={"bubble": (0.06, 0.045, 0.03)}, object_triangles=np.zeros((2, 3, 3)),
                         planner_points=np.eye(3) * 0.01, planner_bodies=("bubble", "table"),
                         static_frames={"tag_camera": ("world", POSE)})


def noisy_depth(seed: int) -> np.ndarray:
    """A 120 x 160 depth image like the sim's: a smooth membrane, 2 counts of noise, no return at the corners."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[:120, :160]
    depth = 1000 + 0.02 * ((x - 80) ** 2 + (y - 60) ** 2) + rng.normal(0, 2, (120, 160))
    depth[:10, :10] = 0
    return np.round(depth).astype(np.uint16)


def camera_image(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    image = np.full((120, 160, 3), 200, dtype=np.uint8)
    image[30:90, 40:120] = 20
    return np.clip(image + rng.normal(0, 2, image.shape), 0, 255).astype(np.uint8)


def stamped(message: msg.Message, seq: int) -> msg.Message:
    return msgspec.structs.replace(message, seq=seq, stamp_ns=1_000 + seq, source="sim_world")


def record(path, messages: list[tuple[str, msg.Message]], raw_format: RawFormat = RawFormat()) -> None:
    """``messages`` logged by the recorder's ``SceneLog`` into the MCAP file ``path``."""
    context = foxglove.Context()
    log = SceneLog(context, SceneBuilder(geometry(), epoch_offset_ns=10**18), raw_format)
    writer, _ = open_sinks(context, RecorderOptions(record=path), path, {})
    log.writer = writer
    for index, (topic, message) in enumerate(messages):
        log.log_message(topic, message, received_ns=10_000 + index)
    writer.close()


def test_recorded_depth_frames_and_poses_decode_bit_exactly_and_images_are_stored_once_compressed(tmp_path):
    depths = [msg.DepthFrame(bubble="bubble", depth=noisy_depth(k), depth_scale_m=1e-4, fx_px=40.0, fy_px=40.0,
                             cx_px=79.5, cy_px=59.5, hw_stamp_ns=k) for k in range(10)]
    arm = msg.ArmState(arm="bubble", tcp_pose=POSE, tcp_speed=np.full(6, 1 / 3), running=True,
                       protective_stop=False, emergency_stop=False, servo_active=True)
    tracked = msg.ObjectPose(object="object", pose=POSE * np.array([1 / 3, 1, 1, 1, 1, 1, 1]), tags_used=(1, 2),
                             quality=0.5)
    deformation = msg.MembraneDeformation(bubble="bubble", deformation=np.full((120, 160), np.nan, np.float32),
                                          reference_stamp_ns=5)
    sent = [("depth/bubble", stamped(d, k + 1)) for k, d in enumerate(depths)]
    sent += [("arm_state/bubble", stamped(arm, 1)), ("object_pose/object", stamped(tracked, 1)),
             ("deformation/bubble", stamped(deformation, 1))]
    path = tmp_path / "run.mcap"
    record(path, sent)
    messages, reader = read_recording(path)
    assert not reader.truncated and [(m.topic, m.message.seq) for m in messages] == [(t, m.seq) for t, m in sent]
    for item, (_, message) in zip(messages, sent):
        assert_same(item.message, message, ignore=())  # every field, arrays in dtype, shape and bytes
    raw_bytes = sum(d.depth.nbytes for d in depths)
    assert path.stat().st_size < 0.5 * raw_bytes, (path.stat().st_size, raw_bytes)  # the copies stored once
    with open(path, "rb") as stream:
        strict = make_reader(stream)
        channels = {channel.topic: channel for channel in strict.get_summary().channels.values()}
        assert channels["sim_world/depth/bubble"].message_encoding == "msgpack"
        assert channels["sim_world/arm_state/bubble"].message_encoding == "json"
        scene = {m.log_time: m.data for _, c, m in strict.iter_messages(topics=["/depth/bubble"])}
        raw = {m.log_time: msgspec.msgpack.decode(m.data)["depth"]
               for _, c, m in strict.iter_messages(topics=["sim_world/depth/bubble"])}
    assert len(scene) == len(raw) == 10
    for log_time, array in raw.items():
        assert array["encoding"] == "png" and array["data"] in scene[log_time]  # the scene copy: the same PNG


def test_camera_images_are_jpeg_by_default_and_raw_lossless_on_request():
    image = msg.CameraImage.of("tag_camera", camera_image(0))
    jpeg = encode_raw(image, None)
    back = decode_raw(msg.CameraImage, jpeg, "msgpack")
    assert back.image.shape == image.image.shape and back.image.dtype == np.uint8
    assert 0 < np.abs(back.image.astype(int) - image.image).mean() < 3.0
    raw = encode_raw(image, encoded_images(image, RawFormat(camera_format="raw")))
    assert_same(decode_raw(msg.CameraImage, raw, "msgpack"), image, ignore=())
    assert len(jpeg) < image.image.nbytes / 5 < len(raw)
    grey = msg.CameraImage.of("tag_camera", camera_image(1)[..., 0])
    assert_same(decode_raw(msg.CameraImage, encode_raw(grey, encoded_images(grey, RawFormat("raw"))), "msgpack"),
                grey, ignore=())
    with pytest.raises(ValueError, match="jpeg, raw"):
        RawFormat(camera_format="png")
    with pytest.raises(ValueError, match="1..100"):
        RawFormat(jpeg_quality=0)
    with pytest.raises(ImageCodecError, match="cannot hold float32"):
        encode_image(np.zeros((4, 4), np.float32), "png")


def test_a_damaged_image_is_a_recording_error_not_a_crash():
    depth = msg.DepthFrame(bubble="b", depth=noisy_depth(0), depth_scale_m=1e-4, fx_px=1.0, fy_px=1.0, cx_px=1.0,
                           cy_px=1.0)
    fields = msgspec.msgpack.decode(encode_raw(depth))
    fields["depth"]["data"] = fields["depth"]["data"][:100]
    with pytest.raises(RecordingError, match="not a PNG or JPEG|decodes to"):
        decode_raw(msg.DepthFrame, msgspec.msgpack.encode(fields), "msgpack")
    fields["depth"]["encoding"] = "gif"
    with pytest.raises(RecordingError, match="unknown encoding 'gif'"):
        decode_raw(msg.DepthFrame, msgspec.msgpack.encode(fields), "msgpack")
    with pytest.raises(RecordingError, match="unknown message encoding 'cbor'"):
        decode_raw(msg.DepthFrame, b"", "cbor")


def test_a_recording_in_the_older_all_json_format_still_reads(tmp_path):
    """Recordings made before the binary channels: every raw channel JSON, images as base64 raw arrays."""
    depth = stamped(msg.DepthFrame(bubble="bubble", depth=noisy_depth(3), depth_scale_m=1e-4, fx_px=1.0, fy_px=1.0,
                                   cx_px=1.0, cy_px=1.0), 1)
    old_json = msgspec.json.encode(depth, enc_hook=lambda a: {"dtype": a.dtype.str, "shape": a.shape,
                                                              "data": a.tobytes()})
    path = tmp_path / "old.mcap"
    with open(path, "wb") as stream:
        writer = Writer(stream)
        writer.start()
        schema = writer.register_schema("DepthFrame", "jsonschema", json.dumps(raw_schema(msg.DepthFrame)).encode())
        channel = writer.register_channel(raw_channel_name("depth/bubble", "sim_world"), "json", schema,
                                          raw_channel_metadata("depth/bubble", msg.DepthFrame, "sim_world"))
        writer.add_message(channel, log_time=1, data=old_json, publish_time=1)
        writer.finish()
    (item,), reader = read_recording(path)
    assert not reader.truncated
    assert_same(item.message, depth, ignore=())
