"""The launcher: its plain functions without processes, and the real launcher over fake services
(``fakes/fake_service.py``): start order and log prefixes, restarts with backoff, the safe shutdown order and its
bound, no process left behind, a launch that fails on a silent service, config errors.

Every process is stopped by pid in teardown (``LauncherRun.cleanup``); waits are bounded.
"""

from __future__ import annotations

import asyncio
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from fakes.stack_run import (
    LINE_TIMEOUT_S,
    LauncherRun,
    alive,
    group_members,
    remove_tree,
    short_run_root,
    wait_until,
    write_config,
)

from hydrosoft.services.commands import keys

from hydrosoft.services.commands import launch as launcher
from hydrosoft.services.bus.config import ServiceConfig, load_config
from hydrosoft.services.recording.mcap_format import read_recording
from hydrosoft.services.commands.launch import (
    LaunchError,
    _OutputProtocol,
    check_ipc_paths,
    command_for,
    describe_exit,
    ipc_paths,
    lock_run_dir,
    ready_pid,
    remove_stale_sockets,
    restart_decision,
    select_services,
    awaited_arms,
    start_order,
    stop_phases,
)

#: The bound on a whole shutdown that the brief sets (the launcher's own is SHUTDOWN_BOUND_S).
SHUTDOWN_LIMIT_S = 10.0


@pytest.fixture
def root():
    path = short_run_root()
    yield path
    remove_tree(path)


@pytest.fixture
def runs():
    """Start launchers with ``runs(config, *args, modes=...)``; each is killed with its services at teardown."""
    started: list[LauncherRun] = []

    def start(config: Path, *args: str, modes: dict[str, str] | None = None) -> LauncherRun:
        run = LauncherRun(config, *args, modes=modes)
        started.append(run)
        return run

    yield start
    for run in started:
        run.cleanup()


def assert_nothing_left(run: LauncherRun) -> None:
    pids = run.pids()
    assert pids, "the launcher reported no pids"
    assert wait_until(lambda: not any(alive(pid) or group_members(pid) for pid in pids), 2.0), {
        pid: group_members(pid) for pid in pids if alive(pid) or group_members(pid)}


# --- plain functions ---------------------------------------------------------------------------------------------


def test_stop_phases_put_the_planner_first_then_all_arm_commanders_then_the_rest_in_reverse():
    names = ["sim_world", "arm_commander-left", "ft_reader-left", "arm_commander-right", "ft_reader-right",
             "tag_tracker", "planner"]
    assert stop_phases(names) == [["planner"], ["arm_commander-left", "arm_commander-right"], ["tag_tracker"],
                                  ["ft_reader-right"], ["ft_reader-left"], ["sim_world"]]
    assert stop_phases(["sim_world", "ft_reader-a"]) == [["ft_reader-a"], ["sim_world"]]


def test_the_planner_starts_first_after_the_recorder_and_the_rest_keep_their_order():
    names = ["sim_world", "arm_commander-left", "ft_reader-left", "bubble_camera-left", "arm_commander-right",
             "ft_reader-right", "bubble_camera-right", "tag_tracker", "planner"]
    assert start_order(names) == ["planner"] + names[:-1]
    assert start_order(["recorder", "sim_world", "tag_tracker", "planner"]) == ["recorder", "planner", "sim_world",
                                                                                 "tag_tracker"]
    assert start_order(["tag_tracker", "planner"]) == ["planner", "tag_tracker"]  # a host without the arms
    assert start_order(["sim_world", "ft_reader-a"]) == ["sim_world", "ft_reader-a"]


def test_the_planner_waits_for_the_arms_of_the_launchs_arm_commanders():
    assert awaited_arms(["sim_world", "arm_commander-left", "ft_reader-left", "arm_commander-right", "planner"]) == [
        "left", "right"]
    assert awaited_arms(["tag_tracker", "planner"]) == []  # a host without the arms: their commanders run elsewhere


