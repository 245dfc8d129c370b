"""The recording's file format: how a bus message becomes an MCAP message that standard tools decode, and back.

An MCAP recording (written by ``recorder``) holds two sorts of channels:

- one **raw channel per bus topic and publishing service**, named ``SERVICE/TOPIC``
  (``ft_reader-bubble/wrench/bubble``, ``planner/status/planner``; one topic can have two publishers: sim_world
  renders ``depth/ARM`` and the bubble camera passes it on): message encoding ``json``, schema encoding
  ``jsonschema`` (derived from the message's ``msgspec`` struct, so Foxglove and any JSON reader decode it without
  our code). Every field travels as itself, header (``seq``, ``stamp_ns``, ``source``) included; a numpy array
  travels as ``{"dtype": "<f8", "shape": [6], "data": BASE64}`` (the raw little-endian C-ordered bytes), so
  ``decode_raw`` rebuilds the exact message, arrays bit for bit. The channel's metadata names
  the bus topic (``hydrosoft.topic``), the message kind (``hydrosoft.kind``) and the publishing service
  (``hydrosoft.source``).
- **scene channels** (names starting with ``/``) in Foxglove's well-known schemas (``services/scene.py``): what a
  person wants to look at. Replay and plots read only the raw channels.

Times. Every MCAP time (``log_time``, ``publish_time``, scene stamps) is on one clock: the host's
``time.monotonic_ns()`` plus a fixed offset to the Unix epoch taken when the recorder started (so viewers show the
wall-clock date and times never jump). ``log_time`` is when the recorder received the message; the foxglove SDK
writes ``publish_time`` equal to it. The publisher's own stamp stays exact in the raw message (``stamp_ns``,
monotonic); the offset is in the file's metadata record ``hydrosoft.clock`` (``epoch_offset_ns``).

A file cut short (a SIGKILLed recorder, a full disk) is readable up to its last complete chunk:
``RecordingReader`` reads records in file order and stops at the first incomplete one (``truncated`` says so).
"""

from __future__ import annotations

import functools
import struct
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
from mcap.exceptions import McapError
from mcap.records import Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader

from hydrosoft.services import messages as msg

#: Channel metadata keys of a raw channel: its bus topic, message kind and publishing service.
TOPIC_KEY = "hydrosoft.topic"
KIND_KEY = "hydrosoft.kind"
SOURCE_KEY = "hydrosoft.source"
#: Name of the metadata record holding the clock offset, and its key.
CLOCK_METADATA = "hydrosoft.clock"
EPOCH_OFFSET_KEY = "epoch_offset_ns"
#: JSON schema of one array field.
ARRAY_SCHEMA = {
    "title": "Array",
    "description": "A numpy array: dtype (numpy's string, e.g. '<f8', '<u2'), shape, and its raw little-endian "
                   "C-ordered bytes in base64.",
    "type": "object",
    "properties": {
        "dtype": {"type": "string"},
        "shape": {"type": "array", "items": {"type": "integer", "minimum": 0}},
        "data": {"type": "string", "contentEncoding": "base64"},
    },
    "required": ["dtype", "shape", "data"],
}


class RecordingError(Exception):
    """A recording that cannot be read, or a raw message that does not decode; the text names the file or topic."""


