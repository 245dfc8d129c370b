"""The recorder service: every bus message to an MCAP file, and the same scene live over Foxglove's WebSocket.

It subscribes to every publisher of the config (each service's data and status endpoint; endpoints beyond this
host, which need CURVE keys, are left out with a warning) and asks the planner for its ``StatusReply`` every
``PLANNER_POLL_S`` (the goal and the object's error travel only there). Each message goes to one foxglove-sdk
logging context with up to two sinks:

- ``--record PATH.mcap``: an MCAP file (``mcap_format`` says what is in it: a raw channel per bus topic and the
  scene channels of ``foxglove_scene``), its chunks compressed with zstd at ``ZSTD_LEVEL``. Camera images are JPEGs of
  ``--jpeg-quality`` (``--camera-images raw``: lossless); depth frames, poses and every other array are kept
  exactly. Chunks hold at most ``CHUNK_SIZE_BYTES`` and the current chunk is closed every
  ``FLUSH_PERIOD_S``, so a crash of the recorder (even SIGKILL) loses at most the last second: the file reads up to
  its last complete chunk. A restarted recorder writes ``PATH.restartN.mcap`` and never overwrites a file.
- ``--view``: Foxglove's WebSocket server on ``--view-host`` (loopback only: the protocol has no authentication)
  and ``--view-port`` (0: any free port); connect Foxglove to ``ws://HOST:PORT``.

Every message received is written; a gap in a topic's ``seq`` (messages the recorder did not get, e.g. dropped by
a publisher's high-water mark) is counted as ``gap``, a message that does not decode under its kind, a scene
conversion that fails as ``foxglove_scene``. None of these stops the recording. The shutdown closes the file with its
summary and index; the launcher stops the recorder last, so the stack's own shutdown is in the file.

Run: ``python -m hydrosoft.services.recorder CONFIG [--name recorder] [--record PATH.mcap] [--view [--view-port P]]``.
"""

from __future__ import annotations

import argparse
import asyncio
import functools
import ipaddress
import json
import sys
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import foxglove
import foxglove.channels
import zmq
from foxglove.mcap import MCAPCompression, MCAPWriteOptions, MCAPWriter

from hydrosoft.services.bus import messages as msg
from hydrosoft.services.bus import service_cli
from hydrosoft.services.bus.sockets import RequestClient, is_local_endpoint
from hydrosoft.services.bus.config import StackConfig
from hydrosoft.services.recording.image_codec import ImageCodecError
from hydrosoft.services.recording.mcap_format import (
    CLOCK_METADATA,
    EPOCH_OFFSET_KEY,
    CAMERA_FORMATS,
    RawFormat,
    encode_raw,
    encoded_images,
    epoch_offset_ns,
    BINARY_ENCODING,
    raw_channel_metadata,
    raw_channel_name,
    raw_encoding,
    raw_schema,
)
from hydrosoft.services.bus.runtime import Service
from hydrosoft.services.recording.foxglove_scene import SceneBuilder, SceneError, SceneGeometry, SceneOutput, scene_topics

SERVICE = "recorder"
#: Uncompressed size of the MCAP file's chunks, bytes (about half a second of the sim stack; 256 KiB chunks made its
#: recording a fifth larger, each membrane deformation image compressing alone): the recorder
#: closes a chunk before a message that would take it past this (``ChunkBudget``); the writer's own limit is
#: ``WRITER_CHUNK_FACTOR`` times larger, a backstop.
CHUNK_SIZE_BYTES = 1024 * 1024
WRITER_CHUNK_FACTOR = 4
#: zstd level of the chunks (zstd's default). Level 9 made a sim stack recording 3 % smaller but compressed at 20 MB/s
#: where 3 did 134 MB/s: with camera images kept raw (18 MB/s of input) the recorder fell behind on 2 busy cores.
ZSTD_LEVEL = 3
#: The current chunk is closed and written this often, s: the most a SIGKILL can lose.
FLUSH_PERIOD_S = 1.0
#: The static scene (frames, bubbles, object) is logged this often, s, so that a late viewer gets it.
STATIC_PERIOD_S = 1.0
#: How often the planner's StatusReply (goal, error, solves) is asked for, s; each request times out after this.
PLANNER_POLL_S = 0.5
#: Messages the SUB socket queues before ZeroMQ drops new ones (the reading loop is usually far ahead).
RCVHWM = 2000
#: How often the SUB socket tries again to connect to an endpoint nobody binds yet, ms (ZeroMQ's default, 100 ms,
#: would miss up to a tenth of a second of each service that starts after the recorder).
RECONNECT_IVL_MS = 10
#: How often the message counts are logged, s.
STATS_LOG_PERIOD_S = 10.0
#: Default port of the live view (Foxglove's default).
VIEW_PORT = 8765


