"""``hydrosoft-stack status``: the report and table functions without sockets, and ``status --json`` against fake
services run by the real launcher (stopped by pid in teardown)."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time

import pytest
from fakes.stack_run import LauncherRun, remove_tree, short_run_root, write_config

from hydrosoft.services.commands import status
from hydrosoft.services.bus.messages import ServiceStatus

#: Longest a status call may take here, s (its window plus a Python start on a busy machine).
STATUS_TIMEOUT_S = 30.0


@pytest.fixture
def root():
    path = short_run_root()
    yield path
    remove_tree(path)


def run_status(config, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "hydrosoft.services.commands.status", str(config), *args],
                          capture_output=True, text=True, timeout=STATUS_TIMEOUT_S)


def test_report_carries_every_field_and_none_means_no_status():
    message = ServiceStatus(state="degraded", pid=42, uptime_s=12.3456, published_hz={"wrench/a": 99.987},
                            received_hz={"arm_state/a": 10.0}, errors={"schema": 2}, last_error="schema: bad",
                            restarts=3, instance="a" * 32)
    report = status.report_for(message, 0.0512)
    assert report == {"state": "degraded", "pid": 42, "uptime_s": 12.346, "published_hz": {"wrench/a": 99.99},
                      "received_hz": {"arm_state/a": 10.0}, "restarts": 3, "errors": {"schema": 2},
                      "last_error": "schema: bad", "heartbeat_age_s": 0.051, "instance": "a" * 32}
    assert status.report_for(None, 0.1) is None
    table = status.format_table({"ft_reader-a": report, "planner": None})
    row = next(line for line in table.splitlines() if line.startswith("ft_reader-a"))
    assert row.split()[1:4] == ["degraded", "42", "12.3s"] and row.split()[-2:] == ["3", "2"]
    assert "errors: schema 2; last: schema: bad" in table
    assert "wrench/a 100.0" in table
    assert any(line.split() == ["planner", "no", "status"] for line in table.splitlines())
    assert table.splitlines()[-1] == f"stack launch {'a' * 32}"


def test_a_services_compilation_is_reported_and_shown_and_absent_for_the_others():
    line = "compiling: stale artefact (torch 2.12.1 -> 2.13.0), building 0123456789ab"
    compiling = status.report_for(ServiceStatus(state="starting", pid=7, uptime_s=3.0, compilation=line), None)
    plain = status.report_for(ServiceStatus(state="ready", pid=8, uptime_s=3.0), 0.1)
    assert compiling["compilation"] == line and "compilation" not in plain
    table = status.format_table({"planner": compiling, "tag_tracker": plain}).splitlines()
    assert table[table.index(next(row for row in table if row.startswith("planner"))) + 2] == f"    compilation: {line}"
    assert sum("compilation:" in row for row in table) == 1


def test_services_of_several_launches_are_flagged():
    reports = {name: status.report_for(ServiceStatus(state="ready", pid=pid, uptime_s=1.0, instance=launch), 0.1)
               for name, pid, launch in (("planner", 1, "a" * 32), ("arm_commander-a", 2, "b" * 32))}
    assert status.format_table(reports).splitlines()[-1] == (
        f"services of SEVERAL stack launches: planner {'a' * 32}, arm_commander-a {'b' * 32}")


def test_nothing_running_lists_every_service_as_null_and_exits_0(root):
    config = write_config(root, ["a"])
    tic_s = time.monotonic()
    result = run_status(config, "--json", "--wait", "0.3")
    assert result.returncode == 0, result.stderr
    document = json.loads(result.stdout)
    assert document == {"services": dict.fromkeys(["sim_world", "arm_commander-a", "ft_reader-a", "bubble_camera-a",
                                                   "tag_tracker", "planner"])}
    assert time.monotonic() - tic_s < STATUS_TIMEOUT_S


def test_bad_config_or_window_exits_2(root):
    config = write_config(root, ["a"], "[planner]\nsamples = 0\n")
    result = run_status(config)
    assert result.returncode == 2 and "planner.samples" in result.stderr
    result = run_status(write_config(root, ["a"]), "--wait", "-1")
    assert result.returncode == 2 and "--wait" in result.stderr


def test_status_json_reports_each_running_service(root):
    config = write_config(root, ["a"])
    run = LauncherRun(config, "--only", "sim_world,tag_tracker", modes={"tag_tracker": "errors"})
    try:
        run.wait_for("[launcher] stack ready")
        pids = {name: int(run.wait_for(f"[launcher] {name} ready (pid")[1].rsplit(" ", 1)[1].rstrip(")"))
                for name in ("sim_world", "tag_tracker")}
        result = run_status(config, "--json", "--wait", "3")
        assert result.returncode == 0, result.stderr
        services = json.loads(result.stdout)["services"]
        assert set(services) == {"sim_world", "arm_commander-a", "ft_reader-a", "bubble_camera-a", "tag_tracker",
                                 "planner"}
        assert all(services[name] is None for name in ("arm_commander-a", "ft_reader-a", "bubble_camera-a", "planner"))
        for name, pid in pids.items():
            report = services[name]
            assert report["state"] == "ready" and report["pid"] == pid and report["restarts"] == 0, report
            assert report["uptime_s"] > 0 and 0 <= report["heartbeat_age_s"] < 1.0, report
            assert report["published_hz"][f"heartbeat/{name}-data"] > 5.0, report  # the fake publishes at 20 Hz
        assert services["tag_tracker"]["errors"] == {"fake_input": 1}
        assert "malformed" in services["tag_tracker"]["last_error"]
        assert services["sim_world"]["errors"] == {} and services["sim_world"]["last_error"] == ""

        table = run_status(config, "--wait", "3").stdout
        assert next(line for line in table.splitlines() if line.startswith("sim_world")).split()[1] == "ready"
    finally:
        if run.process.poll() is None:
            run.process.send_signal(signal.SIGINT)
            run.wait_exit()
        run.cleanup()


def test_a_services_note_is_reported_and_printed_only_when_it_has_one():
    note = "tared: bias [1.2 -0.8 2.5 0.04 -0.03 0.02] N, N m, taken 2026-11-27 07:20:00 UTC (42 s ago, by ft tare)"
    report = status.report_for(ServiceStatus(state="ready", pid=7, uptime_s=3.0, note=note), 0.05)
    assert report["note"] == note
    assert f"    note: {note}" in status.format_table({"ft_reader-a": report}).splitlines()
    plain = status.report_for(ServiceStatus(state="ready", pid=7, uptime_s=3.0), 0.05)
    assert "note" not in plain and "note:" not in status.format_table({"ft_reader-a": plain})
