"""The recorder: its plain parts, the raw channels' codec, and two recordings of one run of the fake publisher and
the real tag tracker (``conftest.recorded_run``): one recorder SIGKILLed mid-run (default format: JPEG camera
images), whose file reads back every message up to its last flush, and one stopped cleanly (lossless), whose file
passes the MCAP reader's strict checks and whose every message decodes with its channel's own schema and a standard
JSON or msgpack decoder, without our code.
"""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import jsonschema
import msgspec
import numpy as np
import pytest
from fakes.bus_publisher import expected, rendered_images, topics
from mcap.reader import make_reader
from mcap.records import Chunk
from mcap.stream_reader import StreamReader
from mcap_protobuf.decoder import DecoderFactory

from hydrosoft.services.bus import messages as msg
from hydrosoft.services.bus.config import parse_config
from hydrosoft.services.recorder import (
    FLUSH_PERIOD_S,
    ChunkBudget,
    RecorderError,
    RecorderOptions,
    SeqGaps,
    bus_endpoints,
    recording_path,
)
from hydrosoft.services.recording.mcap_format import (
    CLOCK_METADATA,
    RecordingError,
    bus_topic,
    decode_raw,
    encode_raw,
    raw_encoding,
    raw_schema,
    read_recording,
)

#: The most a SIGKILL may cost here: the unflushed second, plus what a recorder starved by other tests on two busy
#: cores had not read yet, s (on an idle machine the last message read back is under 1.2 s older than the kill).
KILL_LOSS_S = FLUSH_PERIOD_S + 4.0
#: Header fields the publisher sets (and, for images, the exposure stamp it takes at send time).
STAMPED = ("seq", "stamp_ns", "source")
#: How far a JPEG camera image of the default quality may be from the image sent: mean absolute error, grey levels.
JPEG_MEAN_ERROR = 3.0
SCENE_TOPICS = {"/tf", "/scene/bubbles", "/scene/object", "/scene/plan", "/scene/forces/predicted",
                "/scene/forces/true", "/image/tag_camera", "/depth/bubble"}


def assert_same(recorded: msgspec.Struct, sent: msgspec.Struct, ignore: tuple[str, ...] = STAMPED) -> None:
    """Every field equal, arrays in dtype, shape and bytes, nested structs field by field."""
    assert type(recorded) is type(sent)
    for name in type(sent).__struct_fields__:
        if name in ignore:
            continue
        a, b = getattr(recorded, name), getattr(sent, name)
        if isinstance(b, np.ndarray):
            assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes(), name
        elif isinstance(b, msgspec.Struct):
            assert_same(a, b, ignore=())
        else:
            assert a == b, name


def by_topic(messages) -> dict[str, list]:
    grouped: dict[str, list] = {}
    for item in messages:
        grouped.setdefault(item.topic, []).append(item.message)
    return grouped


def check_published_contents(messages, config, images, jpeg: bool = False) -> dict[str, list]:
    """Each topic of the fake publisher: contiguous seqs, each message as sent (``jpeg``: camera images within
    ``JPEG_MEAN_ERROR`` of the sent ones, every other array bit for bit); returns the messages by topic."""
    grouped = by_topic(messages)
    for topic in topics(config):
        received = grouped[topic]
        seqs = [m.seq for m in received]
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs))), f"{topic}: gaps in {seqs}"
        for message in received:
            sent = expected(topic, message.seq, config, images)
            ignore = STAMPED + ("hw_stamp_ns",) if topic.startswith("image/") else STAMPED
            if jpeg and topic.startswith("image/"):
                assert message.image.shape == sent.image.shape and message.image.dtype == sent.image.dtype
                error = np.abs(message.image.astype(np.int16) - sent.image).mean()
                assert 0 < error < JPEG_MEAN_ERROR, (topic, message.seq, error)
                ignore += ("image",)
            assert_same(message, sent, ignore)
    return grouped


# --- plain parts -------------------------------------------------------------------------------------------------


