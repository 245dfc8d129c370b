"""The recording's file format: how a bus message becomes an MCAP message that standard tools decode, and back.

An MCAP recording (written by ``recorder``) holds two sorts of channels:

- one **raw channel per bus topic and publishing service**, named ``SERVICE/TOPIC``
  (``ft_reader-bubble/wrench/bubble``, ``planner/status/planner``; one topic can have two publishers: sim_world
  renders ``depth/ARM`` and the bubble camera passes it on), schema encoding ``jsonschema`` (derived from the
  message's ``msgspec`` struct). Every field travels as itself, header (``seq``, ``stamp_ns``, ``source``)
  included; a numpy array travels as ``{"dtype": "<f8", "shape": [6], "data": BYTES}`` (the raw little-endian
  C-ordered bytes), so ``decode_raw`` rebuilds the exact message, arrays bit for bit (camera images: as their JPEG
  holds them, unless recorded raw). Two message encodings:

  - the kinds with an image field (``IMAGE_KINDS``: camera images, depth frames, membrane deformation) are
    ``msgpack`` (``BINARY_ENCODING``): bytes as bytes, no base64. A depth frame's counts are a lossless 16-bit PNG
    and a camera image is a JPEG (``RawFormat.camera_format``, ``jpeg_quality``), marked by the array's
    ``"encoding"`` (``png`` or ``jpeg``); with ``camera_format = "raw"`` camera images stay raw bytes (lossless: the
    zstd chunks compress them as well as PNG did, and they decode in well under a millisecond where a 640 x 480 PNG
    took 17 ms). The recorder logs the same bytes on the image's scene channel, and the file's zstd chunks store the
    second copy as a back-reference: the bulk of a recording is stored once, compressed.
  - every other kind is ``json``: arrays in base64, so Foxglove and any JSON reader decode them without our code.

  Recordings written before the binary channels (every channel ``json``, images as raw base64 arrays) still read:
  the reader decodes each channel by its own message encoding. The channel's metadata names the bus topic
  (``hydrosoft.topic``), the message kind (``hydrosoft.kind``) and the publishing service (``hydrosoft.source``).
- **scene channels** (names starting with ``/``) in Foxglove's well-known schemas (``services/recording/foxglove_scene.py``): what a
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

from hydrosoft.services.bus import messages as msg
from hydrosoft.services.recording.image_codec import FORMATS, JPEG, PNG, EncodedImage, decode_image, encode_image

#: Channel metadata keys of a raw channel: its bus topic, message kind and publishing service.
TOPIC_KEY = "hydrosoft.topic"
KIND_KEY = "hydrosoft.kind"
SOURCE_KEY = "hydrosoft.source"
#: Name of the metadata record holding the clock offset, and its key.
CLOCK_METADATA = "hydrosoft.clock"
EPOCH_OFFSET_KEY = "epoch_offset_ns"
#: The raw channels' message encodings (module docstring).
JSON_ENCODING = "json"
BINARY_ENCODING = "msgpack"
#: ``RawFormat.camera_format`` for camera images kept as raw bytes.
RAW = "raw"
CAMERA_FORMATS = (JPEG, RAW)
#: The kinds whose raw channels are binary: each has an image field.
IMAGE_KINDS = (msg.CameraImage, msg.DepthFrame, msg.MembraneDeformation)
_ARRAY_DESCRIPTION = ("A numpy array: dtype (numpy's string, e.g. '<f8', '<u2'), shape, and its raw little-endian "
                      "C-ordered bytes ({data}); with encoding 'png' or 'jpeg', the bytes of that image file.")


def _array_schema(data: dict[str, Any], where: str) -> dict[str, Any]:
    return {
        "title": "Array",
        "description": _ARRAY_DESCRIPTION.format(data=where),
        "type": "object",
        "properties": {
            "dtype": {"type": "string"},
            "shape": {"type": "array", "items": {"type": "integer", "minimum": 0}},
            "encoding": {"type": "string", "enum": list(FORMATS)},
            "data": data,
        },
        "required": ["dtype", "shape", "data"],
    }


#: JSON schema of one array field of a json channel, and of a msgpack channel (bytes are msgpack's bin type).
ARRAY_SCHEMA = _array_schema({"type": "string", "contentEncoding": "base64"}, "base64")
BINARY_ARRAY_SCHEMA = _array_schema({"description": "msgpack bin"}, "msgpack bin")


class RecordingError(Exception):
    """A recording that cannot be read, or a raw message that does not decode; the text names the file or topic."""


@dataclass(frozen=True)
class RawFormat:
    """How the recorder stores image fields. camera_format: ``jpeg`` (lossy, compact) or ``raw`` (lossless, several
    times larger) for camera images; jpeg_quality: 1..100 (75: a sim camera image of 640 x 480 in 12 kB, 2.1 grey
    levels rms from the original, whose own noise is 2; 85 took 23 kB, 90 34 kB). Depth frames are always lossless
    PNG."""

    camera_format: str = JPEG
    jpeg_quality: int = 75

    def __post_init__(self) -> None:
        if self.camera_format not in CAMERA_FORMATS:
            raise ValueError(f"camera image format must be one of {', '.join(CAMERA_FORMATS)}, got "
                             f"{self.camera_format!r}")
        if not 1 <= self.jpeg_quality <= 100:
            raise ValueError(f"JPEG quality must be 1..100, got {self.jpeg_quality}")


class _ArrayJson(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    dtype: str
    shape: tuple[int, ...]
    data: bytes
    encoding: str = ""


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


def raw_encoding(kind: type[msg.Message]) -> str:
    """The message encoding of ``kind``'s raw channel: ``msgpack`` for the ``IMAGE_KINDS``, else ``json``."""
    return BINARY_ENCODING if issubclass(kind, IMAGE_KINDS) else JSON_ENCODING