@pytest.mark.parametrize(("policy", "code", "restarts", "restart", "delay_s"), [
    ("never", 1, 0, False, 0.0),
    ("on-failure", 0, 0, False, 0.0),
    ("on-failure", 1, 0, True, 0.5),
    ("on-failure", -9, 0, True, 0.5),  # killed by a signal is a failure
    ("on-failure", 1, 2, True, 2.0),  # doubling: 0.5, 1, 2
    ("on-failure", 1, 3, False, 0.0),  # max_restarts reached
    ("always", 0, 1, True, 1.0),
])
def test_restart_decision_follows_the_policy_with_doubling_backoff(policy, code, restarts, restart, delay_s):
    decision = restart_decision(ServiceConfig(restart=policy, max_restarts=3, backoff_s=0.5), code, restarts)
    assert (decision.restart, decision.delay_s) == (restart, delay_s), decision.reason


def test_backoff_is_capped():
    decision = restart_decision(ServiceConfig(max_restarts=50, backoff_s=1.0), 1, 20)
    assert decision.restart and decision.delay_s == launcher.MAX_BACKOFF_S


def test_small_helpers():
    assert ready_pid("READY planner 123", "planner") == 123
    assert ready_pid("READY planner 123", "planner_x") is None
    assert ready_pid("READY planner", "planner") is None
    assert ready_pid("2026 planner INFO: READY planner 1", "planner") is None
    assert describe_exit(0) == "exit 0" and describe_exit(-9) == "killed by SIGKILL"
    assert describe_exit(None) == "running"


def test_command_runs_the_service_module_or_the_override(monkeypatch):
    monkeypatch.delenv(launcher.SERVICE_MODULE_ENV, raising=False)
    assert command_for("ft_reader-left", "c.toml") == [sys.executable, "-m", "hydrosoft.services.ft_reader", "c.toml",
                                                        "--name", "ft_reader-left"]
    monkeypatch.setenv(launcher.SERVICE_MODULE_ENV, "fake_service")
    assert command_for("planner", "c.toml")[1:3] == ["-m", "fake_service"]


def test_only_selects_services_in_start_order_and_names_unknown_ones(root):
    config = load_config(write_config(root, ["a"]))
    assert select_services(config, "planner, sim_world") == ["sim_world", "planner"]
    assert select_services(config, None) == config.service_names()
    with pytest.raises(LaunchError, match="no such service arm_commander-b"):
        select_services(config, "planner,arm_commander-b")


def test_ipc_paths_too_long_for_a_unix_socket_are_refused(root):
    config = load_config(write_config(root, ["a"]))
    paths = ipc_paths(config, ["planner"])
    assert {p.name for p in paths} == {"planner.data", "planner.status", "planner.cmd"}
    check_ipc_paths(paths)
    with pytest.raises(LaunchError, match="shorter run_dir"):
        check_ipc_paths([Path("/tmp/" + "x" * 120)])


def test_only_stale_socket_files_are_removed(root):
    stale, other = root / "planner.status", root / "planner.data"
    listener = socket.socket(socket.AF_UNIX)
    listener.bind(str(stale))
    listener.close()  # the file stays behind, as after a killed service
    other.write_text("not a socket")
    assert remove_stale_sockets([stale, other, root / "missing"]) == [stale]
    assert not stale.exists() and other.exists()


def test_a_second_launcher_cannot_take_the_same_run_dir(root):
    first = lock_run_dir(root / "run")
    try:
        with pytest.raises(LaunchError, match="another launcher"):
            lock_run_dir(root / "run")
    finally:
        first.close()
    lock_run_dir(root / "run").close()  # free again once the first one let go


def test_output_is_split_into_lines_and_overlong_lines_are_cut(monkeypatch):
    monkeypatch.setattr(launcher, "MAX_LINE_BYTES", 8)
    lines: list[str] = []

    async def feed() -> None:
        protocol = _OutputProtocol(lines.append)
        for chunk in (b"one\ntw", b"o\r\n", b"0123456789ab\n", b"tail"):
            protocol.pipe_data_received(1, chunk)
        protocol.pipe_connection_lost(1, None)

    asyncio.run(feed())
    assert lines == ["one", "two", "01234567", "89ab", "tail"]