class RecorderError(Exception):
    """The recorder cannot start as asked; the text says what to change."""


@dataclass(frozen=True)
class RecorderOptions:
    """record: the MCAP file to write, or None. view: serve the live view. view_host, view_port: where (port 0:
    any free port). raw_format: how image fields are stored."""

    record: Path | None = None
    view: bool = False
    view_host: str = "127.0.0.1"
    view_port: int = VIEW_PORT
    raw_format: RawFormat = RawFormat()

    def __post_init__(self) -> None:
        if self.record is None and not self.view:
            raise RecorderError("nothing to do: give --record PATH.mcap, --view or both")
        try:
            loopback = ipaddress.ip_address(self.view_host).is_loopback
        except ValueError:
            loopback = False
        if self.view and not loopback:
            raise RecorderError(f"--view-host {self.view_host!r} is not a loopback address: the live view has no "
                                "authentication; serve it on 127.0.0.1 and reach it through an ssh tunnel")


def bus_endpoints(config: StackConfig) -> tuple[list[str], list[str]]:
    """The publisher endpoints of ``config``'s services (each one's data and status endpoint), split into those on
    this host and those beyond it (which would need CURVE keys)."""
    endpoints = [config.endpoint(name, kind) for name in config.service_names() for kind in ("data", "status")]
    local = [e for e in endpoints if is_local_endpoint(e)]
    return local, [e for e in endpoints if e not in local]


def recording_path(path: Path, restarts: int) -> Path:
    """The file a recorder run writes: ``path``, or ``STEM.restartN.SUFFIX`` after N restarts."""
    return path if restarts == 0 else path.with_name(f"{path.stem}.restart{restarts}{path.suffix}")


class SeqGaps:
    """Per topic and publisher, the messages missing between consecutive ``seq`` numbers (a publisher that
    restarts starts again at 1, which is not a gap)."""

    def __init__(self) -> None:
        self._last: dict[tuple[str, str], int] = {}

    def missing(self, topic: str, source: str, seq: int) -> int:
        """How many messages of ``topic`` from ``source`` were not seen before this one, numbered ``seq``."""
        last = self._last.get((topic, source))
        self._last[(topic, source)] = seq
        return seq - last - 1 if last is not None and seq > last + 1 else 0


class ChunkBudget:
    """Where the recorder closes the file's chunks: before a message (with its scene copy) that would take the
    current chunk past ``limit_bytes``, so that a message and its scene copy share one chunk and zstd stores the copy
    as a back-reference (an image's copy in the next chunk would be stored again)."""

    def __init__(self, limit_bytes: int) -> None:
        self.limit_bytes = limit_bytes
        self.used_bytes = 0

    def close_before(self, nbytes: int) -> bool:
        """Whether to close the current chunk before logging ``nbytes`` more; counts them in either case."""
        close = self.used_bytes > 0 and self.used_bytes + nbytes > self.limit_bytes
        self.used_bytes = nbytes if close else self.used_bytes + nbytes
        return close

    def closed(self) -> None:
        """The chunk was closed (by the periodic flush)."""
        self.used_bytes = 0


