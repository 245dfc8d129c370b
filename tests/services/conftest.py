"""Fixtures shared by the service tests.

``recorded_run`` (session): one short run of the fake publisher (``fakes/bus_publisher.py``) and the real tag
tracker, recorded by two recorders at once: one SIGKILLed mid-run (``killed``, camera images as JPEG, the default),
one stopped cleanly at the end (``clean``, camera images raw, lossless, so a replay re-runs the tracker exactly).
The recorder, replay and plot tests read these files. Every process is stopped by its pid.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import pytest
from recording_processes import publisher, recorder, remove_root, service, short_root, write_config

from hydrosoft.services.bus.config import StackConfig, load_config

RUN_BEFORE_KILL_S = 3.0  # the publisher's run recorded by both recorders, s
RUN_AFTER_KILL_S = 1.5  # then by the clean recorder alone, s


@dataclass(frozen=True)
class RecordedRun:
    """root: the run's folder; config_path, config: its stack config; clean, killed: the two recordings; kill_ns:
    ``time.monotonic_ns()`` just before the SIGKILL; clean_exit: the clean recorder's exit code; logs: each
    process's log text."""

    root: Path
    config_path: Path
    config: StackConfig
    clean: Path
    killed: Path
    kill_ns: int
    clean_exit: int
    logs: dict[str, str]


@pytest.fixture(scope="session")
def recorded_run():
    root = short_root()
    config_path = write_config(root)
    clean, killed = root / "clean.mcap", root / "killed.mcap"
    killed_recorder = recorder(config_path, root, "--record", killed, name="recorder")
    clean_recorder = recorder(config_path, root, "--record", clean, "--camera-images", "raw", name="recorder-clean")
    tracker = service("tag_tracker", config_path, root)
    processes = [killed_recorder, clean_recorder, tracker]
    try:
        for process in processes:
            process.wait_ready()
        source = publisher(config_path, root)
        processes.append(source)
        source.wait_ready()
        time.sleep(RUN_BEFORE_KILL_S)
        kill_ns = time.monotonic_ns()
        killed_recorder.kill()
        time.sleep(RUN_AFTER_KILL_S)
        source.stop()
        tracker.stop()
        clean_exit = clean_recorder.stop()
    finally:
        for process in processes:
            process.stop()
    logs = {process.name: process.log() for process in processes}
    yield RecordedRun(root, config_path, load_config(config_path), clean, killed, kill_ns, clean_exit, logs)
    remove_root(root)
