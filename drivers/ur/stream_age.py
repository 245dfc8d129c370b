"""Age of the newest sample of a stream that carries the sender's clock but not its own receive time.

ur_rtde hands out the latest RTDE values without saying when they arrived, and keeps handing out the same ones for
about 2.5 s after the stream stops. Each sample does carry the controller's ``timestamp`` (s since the controller
started), so the age of what we hold can be estimated as ``(host_s - device_s) - offset``, where ``offset`` is the
smallest ``host_s - device_s`` seen so far: the clock offset plus the fastest delivery. A stalled stream makes
``host_s - device_s`` grow one second per second, whether the reader polls at 500 Hz or once a minute.

Clock drift: if the controller's clock runs slow against the host, ``host_s - device_s`` creeps up even on a fresh
stream. The offset may therefore rise by ``drift_allowance`` seconds per second (default 1e-3, twenty times a
50 ppm crystal), so drift never reads as staleness while a stall still ages at ``1 - drift_allowance`` s per s.
"""

from __future__ import annotations

DEFAULT_DRIFT_ALLOWANCE = 1e-3  # s of offset rise per s of host time


class StreamAge:
    """Running estimate of the age (s) of the newest sample. ``reset()`` when the device may have restarted."""

    def __init__(self, drift_allowance: float = DEFAULT_DRIFT_ALLOWANCE) -> None:
        if not 0.0 <= drift_allowance < 1.0:
            raise ValueError(f"drift_allowance must be in [0, 1), got {drift_allowance}")
        self.drift_allowance = drift_allowance
        self._offset_s: float | None = None
        self._last_host_s = 0.0

    def reset(self) -> None:
        self._offset_s = None

    def observe(self, device_s: float, host_ns: int) -> float:
        """Age (s, >= 0) of the sample stamped ``device_s`` (device clock, s) held at ``host_ns`` (monotonic ns)."""
        host_s = host_ns / 1e9
        lag_s = host_s - device_s
        if self._offset_s is None:
            self._offset_s = lag_s
        else:
            allowed_rise_s = self.drift_allowance * max(0.0, host_s - self._last_host_s)
            self._offset_s = min(lag_s, self._offset_s + allowed_rise_s)
        self._last_host_s = host_s
        return lag_s - self._offset_s