class SceneLog:
    """The foxglove-sdk logging context with its sinks and channels: a raw channel per bus topic and publisher and a
    typed channel per scene topic, each made on first use. ``writer``, when set, is the MCAP file's, whose chunks
    ``chunks`` closes."""

    def __init__(self, context: foxglove.Context, builder: SceneBuilder, raw_format: RawFormat = RawFormat()) -> None:
        self.context = context
        self.builder = builder
        self.raw_format = raw_format
        self.writer: MCAPWriter | None = None
        self.chunks = ChunkBudget(CHUNK_SIZE_BYTES)
        self.counts: Counter[str] = Counter()
        self._raw: dict[str, foxglove.Channel] = {}
        self._scene: dict[str, object] = {}

    def log_message(self, topic: str, message: msg.Message, received_ns: int) -> None:
        """Log ``message`` on its raw channel and its scene channels, at ``received_ns`` (monotonic); an image is
        compressed once for both. Raises SceneError when it does not fit the scene or its image does not compress
        (the raw message is logged all the same, uncompressed)."""
        log_time = received_ns + self.builder.epoch_offset_ns
        name = raw_channel_name(topic, message.source)
        channel = self._raw.get(name)
        kind = type(message)
        if channel is None:
            schema = foxglove.Schema(name=kind.__name__, encoding="jsonschema",
                                     data=json.dumps(raw_schema(kind)).encode())
            channel = self._raw[name] = foxglove.Channel(
                name, schema=schema, message_encoding=raw_encoding(kind), context=self.context,
                metadata=raw_channel_metadata(topic, kind, message.source))
        try:
            images = encoded_images(message, self.raw_format)
        except ImageCodecError as error:
            channel.log(encode_raw(message, images={}), log_time=log_time)
            self.counts[topic] += 1
            raise SceneError(f"{topic}: image not compressed: {error}") from None
        if channel.has_sinks():
            data = encode_raw(message, images)
            copies = 2 if raw_encoding(kind) == BINARY_ENCODING else 1  # an image kind's scene copy is as large
            if self.writer is not None and self.chunks.close_before(copies * len(data)):
                self.writer.flush()
            channel.log(data, log_time=log_time)
        self.counts[topic] += 1
        self.log_scene(self.builder.convert(topic, message, images), log_time)

    def open_scene_channels(self, topics: dict[str, type]) -> None:
        """Make the scene channels ``topics`` (topic -> Foxglove message type) now. A channel made while a viewer is
        connected can be advertised to it before the server accepts subscriptions to it (foxglove-sdk 0.30
        answered such a subscription with "unknown channel" and never sent that channel's data); channels that
        exist when the viewer connects are advertised with the server's first message."""
        for topic, message_type in topics.items():
            if topic not in self._scene:
                self._scene[topic] = getattr(foxglove.channels, f"{message_type.__name__}Channel")(
                    topic, context=self.context)

    def log_scene(self, outputs: Sequence[SceneOutput], log_time: int) -> None:
        """Log scene messages at ``log_time`` (the file's clock)."""
        for topic, scene_message in outputs:
            channel = self._scene.get(topic)
            if channel is None:
                channel_class = getattr(foxglove.channels, f"{type(scene_message).__name__}Channel")
                channel = self._scene[topic] = channel_class(topic, context=self.context)
            channel.log(scene_message, log_time=log_time)

    def log_static(self, now_ns: int) -> None:
        """Log the static scene at ``now_ns`` (monotonic)."""
        self.log_scene(self.builder.static(now_ns), now_ns + self.builder.epoch_offset_ns)