def test_raw_messages_round_trip_bit_exactly_and_match_their_json_schema():
    deformation = np.full((4, 5), np.nan, dtype=np.float32)
    deformation[1, 2] = 1.25e-3
    sent = [
        msg.MembraneDeformation(bubble="b", deformation=deformation, reference_stamp_ns=7, seq=3, stamp_ns=11,
                                source="bubble_camera-b", hw_stamp_ns=None),
        msg.Wrench(sensor="b", wrench=np.array([0.1, 1 / 3, -2.5e-300, 0, 5e300, np.pi]), tared=True, hw_stamp_ns=9),
        msg.StatusReply(ok=True, goal=msg.Goal(task="pushing", target_pose=np.array([0.1, 0, 0.02, 1, 0, 0, 0.0]),
                                               tolerance_mm=5.0, timeout_s=30.0),
                        status=msg.ServiceStatus(state="ready", pid=1, uptime_s=2.0, errors={"x": 1})),
    ]
    for message in sent:
        data = encode_raw(message)
        back = decode_raw(type(message), data, raw_encoding(type(message)))
        assert_same(back, message, ignore=())
        loads = json.loads if raw_encoding(type(message)) == "json" else msgspec.msgpack.decode
        jsonschema.validate(loads(data), raw_schema(type(message)))
    assert raw_schema(msg.Wrench)["title"] == "Wrench" and raw_schema(msg.Wrench)["type"] == "object"
    with pytest.raises(RecordingError, match="Wrench"):
        decode_raw(msg.Wrench, b'{"sensor": 1}')
    nan_wrench = {"sensor": "b", "tared": True, "wrench": {"dtype": "<f8", "shape": [6],
                                                           "data": np.full(6, np.nan).tobytes()}}
    with pytest.raises(msg.NonFinite):  # validated as the bus validates
        decode_raw(msg.Wrench, msgspec.json.encode(nan_wrench))


def test_plain_parts():
    gaps = SeqGaps()
    assert [gaps.missing("t", "a", s) for s in (1, 2, 5, 6, 1, 2)] == [0, 0, 2, 0, 0, 0]  # 1 after 6: a restart
    assert [gaps.missing("t", "b", s) for s in (1, 2)] == [0, 0]  # another publisher of the same topic
    assert recording_path(Path("/r/run.mcap"), 0).name == "run.mcap"
    assert recording_path(Path("/r/run.mcap"), 2).name == "run.restart2.mcap"
    budget = ChunkBudget(100)  # closes a chunk before what would overflow it, never before the first message
    assert [budget.close_before(n) for n in (150, 10, 60, 40, 1)] == [False, True, False, True, False]
    budget.closed()
    assert budget.close_before(90) is False
    with pytest.raises(RecorderError, match="nothing to do"):
        RecorderOptions()
    with pytest.raises(RecorderError, match="loopback"):
        RecorderOptions(view=True, view_host="0.0.0.0")
    config = parse_config('run_dir = "/tmp/x"\n[[arms]]\nname = "bubble"\n'
                          '[endpoints]\n"planner.data" = "tcp://10.0.0.2:5555"\n'
                          '[curve]\nsecret_key_file = "/k"\nauthorized_keys_dir = "/d"\n')
    local, remote = bus_endpoints(config)
    assert remote == ["tcp://10.0.0.2:5555"]
    assert "ipc:///tmp/x/sim_world.data" in local and "ipc:///tmp/x/planner.status" in local and len(local) == 11


# --- recordings of a run -----------------------------------------------------------------------------------------