class _ArrayJson(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    dtype: str
    shape: tuple[int, ...]
    data: bytes


def epoch_offset_ns() -> int:
    """The offset from ``time.monotonic_ns()`` to Unix time now, ns (add it to a monotonic stamp)."""
    return time.time_ns() - time.monotonic_ns()


def is_raw_topic(topic: str) -> bool:
    """Whether an MCAP channel name is a raw channel's (scene channels start with ``/``)."""
    return not topic.startswith("/")


def raw_channel_name(topic: str, source: str) -> str:
    """The MCAP channel of bus topic ``topic`` published by service ``source``: ``SOURCE/TOPIC``."""
    return f"{source}/{topic}"


def raw_channel_metadata(topic: str, kind: type[msg.Message], source: str) -> dict[str, str]:
    """The metadata of a raw channel (see the module docstring)."""
    return {TOPIC_KEY: topic, KIND_KEY: kind.__name__, SOURCE_KEY: source}


def bus_topic(channel: Channel) -> str:
    """The bus topic a raw channel carries."""
    return channel.metadata.get(TOPIC_KEY, channel.topic)


def _schema_hook(type_: type) -> dict[str, Any]:
    if type_ is np.ndarray:
        return {"$ref": "#/$defs/Array"}
    raise NotImplementedError(f"no JSON schema for {type_!r}")


@functools.cache
def raw_schema(kind: type[msg.Message]) -> dict[str, Any]:
    """The JSON schema of ``kind``'s raw channel: an object with every struct field (arrays as ``ARRAY_SCHEMA``)."""
    document = msgspec.json.schema(kind, schema_hook=_schema_hook)
    defs = {**document["$defs"], "Array": ARRAY_SCHEMA}
    return {**defs[kind.__name__], "$defs": defs}


def _array_to_json(value: Any) -> dict[str, Any]:
    if not isinstance(value, np.ndarray):
        raise TypeError(f"cannot encode {type(value).__name__}")
    array = np.ascontiguousarray(value)
    return {"dtype": array.dtype.str, "shape": array.shape, "data": memoryview(array).cast("B")}


def encode_raw(message: msg.Message) -> bytes:
    """The JSON of ``message`` for its raw channel (arrays as dtype, shape and base64 bytes)."""
    return msgspec.json.encode(message, enc_hook=_array_to_json)


def _json_to_array(type_: type, obj: Any) -> Any:
    if type_ is not np.ndarray:
        raise NotImplementedError(f"unexpected type {type_!r}")
    array = msgspec.convert(obj, _ArrayJson)
    try:
        return np.frombuffer(array.data, dtype=np.dtype(array.dtype)).reshape(array.shape)
    except (TypeError, ValueError) as error:
        raise RecordingError(f"array {array.dtype} {array.shape} of {len(array.data)} bytes: {error}") from None


def decode_raw(kind: type[msg.Message], data: bytes) -> msg.Message:
    """The message of ``kind`` a raw channel's JSON ``data`` holds, validated as the bus validates it. Raises
    RecordingError (or the ``MessageError`` of a message that breaks its kind's rules)."""
    try:
        message = msgspec.json.decode(data, type=kind, dec_hook=_json_to_array)
    except msgspec.ValidationError as error:
        raise RecordingError(f"{kind.__name__}: {error}") from None
    except msgspec.DecodeError as error:
        raise RecordingError(f"{kind.__name__}: not JSON: {error}") from None
    msg.validate(message)
    return message


@dataclass(frozen=True)
class RecordedMessage:
    """One raw message of a recording. topic: its bus topic; message: the decoded message (header as published);
    log_time_ns: when the recorder received it, on the file's clock (ns, see the module docstring)."""

    topic: str
    message: msg.Message
    log_time_ns: int


class RecordingReader:
    """The raw messages of the MCAP file ``path`` in file order (only the bus topics ``topics`` and their sub-topics
    when given), read lazily by iterating, with chunk CRCs checked. What else the file holds is collected on the
    way: ``channels`` (by channel name), ``schemas`` (by id), ``metadata`` records (by name) and ``scene_counts``
    (messages per scene channel). A file that ends early (a killed recorder) yields everything up to its last
    complete chunk; then ``truncated`` is set and ``error`` names the incomplete record. Iterating raises
    RecordingError when the file is not MCAP at all or a raw message does not decode."""

    def __init__(self, path: str | Path, topics: Sequence[str] | None = None) -> None:
        self.path = Path(path)
        self.topics = None if topics is None else list(topics)
        self.channels: dict[str, Channel] = {}
        self.schemas: dict[int, Schema] = {}
        self.metadata: dict[str, dict[str, str]] = {}
        self.scene_counts: dict[str, int] = {}
        self.truncated = False
        self.error = ""

    @property
    def epoch_offset_ns(self) -> int:
        """The clock offset the recorder used (0 when its metadata record was not read yet)."""
        return int(self.metadata.get(CLOCK_METADATA, {}).get(EPOCH_OFFSET_KEY, 0))

    def raw_channels(self) -> dict[str, Channel]:
        """Every raw channel of the file (of ``topics``), by channel name, read without decoding any message; the
        file's metadata records are collected on the way."""
        channels = {}
        records = 0
        with open(self.path, "rb") as stream:
            try:
                for records, record in enumerate(StreamReader(stream).records, start=1):
                    if isinstance(record, Channel) and is_raw_topic(record.topic) and _wanted(record, self.topics):
                        channels[record.topic] = record
                    elif isinstance(record, Metadata):
                        self.metadata[record.name] = dict(record.metadata)
            except (McapError, EOFError, ValueError, struct.error) as error:
                if records == 0:
                    raise RecordingError(f"{self.path} is not a readable MCAP file: {error}") from None
        return channels

    def __iter__(self) -> Iterator[RecordedMessage]:
        kinds: dict[int, type[msg.Message]] = {}
        names: dict[int, str] = {}
        with open(self.path, "rb") as stream:
            records = StreamReader(stream, validate_crcs=True).records
            while True:
                try:
                    record = next(records, None)
                except (McapError, EOFError, ValueError, struct.error) as error:
                    if not self.channels and not self.schemas:
                        raise RecordingError(f"{self.path} is not a readable MCAP file: {error}") from None
                    self.truncated, self.error = True, f"{type(error).__name__}: {error}"
                    return
                if record is None:
                    return
                if isinstance(record, Schema):
                    self.schemas[record.id] = record
                elif isinstance(record, Channel):
                    self.channels[record.topic] = record
                    names[record.id] = record.topic
                    if is_raw_topic(record.topic) and _wanted(record, self.topics):
                        kinds[record.id] = _kind_of(record)
                        names[record.id] = bus_topic(record)
                elif isinstance(record, Metadata):
                    self.metadata[record.name] = dict(record.metadata)
                elif isinstance(record, Message):
                    topic = names.get(record.channel_id, "")
                    if record.channel_id in kinds:
                        yield _recorded(topic, record, kinds[record.channel_id])
                    elif not is_raw_topic(topic):
                        self.scene_counts[topic] = self.scene_counts.get(topic, 0) + 1


def read_recording(path: str | Path, topics: Sequence[str] | None = None) -> tuple[list[RecordedMessage],
                                                                                 RecordingReader]:
    """Every raw message of ``path`` (see ``RecordingReader``) in a list, and the reader that read them."""
    reader = RecordingReader(path, topics)
    return list(reader), reader


def _wanted(channel: Channel, topics: Sequence[str] | None) -> bool:
    """Whether a raw channel's bus topic is one of ``topics`` or below one (None: all)."""
    topic = bus_topic(channel)
    return topics is None or any(topic == t or topic.startswith(t.rstrip("/") + "/") for t in topics)


def _kind_of(channel: Channel) -> type[msg.Message]:
    try:
        kind = msg.kind_for_topic(bus_topic(channel))
    except msg.UnknownTopic as error:
        raise RecordingError(f"channel {channel.topic!r}: {error}") from None
    name = channel.metadata.get(KIND_KEY, "")
    if name and name != kind.__name__:
        raise RecordingError(f"channel {channel.topic!r} says it carries {name}, but the topic belongs to "
                             f"{kind.__name__}")
    return kind


def _recorded(topic: str, record: Message, kind: type[msg.Message]) -> RecordedMessage:
    try:
        message = decode_raw(kind, record.data)
    except (RecordingError, msg.MessageError) as error:
        raise RecordingError(f"{topic} at log time {record.log_time}: {error}") from None
    return RecordedMessage(topic, message, record.log_time)
