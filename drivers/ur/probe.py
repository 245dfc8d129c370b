"""Checks, in asyncio, that a UR controller answers before the ur_rtde constructors run.

ur_rtde's constructors hold the GIL while they wait (the receive client until its first data package, up to the
2.5 s read deadline; the control client for the dashboard and the script port), so calling them against a
controller that is gone or stalled would freeze the caller's event loop. These probes fail fast instead, with a
``NotConnected`` that names the host, the port and what went wrong. Nothing here blocks the loop.
"""

from __future__ import annotations

import asyncio
import contextlib
import struct

from hydrosoft.drivers.errors import NotConnected
from hydrosoft.drivers.ur import rtde_protocol as rtde
from hydrosoft.drivers.ur.config import RTDE_PORT

PROBE_PROTOCOL_VERSION = 2
PROBE_OUTPUT_HZ = 125.0  # every controller generation accepts this rate
PROBE_VARIABLE = "timestamp"


async def probe_port(host: str, port: int, name: str, timeout_s: float) -> None:
    """Open and close a TCP connection to ``host:port``; ``NotConnected`` when that fails within ``timeout_s``."""
    try:
        _, writer = await asyncio.wait_for(asyncio.open_connection(host, port), timeout_s)
    except (OSError, asyncio.TimeoutError) as exc:
        raise NotConnected(f"UR controller {host}: cannot reach the {name} port {port}: {error_text(exc)}") from exc
    await _close(writer)


async def probe_rtde_stream(host: str, timeout_s: float) -> None:
    """Ask the controller's RTDE server for ``timestamp`` and wait for one data package, all within ``timeout_s``.

    Raises ``NotConnected`` when the port is closed, the handshake is refused, or no data package arrives (a
    stalled stream).
    """
    try:
        reader, writer = await asyncio.wait_for(asyncio.open_connection(host, RTDE_PORT), timeout_s)
    except (OSError, asyncio.TimeoutError) as exc:
        raise NotConnected(f"UR controller {host}: cannot reach the RTDE port {RTDE_PORT}: {error_text(exc)}") from exc
    try:
        writer.write(rtde.encode_packet(rtde.CMD_REQUEST_PROTOCOL_VERSION, struct.pack(">H", PROBE_PROTOCOL_VERSION)))
        writer.write(
            rtde.encode_packet(rtde.CMD_SETUP_OUTPUTS, struct.pack(">d", PROBE_OUTPUT_HZ) + PROBE_VARIABLE.encode())
        )
        writer.write(rtde.encode_packet(rtde.CMD_START))
        await asyncio.wait_for(_first_data_package(reader), timeout_s)
    except asyncio.TimeoutError as exc:
        raise NotConnected(
            f"UR controller {host}: the RTDE server sent no data package within {timeout_s} s (stream stalled)"
        ) from exc
    except (OSError, rtde.RtdeProtocolError) as exc:
        raise NotConnected(f"UR controller {host}: RTDE handshake failed: {error_text(exc)}") from exc
    finally:
        await _close(writer)


async def _first_data_package(reader: asyncio.StreamReader) -> None:
    packets = rtde.PacketReader()
    while True:
        data = await reader.read(4096)
        if not data:
            raise rtde.RtdeProtocolError("the controller closed the connection")
        packets.feed(data)
        for packet in packets.packets():
            if packet.command == rtde.CMD_DATA_PACKAGE:
                return
            if packet.command in (rtde.CMD_SETUP_OUTPUTS, rtde.CMD_START) and packet.payload[:1] == b"\x00":
                raise rtde.RtdeProtocolError(f"the controller refused '{chr(packet.command)}'")


async def _close(writer: asyncio.StreamWriter) -> None:
    writer.close()
    with contextlib.suppress(OSError):
        await writer.wait_closed()


def error_text(exc: BaseException) -> str:
    """A short reason for ``exc`` to put in an error message."""
    if isinstance(exc, asyncio.TimeoutError):
        return "timed out"
    if isinstance(exc, ConnectionRefusedError):
        return "connection refused (nothing listens there)"
    return str(exc) or type(exc).__name__
