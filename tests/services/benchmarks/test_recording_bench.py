"""``bench recording``: its plain parts (the private config, the latency summary, the table). The whole benchmark
launches the sim stack for minutes, so it is run by hand (``hydrosoft-stack bench recording``), not here."""

from __future__ import annotations

import os
from pathlib import Path

from mcap.writer import Writer

from hydrosoft.services.benchmarks.launched_stack import DEFAULT_CONFIG, cpu_time_s, private_config
from hydrosoft.services.benchmarks.recording import PHASES, format_table, latency_summary, recorded_span_s
from hydrosoft.services.bus.config import load_config


def test_the_private_config_moves_the_run_dir_and_the_ur_controller(tmp_path):
    original = load_config(DEFAULT_CONFIG)
    private = load_config(private_config(DEFAULT_CONFIG, tmp_path))
    assert private.run_dir == str(tmp_path / "run")
    assert private.arms[0].ft_port == str(tmp_path / "run" / Path(original.arms[0].ft_port).name)
    assert private.arms[0].ur_host != original.arms[0].ur_host and private.arms[0].ur_host.startswith("127.0.0.")
    assert private.planner == original.planner and private.scene == original.scene


def test_the_latency_summary_and_the_table():
    summary = latency_summary({"wrench/a": [1_000_000] * 99 + [50_000_000]}, seconds=2.0)
    assert summary == {"wrench/a": {"p50_ms": 1.0, "p99_ms": 1.49, "hz": 50.0}}
    phase = {"plan_hz": 4.0, "mean_solve_ms": 200.0, "latency": summary}
    table = format_table({**dict.fromkeys(PHASES, phase), "recording_mb": 10.0, "recording_s": 20.0,
                          "recording_mb_per_s": 0.5, "recorder_cpu_percent": 12.0})
    assert "wrench/a" in table and "1.00/1.49 ms 50 Hz" in table and "12.0 % of one core" in table
    assert "10.0 MB over 20.0 s (0.5 MB/s)" in table
    assert cpu_time_s(os.getpid()) > 0


def test_the_recorded_span_is_the_files_first_to_last_message(tmp_path):
    path = tmp_path / "r.mcap"
    with open(path, "wb") as stream:
        writer = Writer(stream)
        writer.start()
        channel = writer.register_channel("t", "json", 0)
        for t_ns in (5_000_000_000, 6_000_000_000, 7_500_000_000):
            writer.add_message(channel, log_time=t_ns, data=b"{}", publish_time=t_ns)
        writer.finish()
    assert recorded_span_s(path) == 2.5