def bus_topic(channel: Channel) -> str:
    """The bus topic a raw channel carries."""
    return channel.metadata.get(TOPIC_KEY, channel.topic)


def _schema_hook(type_: type) -> dict[str, Any]:
    if type_ is np.ndarray:
        return {"$ref": "#/$defs/Array"}
    raise NotImplementedError(f"no JSON schema for {type_!r}")


@functools.cache
def raw_schema(kind: type[msg.Message]) -> dict[str, Any]:
    """The JSON schema of ``kind``'s raw channel: an object with every struct field (arrays as ``ARRAY_SCHEMA``, or
    ``BINARY_ARRAY_SCHEMA`` on a msgpack channel)."""
    document = msgspec.json.schema(kind, schema_hook=_schema_hook)
    array = BINARY_ARRAY_SCHEMA if raw_encoding(kind) == BINARY_ENCODING else ARRAY_SCHEMA
    defs = {**document["$defs"], "Array": array}
    return {**defs[kind.__name__], "$defs": defs}


def encoded_images(message: msg.Message, raw_format: RawFormat = RawFormat()) -> dict[str, EncodedImage]:
    """The compressed image fields of ``message`` by field name: a camera image as JPEG (none when ``raw_format``
    keeps it raw), a depth frame's counts as PNG; none for other kinds. Raises ImageCodecError for an image the
    format cannot hold."""
    match message:
        case msg.CameraImage() if raw_format.camera_format == JPEG:
            return {"image": encode_image(message.image, JPEG, raw_format.jpeg_quality)}
        case msg.DepthFrame():
            return {"depth": encode_image(message.depth, PNG)}
    return {}


def _array_to_json(value: Any) -> dict[str, Any]:
    if not isinstance(value, np.ndarray):
        raise TypeError(f"cannot encode {type(value).__name__}")
    array = np.ascontiguousarray(value)
    return {"dtype": array.dtype.str, "shape": array.shape, "data": memoryview(array).cast("B")}


def _array_to_builtins(value: Any) -> dict[str, Any]:
    array = _array_to_json(value)
    return {**array, "shape": list(array["shape"]), "data": array["data"].tobytes()}


def encode_raw(message: msg.Message, images: dict[str, EncodedImage] | None = None) -> bytes:
    """The bytes of ``message`` on its raw channel, in its kind's ``raw_encoding``. ``images``: its compressed image
    fields (default: ``encoded_images(message)``), used on a msgpack channel."""
    if raw_encoding(type(message)) == JSON_ENCODING:
        return msgspec.json.encode(message, enc_hook=_array_to_json)
    fields = msgspec.to_builtins(message, enc_hook=_array_to_builtins, builtin_types=(bytes,))
    for name, image in (encoded_images(message) if images is None else images).items():
        array = getattr(message, name)
        fields[name] = {"dtype": array.dtype.str, "shape": list(array.shape), "encoding": image.format,
                        "data": image.data}
    return msgspec.msgpack.encode(fields)


def _to_array(type_: type, obj: Any) -> Any:
    if type_ is not np.ndarray:
        raise NotImplementedError(f"unexpected type {type_!r}")
    array = msgspec.convert(obj, _ArrayJson)
    try:
        if array.encoding:
            if array.encoding not in FORMATS:
                raise ValueError(f"unknown encoding {array.encoding!r}")
            return decode_image(array.data, array.dtype, array.shape)
        return np.frombuffer(array.data, dtype=np.dtype(array.dtype)).reshape(array.shape)
    except (TypeError, ValueError) as error:
        raise RecordingError(f"array {array.dtype} {array.shape} of {len(array.data)} bytes: {error}") from None


def decode_raw(kind: type[msg.Message], data: bytes, encoding: str = JSON_ENCODING) -> msg.Message:
    """The message of ``kind`` a raw channel's ``data`` in message ``encoding`` (``json`` or ``msgpack``) holds,
    validated as the bus validates it. Raises RecordingError (or the ``MessageError`` of a message that breaks its
    kind's rules)."""
    decoders = {JSON_ENCODING: msgspec.json.decode, BINARY_ENCODING: msgspec.msgpack.decode}
    if encoding not in decoders:
        raise RecordingError(f"{kind.__name__}: unknown message encoding {encoding!r}")
    try:
        message = decoders[encoding](data, type=kind, dec_hook=_to_array)
    except msgspec.ValidationError as error:
        raise RecordingError(f"{kind.__name__}: {error}") from None
    except msgspec.DecodeError as error:
        raise RecordingError(f"{kind.__name__}: not {encoding}: {error}") from None
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
        kinds: dict[int, tuple[type[msg.Message], str]] = {}
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
                        kinds[record.id] = (_kind_of(record), record.message_encoding)
                        names[record.id] = bus_topic(record)
                elif isinstance(record, Metadata):
                    self.metadata[record.name] = dict(record.metadata)
                elif isinstance(record, Message):
                    topic = names.get(record.channel_id, "")
                    if record.channel_id in kinds:
                        yield _recorded(topic, record, *kinds[record.channel_id])
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


def _recorded(topic: str, record: Message, kind: type[msg.Message], encoding: str) -> RecordedMessage:
    try:
        message = decode_raw(kind, record.data, encoding)
    except (RecordingError, msg.MessageError) as error:
        raise RecordingError(f"{topic} at log time {record.log_time}: {error}") from None
    return RecordedMessage(topic, message, record.log_time)