def test_bad_config_exits_2_naming_the_key(root, capsys):
    path = write_config(root, ["a"], "[limits]\nmax_speed_m_s = -1.0\n")
    assert launcher.launch(path) == 2
    assert "limits.max_speed_m_s" in capsys.readouterr().err
    path.write_text(path.read_text().replace("max_speed_m_s = -1.0", "max_sped_m_s = 0.1"))
    result = subprocess.run([sys.executable, "-m", "hydrosoft.services.commands.launch", str(path)], capture_output=True,
                            text=True, timeout=30)
    assert result.returncode == 2 and "max_sped_m_s" in result.stderr and "limits" in result.stderr, result.stderr
    assert not (root / "run").exists()  # nothing was started or created


def test_unknown_only_name_exits_2(root, capsys):
    assert launcher.launch(write_config(root, ["a"]), only="planner,mapper") == 2
    assert "mapper" in capsys.readouterr().err


def test_a_secret_key_others_may_read_or_an_unknown_host_exits_2_before_anything_starts(root, capsys):
    public, secret = keys.generate_key_pair(root / "keys", "robot")
    secret.chmod(0o640)
    path = write_config(root, ["a"], f'[curve]\nsecret_key_file = "{secret}"\n'
                                     f'authorized_keys_dir = "{public.parent}"\n')
    assert launcher.launch(path) == 2
    assert f"{secret} has mode 0640" in capsys.readouterr().err
    secret.chmod(0o600)
    assert launcher.launch(path, host="robot") == 2  # the config names no hosts
    assert "--host: no host 'robot'" in capsys.readouterr().err
    assert not (root / "run").exists()


# --- the real launcher over fake services ------------------------------------------------------------------------


def test_services_start_in_order_with_prefixed_logs_and_stop_in_the_safe_order(root, runs):
    """The services start one after another, each once the one before is ready, but the planner: it starts first,
    told to wait for the launch's arm commanders (``$HYDROSOFT_AWAIT_ARMS``), and the others start while it gets
    ready (slowly, as it loads its solver); the stack is ready once it is. Only the planner's first run waits."""
    only = ["sim_world", "arm_commander-left", "ft_reader-left", "arm_commander-right", "tag_tracker", "planner"]
    run = runs(write_config(root, ["left", "right"]), "--only", ",".join(only),
               modes={"tag_tracker": "spawns_child", "ft_reader-left": "hang_on_stop", "planner": "slow_ready"})
    run.wait_for("[launcher] stack ready")
    others = only[:-1]
    assert [run.index(f"[launcher] {name} ready (pid") for name in others] == sorted(
        run.index(f"[launcher] {name} ready (pid") for name in others)
    planner_starts = run.index("[launcher] planner started (pid")  # its own first line may come later
    assert planner_starts < run.index("[launcher] sim_world ready (pid")
    assert max(run.index(f"[launcher] {name} ready (pid") for name in only) < run.index("[launcher] stack ready")
    assert run.find(lambda line: line.startswith("[planner] ") and "awaits arms 'left,right'" in line)
    assert run.find(lambda line: line.startswith("[sim_world] ") and "awaits arms None" in line)
    for name in only:  # every line of a service arrives with its prefix (here: the runtime's log line)
        assert run.find(lambda line, name=name: line.startswith(f"[{name}] ") and f"fake service {name} " in line)
    assert (root / "run" / "launcher.lock").read_text().strip() == str(run.process.pid)

    tic_s = time.monotonic()
    run.process.send_signal(signal.SIGINT)
    assert run.wait_exit() == 0, run.text()[-4000:]
    assert time.monotonic() - tic_s < SHUTDOWN_LIMIT_S, run.text()[-4000:]

    planner = run.index("[launcher] stopping planner")
    arms = [run.index(f"[launcher] stopping arm_commander-{arm}") for arm in ("left", "right")]
    rest = [run.index(f"[launcher] stopping {name}") for name in ("tag_tracker", "ft_reader-left", "sim_world")]
    assert planner < min(arms) and max(arms) < rest[0] and rest == sorted(rest), run.text()[-4000:]
    assert run.index("[launcher] stopped planner") < min(arms)
    assert max(run.index(f"stopped arm_commander-{arm} (arm stopped)") for arm in ("left", "right")) < rest[0]
    assert "stopped ft_reader-left: SIGKILL after" in run.text()  # hung on its shutdown hook
    child = run.find(lambda line: ": child " in line)
    assert child, "the spawning fake logged no child"
    assert_nothing_left(run)  # services, their groups and the child left behind by tag_tracker