def test_a_sigkilled_recorder_leaves_every_message_up_to_its_last_flush_readable_with_schemas(recorded_run):
    run = recorded_run
    messages, reader = read_recording(run.killed)
    grouped = check_published_contents(messages, run.config, rendered_images(run.config), jpeg=True)
    for topic in topics(run.config):
        last_stamp_ns = grouped[topic][-1].stamp_ns
        assert last_stamp_ns > run.kill_ns - KILL_LOSS_S * 1e9, (
            f"{topic}: the last message read back was sent {(run.kill_ns - last_stamp_ns) * 1e-9:.2f} s before "
            "the kill")
        assert grouped[topic][0].seq == 1, f"{topic} recorded from seq {grouped[topic][0].seq}"
    assert reader.epoch_offset_ns > 0 and CLOCK_METADATA in reader.metadata
    for topic, channel in reader.channels.items():
        schema = reader.schemas[channel.schema_id]
        if topic.startswith("/"):
            assert channel.message_encoding == "protobuf" and schema.name.startswith("foxglove."), topic
        else:
            kind = msg.kind_for_topic(bus_topic(channel))
            assert (channel.message_encoding, schema.encoding) == (raw_encoding(kind), "jsonschema"), topic
            assert schema.name == kind.__name__
            assert topic == f"{channel.metadata['hydrosoft.source']}/{bus_topic(channel)}"
    with open(run.killed, "rb") as stream:
        chunks = 0
        try:
            for record in StreamReader(stream, emit_chunks=True).records:
                chunks += isinstance(record, Chunk)
        except Exception:  # noqa: BLE001 - the incomplete last chunk
            pass
    assert chunks >= 5, chunks


def test_a_clean_recording_passes_the_strict_reader_and_decodes_with_its_own_schemas(recorded_run):
    run = recorded_run
    assert run.clean_exit == 0, run.logs["recorder-clean"]
    messages, reader = read_recording(run.clean)
    assert not reader.truncated
    check_published_contents(messages, run.config, rendered_images(run.config))
    grouped = by_topic(messages)
    assert "object_pose/object" in grouped and "tags/tag_camera" in grouped  # the tag tracker's, live
    assert "status/tag_tracker" in grouped and "heartbeat/ft_reader-bubble" in grouped
    assert SCENE_TOPICS <= set(reader.scene_counts), reader.scene_counts
    with open(run.clean, "rb") as stream:
        strict = make_reader(stream, validate_crcs=True, decoder_factories=[DecoderFactory()])
        summary = strict.get_summary()
        assert summary is not None and summary.chunk_indexes and summary.statistics is not None
        counts: Counter[str] = Counter()
        for schema, channel, message, decoded in strict.iter_decoded_messages(
                topics=[t for t in reader.channels if t.startswith("/")]):
            counts[channel.topic] += 1
            assert decoded is not None
        for schema, channel, message in strict.iter_messages(topics=[t for t in reader.channels
                                                                     if not t.startswith("/")]):
            counts[channel.topic] += 1
            loads = json.loads if channel.message_encoding == "json" else msgspec.msgpack.decode
            jsonschema.validate(loads(message.data), json.loads(schema.data))
    assert sum(counts.values()) == summary.statistics.message_count
    assert dict(summary.statistics.channel_message_counts) == {
        summary.channels[i].id: counts[summary.channels[i].topic] for i in summary.channels}
    image = next(m for m in messages if m.topic == "image/tag_camera").message
    assert msgspec.msgpack.decode(encode_raw(image))["image"]["shape"] == [480, 640, 1]  # sim's grey tag camera


def test_the_material_fit_reads_a_live_stack_recording_as_one_trajectory(recorded_run):
    from hydrosoft.bench.stack_recording import read_stack_recording

    messages, _ = read_recording(recorded_run.clean, ["arm_state/bubble", "object_pose/object"])
    grouped = by_topic(messages)
    read = read_stack_recording(recorded_run.clean, object_name="cube", clamped=True)
    assert read.arm == "bubble" and read.kept >= 2, (read.kept, read.dropped)
    states = np.stack([m.tcp_pose for m in sorted(grouped["arm_state/bubble"], key=lambda m: m.stamp_ns)])
    low, high = np.minimum(states[:-1], states[1:]) - 1e-12, np.maximum(states[:-1], states[1:]) + 1e-12
    for pose in read.trajectory.bubble_poses:  # interpolated to the wrench stamps: between two recorded states
        assert ((low[:, :3] <= pose[:3]) & (pose[:3] <= high[:, :3])).all(axis=1).any()
    first = min(grouped["object_pose/object"], key=lambda m: m.stamp_ns).pose
    np.testing.assert_array_equal(read.trajectory.object_poses, np.broadcast_to(first, (read.kept, 7)))