def open_sinks(context: foxglove.Context, options: RecorderOptions, path: Path | None,
               metadata: dict[str, dict[str, str]]) -> tuple[MCAPWriter | None, foxglove.WebSocketServer | None]:
    """Open the MCAP writer (when ``path``) with ``metadata`` records, and the live view's server (when
    ``options.view``); returns ``(writer or None, server or None)``. Raises RecorderError when the file exists."""
    writer = server = None
    if path is not None:
        if path.exists():
            raise RecorderError(f"{path} exists; the recorder never overwrites a recording")
        path.parent.mkdir(parents=True, exist_ok=True)
        writer = foxglove.open_mcap(path, context=context, writer_options=MCAPWriteOptions(
            chunk_size=WRITER_CHUNK_FACTOR * CHUNK_SIZE_BYTES, compression=MCAPCompression.Zstd,
            compression_level=ZSTD_LEVEL, compression_threads=0))
        for name, values in metadata.items():
            writer.write_metadata(name, values)
    if options.view:
        server = foxglove.start_server(name="hydrosoft-stack", host=options.view_host, port=options.view_port,
                                       context=context)
    return writer, server


async def serve(service: Service, config: StackConfig, config_path: str, options: RecorderOptions) -> None:
    """Record (and serve) every bus message until cancelled (module docstring)."""
    loop = asyncio.get_running_loop()
    geometry = await loop.run_in_executor(None, SceneGeometry.from_config, config)
    offset_ns = epoch_offset_ns()
    context = foxglove.Context()
    scene = SceneLog(context, SceneBuilder(geometry, offset_ns), options.raw_format)
    scene.open_scene_channels(scene_topics(config, options.raw_format))
    path = recording_path(options.record, service.restarts) if options.record is not None else None
    metadata = {CLOCK_METADATA: {EPOCH_OFFSET_KEY: str(offset_ns)},
                "hydrosoft.run": {"config": str(Path(config_path).resolve()), "services": json.dumps(
                    config.service_names()), "config_text": Path(config_path).read_text()}}
    writer, server = open_sinks(context, options, path, metadata)
    scene.writer = writer

    async def close_sinks() -> None:
        if writer is not None:
            writer.close()
            service.log.info("closed %s (%d messages)", path, sum(scene.counts.values()))
        if server is not None:
            server.stop()

    service.on_shutdown(close_sinks)
    local, remote = bus_endpoints(config)
    for endpoint in remote:
        service.log.warning("not recording %s: not on this host (it would need CURVE keys)", endpoint)
    sock = service.bus.socket(zmq.SUB, local, bind=False, options=[
        (zmq.RCVHWM, RCVHWM), (zmq.RECONNECT_IVL, RECONNECT_IVL_MS), (zmq.MAXMSGSIZE, msg.MAX_FRAME_BYTES),
        (zmq.SUBSCRIBE, b"")])
    if path is not None:
        service.log.info("recording %d endpoints to %s", len(local), path)
    if server is not None:
        service.log.info("live view: ws://%s:%d (open it in Foxglove: Open connection, Foxglove WebSocket)",
                         options.view_host, server.port)
    gaps = SeqGaps()
    tasks = [asyncio.create_task(_static_and_flush_forever(scene, writer)),
             asyncio.create_task(_log_counts_forever(service, scene))]
    if is_local_endpoint(config.endpoint("planner", "cmd")):
        planner = RequestClient(service.bus, config.endpoint("planner", "cmd"), source=service.name,
                                timeout_s=PLANNER_POLL_S)
        tasks.append(asyncio.create_task(_poll_planner_forever(service, scene, planner)))
    await service.ready()
    try:
        while True:
            frames = await sock.recv_multipart(copy=False)
            received_ns = time.monotonic_ns()
            try:
                topic, message = msg.decode(frames)
            except msg.MessageError as error:
                service.count_error(error.kind, f"not recorded: {error}")
                continue
            missing = gaps.missing(topic, message.source, message.seq)
            if missing:
                service.count_error("gap", f"{missing} message(s) of {topic} from {message.source} before seq "
                                           f"{message.seq} not received")
            _log(service, scene, topic, message, received_ns)
    finally:
        for task in tasks:
            task.cancel()


def _log(service: Service, scene: SceneLog, topic: str, message: msg.Message, received_ns: int) -> None:
    try:
        scene.log_message(topic, message, received_ns)
    except SceneError as error:
        service.count_error("scene", str(error))


