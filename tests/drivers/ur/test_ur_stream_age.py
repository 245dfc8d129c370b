"""Age of the newest controller sample, from its timestamp against the host clock."""

from __future__ import annotations

import pytest

from hydrosoft.drivers.ur.stream_age import StreamAge

S = 1_000_000_000  # ns per s
BOOT_S = 1000.0  # the controller started 1000 s before the host's clock origin


def test_fresh_stream_reads_as_its_delivery_jitter():
    age = StreamAge()
    for k in range(1000):  # 500 Hz samples delivered 1-3 ms after they were stamped
        device_s = k * 0.002
        assert age.observe(device_s, round((BOOT_S + device_s + 0.001 + 0.002 * (k % 2)) * S)) <= 0.002 + 1e-9


def test_a_stall_ages_one_second_per_second_even_when_polled_rarely():
    age = StreamAge()
    age.observe(5.000, round((BOOT_S + 5.001) * S))
    assert age.observe(5.000, round((BOOT_S + 5.301) * S)) == pytest.approx(0.3, abs=1e-3)
    rare = StreamAge()
    rare.observe(1.000, round((BOOT_S + 1.001) * S))
    # one poll 10 s later finds a sample stamped 0.5 s before: the stamp changed, yet the sample is old
    assert rare.observe(10.501, round((BOOT_S + 11.001) * S)) == pytest.approx(0.5, abs=0.02)


def test_slow_controller_clock_never_reads_as_stale():
    age = StreamAge()
    worst = 0.0
    for k in range(3600):  # one hour, one poll a second, controller clock 200 ppm slow
        host_s = BOOT_S + k
        worst = max(worst, age.observe(k * (1 - 200e-6), round(host_s * S)))
    assert worst < 1e-3


def test_reset_forgets_the_old_clock():
    age = StreamAge()
    age.observe(500.0, round((BOOT_S + 500.0) * S))
    age.reset()  # the controller rebooted: its timestamp restarted from zero
    assert age.observe(0.5, round((BOOT_S + 600.0) * S)) == 0.0
    with pytest.raises(ValueError, match="drift_allowance"):
        StreamAge(drift_allowance=1.0)
