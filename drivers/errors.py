"""The drivers' exceptions: one root, a few kinds a service can act on."""

from __future__ import annotations


class DriverError(Exception):
    """Root of every driver failure."""


class NotConnected(DriverError, ConnectionError):
    """The device is not connected (never connected, closed, or the link dropped)."""


class Stale(DriverError):
    """The device stopped producing new data: its newest reading is older than the driver's limit."""


class ProtocolError(DriverError):
    """The device sent bytes that do not parse (bad frame, bad CRC, unexpected reply)."""


class DeviceFault(DriverError):
    """The device reports a fault of its own (protective stop, emergency stop, script not running)."""