def test_a_crashing_service_is_restarted_with_doubling_backoff_then_given_up(root, runs):
    extra = "[services.ft_reader-a]\nrestart = \"on-failure\"\nmax_restarts = 2\nbackoff_s = 0.3\n"
    run = runs(write_config(root, ["a"], extra), "--only", "sim_world,ft_reader-a", "--log-dir", str(root / "logs"),
               modes={"ft_reader-a": "crash"})
    run.wait_for("[launcher] gave up on ft_reader-a")
    ended = [t for t, _ in run.find(lambda line: line.startswith("[launcher] ft_reader-a ended"))]
    runs_logged = run.find(lambda line: "fake service ft_reader-a in mode crash" in line)
    started = [t for t, _ in runs_logged]
    assert len(ended) == 2 and len(started) == 3, run.text()[-4000:]
    assert [line.rsplit("(", 1)[1] for _, line in runs_logged] == ["restart 0)", "restart 1)", "restart 2)"]
    for restart, (end_s, next_start_s) in enumerate(zip(ended, started[1:])):
        assert next_start_s - end_s >= 0.3 * 2**restart - 0.02, (restart, next_start_s - end_s)
    assert "restart 1 of 2 in 0.30 s" in run.text() and "restart 2 of 2 in 0.60 s" in run.text()
    assert "gave up after 2 restarts" in run.text()
    assert (root / "logs" / "ft_reader-a.log").read_text().count("READY ft_reader-a ") == 3

    sim_world = int(run.wait_for("[launcher] sim_world ready (pid")[1].rsplit(" ", 1)[1].rstrip(")"))
    assert run.process.poll() is None and alive(sim_world)  # the rest stay up
    run.process.send_signal(signal.SIGINT)
    assert run.wait_exit() == 0
    assert "ft_reader-a was not running" in run.text()
    assert_nothing_left(run)


def test_a_service_that_never_gets_ready_fails_the_launch_naming_it(root, runs):
    """An arm commander that never gets ready fails the launch; no sensor after it starts, and the planner, started
    first (and waiting for that commander's state before it takes a goal), is stopped with the rest."""
    extra = "[services.arm_commander-a]\nready_timeout_s = 1.0\n"
    run = runs(write_config(root, ["a"], extra), "--only", "sim_world,arm_commander-a,tag_tracker,planner",
               modes={"arm_commander-a": "never_ready", "planner": "slow_ready"})
    assert run.wait_exit(LINE_TIMEOUT_S) == 1, run.text()[-4000:]
    assert "launch failed: arm_commander-a did not report READY within 1 s" in run.text()
    assert all(f"stopping {name} (pid" in run.text() for name in ("planner", "arm_commander-a", "sim_world"))
    assert not run.find(lambda line: line.startswith("[tag_tracker]"))  # never started
    assert "stack ready" not in run.text()
    assert_nothing_left(run)


def test_a_sensor_that_never_gets_ready_while_the_planner_starts_fails_the_launch_and_stops_the_planner(root, runs):
    extra = "[services.tag_tracker]\nready_timeout_s = 1.0\n"
    run = runs(write_config(root, ["a"], extra), "--only", "sim_world,tag_tracker,planner",
               modes={"tag_tracker": "never_ready", "planner": "slow_ready"})
    assert run.wait_exit(LINE_TIMEOUT_S) == 1, run.text()[-4000:]
    assert "launch failed: tag_tracker did not report READY within 1 s" in run.text()
    assert all(f"stopping {name} (pid" in run.text() for name in ("planner", "tag_tracker", "sim_world"))
    assert "stack ready" not in run.text()
    assert_nothing_left(run)