async def _static_and_flush_forever(scene: SceneLog, writer: MCAPWriter | None) -> None:
    while True:
        scene.log_static(time.monotonic_ns())
        if writer is not None:
            writer.flush()
            scene.chunks.closed()
        await asyncio.sleep(min(STATIC_PERIOD_S, FLUSH_PERIOD_S))


async def _poll_planner_forever(service: Service, scene: SceneLog, planner: RequestClient) -> None:
    while True:
        started_s = time.monotonic()
        try:
            reply = await planner.request(msg.GetStatus())
        except TimeoutError:
            pass  # no planner (yet): nothing to record
        except msg.MessageError as error:
            service.count_error(error.kind, f"the planner's status reply: {error}")
        else:
            _log(service, scene, msg.StatusReply.topic, reply, time.monotonic_ns())
        await asyncio.sleep(max(0.0, PLANNER_POLL_S - (time.monotonic() - started_s)))


async def _log_counts_forever(service: Service, scene: SceneLog) -> None:
    then = Counter(scene.counts)
    while True:
        await asyncio.sleep(STATS_LOG_PERIOD_S)
        now = Counter(scene.counts)
        service.log.info("%d messages on %d topics in %.0f s", sum((now - then).values()), len(now),
                         STATS_LOG_PERIOD_S)
        then = now


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments: CONFIG [--name recorder] [--record PATH.mcap] [--camera-images jpeg|raw] [--jpeg-quality Q] [--view]
    [--view-host H] [--view-port P]."""
    parser.add_argument("config", help="the stack's TOML config (deploy/sim.toml, deploy/lab.toml)")
    parser.add_argument("--name", default=SERVICE, help=f"service name (default {SERVICE})")
    parser.add_argument("--record", type=Path, default=None, metavar="PATH.mcap",
                        help="write every bus message to this MCAP file (it must not exist)")
    parser.add_argument("--camera-images", choices=CAMERA_FORMATS, default=RawFormat.camera_format,
                        help=f"how camera images are stored: jpeg (lossy, compact) or raw (lossless, several times "
                             f"larger); default {RawFormat.camera_format}")
    parser.add_argument("--jpeg-quality", type=int, default=RawFormat.jpeg_quality,
                        help=f"JPEG quality of camera images, 1..100 (default {RawFormat.jpeg_quality})")
    parser.add_argument("--view", action="store_true", help="serve the live view over Foxglove's WebSocket")
    parser.add_argument("--view-host", default="127.0.0.1", help="the live view's address (loopback only)")
    parser.add_argument("--view-port", type=int, default=VIEW_PORT,
                        help=f"the live view's port (default {VIEW_PORT}; 0: any free port, logged)")


def run(args: argparse.Namespace) -> int:
    """Run the recorder until SIGINT/SIGTERM; the exit code (2: a bad config or options)."""
    return run_with_options(args, lambda: RecorderOptions(record=args.record, view=args.view,
                                                          view_host=args.view_host, view_port=args.view_port,
                                                          raw_format=_raw_format(args)))


def _raw_format(args: argparse.Namespace) -> RawFormat:
    try:
        return RawFormat(args.camera_images, args.jpeg_quality)
    except ValueError as error:
        raise RecorderError(str(error)) from None


def run_with_options(args: argparse.Namespace, options: Callable[[], RecorderOptions]) -> int:
    """Run ``serve`` with the ``RecorderOptions`` that ``options()`` builds from the command line
    (``service_cli.run``); the exit code (2: options or a config that cannot be used)."""
    try:
        built = options()
    except RecorderError as err:
        print(f"{args.name}: {err}", file=sys.stderr)
        return 2
    return service_cli.run(args, functools.partial(serve, config_path=args.config, options=built))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog=f"python -m hydrosoft.services.{SERVICE}",
                                     description=__doc__.split("\n", 1)[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    service_cli.exit_process(main())