def test_the_shutdown_stays_within_its_bound_when_every_service_hangs(root, runs):
    only = ["sim_world", "arm_commander-a", "planner"]
    run = runs(write_config(root, ["a"]), "--only", ",".join(only), modes=dict.fromkeys(only, "hang_on_stop"))
    run.wait_for("[launcher] stack ready")
    tic_s = time.monotonic()
    run.process.send_signal(signal.SIGINT)
    assert run.wait_exit() == 0
    assert time.monotonic() - tic_s < SHUTDOWN_LIMIT_S, run.text()[-4000:]
    assert f"stopped planner: SIGKILL after {launcher.STOP_WAIT_S:.1f} s" in run.text()
    assert (f"stopped arm_commander-a (arm stop NOT confirmed): SIGKILL after {launcher.ARM_STOP_WAIT_S:.1f} s"
            in run.text())
    assert run.index("stopped arm_commander-a") < run.index("stopped sim_world: SIGKILL after")
    assert_nothing_left(run)


def test_a_killed_launcher_takes_its_services_with_it(root, runs):
    run = runs(write_config(root, ["a"]), "--only", "sim_world,planner")
    run.wait_for("[launcher] stack ready")
    pids = run.pids()
    run.process.kill()
    run.wait_exit()
    assert wait_until(lambda: not any(alive(pid) for pid in pids), 5.0), [pid for pid in pids if alive(pid)]
    # each service wrote its own log, shutdown included, though its output pipe to the launcher was gone
    (instance,) = re.findall(r"\[launcher\] launch instance ([0-9a-f]{32})", run.text())
    for name in ("sim_world", "planner"):
        text = (root / "run" / "logs" / f"{name}.log").read_text()
        assert f"stack launch {instance}" in text, text  # the launch's id, passed to every service
        assert "SIGTERM received, stopping" in text and "stopped (exit 0)" in text, text



# --- recording (--record, --view) --------------------------------------------------------------------------------

#: The recorder compiles the task scene (torch) before it reports READY.
RECORDER_READY_S = 90.0


def test_the_recorder_command_is_the_real_recorder_with_the_options(monkeypatch):
    monkeypatch.setenv(launcher.SERVICE_MODULE_ENV, "fake_service")
    recorder = launcher.RecorderLaunch(Path("/r/run.mcap"), view=True, view_port=9000)
    command = recorder.with_recorder(command_for)
    assert command("recorder", "c.toml")[1:] == ["-m", "hydrosoft.services.recorder", "c.toml", "--name", "recorder",
                                                 "--record", "/r/run.mcap", "--view", "--view-port", "9000"]
    assert command("planner", "c.toml")[1:3] == ["-m", "fake_service"]
    assert not launcher.RecorderLaunch().wanted
    assert launcher.RecorderLaunch(view=True).command("c.toml")[-1] == "--view"


def test_record_starts_the_recorder_first_and_stops_it_last_so_the_file_holds_every_shutdown(root, runs):
    only = ["sim_world", "arm_commander-a", "planner"]
    path = root / "run.mcap"
    run = runs(write_config(root, ["a"]), "--only", ",".join(only), "--record", str(path))
    run.wait_for("[launcher] stack ready", timeout_s=RECORDER_READY_S)
    time.sleep(1.0)
    run.process.send_signal(signal.SIGINT)
    assert run.wait_exit() == 0, run.text()[-4000:]
    assert run.index("[launcher] recorder ready") < run.index("[launcher] sim_world ready")
    assert max(run.index(f"[launcher] stopped {name}") for name in only) < run.index("[launcher] stopping recorder")
    messages, reader = read_recording(path)
    assert not reader.truncated
    for name in only:
        states = [m.message.state for m in messages if m.topic == f"status/{name}"]
        assert states[-1] == "stopping", (name, states)
        assert sum(m.topic == f"heartbeat/{name}-data" for m in messages) >= 5  # 20 Hz for a second and more
    assert_nothing_left(run)
