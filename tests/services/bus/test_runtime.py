"""The service runtime: status, errors and rates in-process, and a real service subprocess that prints READY,
publishes its status and heartbeat, idles without spinning and stops cleanly on SIGTERM and SIGINT.

Run as a script, this file is that tiny service: ``python test_runtime.py MODE STATUS_ENDPOINT``.
"""

import asyncio
import gc
import os
import signal
import sys
import tempfile
import time
from pathlib import Path

import msgspec
import numpy as np
import pytest

from hydrosoft.services.bus import messages as m
from hydrosoft.services.bus.sockets import Bus, LatestSubscriber
from hydrosoft.services.bus.runtime import INSTANCE_ENV, RuntimeConfig, Service, run_service

TEST_TIMEOUT_S = 30.0
#: Longest wait for the subprocess to print READY (imports on two busy cores), s.
START_TIMEOUT_S = 20.0
#: The tiny service's shutdown bound, and the longest a stop may take in all, s.
SHUTDOWN_TIMEOUT_S = 1.0
STOP_BOUND_S = 5.0
#: CPU seconds an idle service may use in IDLE_WINDOW_S (status at 10 Hz, heartbeat at 20 Hz).
IDLE_WINDOW_S = 1.0
IDLE_CPU_LIMIT_S = 0.1


def run(coroutine, timeout_s: float = TEST_TIMEOUT_S):
    return asyncio.run(asyncio.wait_for(coroutine, timeout_s))


def config(endpoint: str) -> RuntimeConfig:
    return RuntimeConfig(status_endpoint=endpoint, status_period_s=0.1, heartbeat_period_s=0.05,
                         shutdown_timeout_s=SHUTDOWN_TIMEOUT_S)


@pytest.fixture(autouse=True)
def unfrozen_collector():
    """A service made here freezes the test process's objects when it is ready: unfreeze them after each test."""
    yield
    gc.unfreeze()


@pytest.fixture
def ipc_dir():
    with tempfile.TemporaryDirectory(prefix="hs-rt-") as path:
        yield Path(path)


def test_config_rejects_bad_values():
    with pytest.raises(ValueError, match="status_period_s must be > 0"):
        RuntimeConfig(status_endpoint="ipc:///tmp/x", status_period_s=0.0)
    with pytest.raises(ValueError, match="not a logging level"):
        RuntimeConfig(status_endpoint="ipc:///tmp/x", log_level="LOUD")
    with pytest.raises(msgspec.ValidationError, match="heartbeat_period_s must be > 0"):
        msgspec.toml.decode(b'status_endpoint = "ipc:///tmp/x"\nheartbeat_period_s = -1', type=RuntimeConfig)


def test_a_ready_service_froze_its_start_up_objects_and_one_degraded_for_a_cause_says_so(ipc_dir, capsys):
    """``ready`` settles the garbage collector (start-up objects collected once and frozen: no later collection walks
    them) before it prints READY; a service degraded for a cause before it is ready reports ``degraded``."""
    async def scenario():
        with Bus() as bus:
            service = Service("tester", config(f"ipc://{ipc_dir}/status"), bus)
            gc.unfreeze()
            service.degrade("device_unavailable")
            await service.ready()
            return service.state, gc.get_freeze_count()

    state, frozen = run(scenario())
    assert state == "degraded" and frozen > 0
    assert f"READY tester {os.getpid()}" in capsys.readouterr().out


def test_status_reports_state_errors_and_rates(ipc_dir):
    async def scenario():
        with Bus() as bus:
            service = Service("tester", config(f"ipc://{ipc_dir}/status"), bus)
            assert service.status().state == "starting"
            data = service.publisher(f"ipc://{ipc_dir}/data")
            listener = LatestSubscriber(bus, [f"ipc://{ipc_dir}/status", f"ipc://{ipc_dir}/data"])
            reader = service.subscriber(f"ipc://{ipc_dir}/data", ["wrench"], background=True)
            service.count_error("driver_timeout", "no frame for 0.5 s")
            service.count_error("driver_timeout", "no frame for 0.6 s")
            deadline_s = time.monotonic() + 5.0
            while not reader.received and time.monotonic() < deadline_s:  # slow joiner
                await data.send(m.Wrench(sensor="ft", wrench=np.zeros(6), tared=True), "wrench/ft")
                await asyncio.sleep(0.01)
            await asyncio.sleep(0.05)
            service.measure_rates()
            service.compilation = "compiled (artefact 0123456789ab)"
            await service.set_state("degraded")
            status = None
            deadline_s = time.monotonic() + 5.0
            while status is None or status.state != "degraded":  # the listener may join after the first status
                assert time.monotonic() < deadline_s, "no degraded status within 5 s"
                await service.publish_status()
                if "status/tester" in await listener.wait(0.1):
                    status = listener.latest("status/tester", 5.0, m.ServiceStatus).value
            assert status.source == "tester" and status.pid == os.getpid()
            assert status.errors == {"driver_timeout": 2}
            assert status.last_error == "driver_timeout: no frame for 0.6 s"
            assert status.published_hz["wrench/ft"] > 0 and status.received_hz["wrench/ft"] > 0
            assert status.uptime_s > 0
            assert status.compilation == "compiled (artefact 0123456789ab)"

    run(scenario())


def test_a_service_takes_its_launch_id_from_the_launcher_or_makes_its_own(ipc_dir, monkeypatch):
    async def instance(name: str) -> str:
        with Bus() as bus:
            return Service(name, config(f"ipc://{ipc_dir}/{name}"), bus).status().instance

    monkeypatch.setenv(INSTANCE_ENV, "f" * 32)
    assert run(instance("launched")) == "f" * 32
    monkeypatch.delenv(INSTANCE_ENV)
    alone, other = run(instance("alone")), run(instance("other"))
    assert len(alone) == 32 and alone != other


def test_a_supervised_task_that_ends_leaves_the_service_degraded_and_counted(ipc_dir):
    async def scenario():
        with Bus() as bus:
            service = Service("tester", config(f"ipc://{ipc_dir}/status"), bus)
            await service.ready()

            async def server():
                raise RuntimeError("socket gone")

            service.supervise(asyncio.create_task(server(), name="tester.serve"))
            await asyncio.sleep(0.05)
            assert service.state == "degraded" and service.errors.counts == {"task_ended": 1}
            await service.set_state("ready")  # a degraded service does not claim to be ready again
            assert service.state == "degraded" and service.effective_state("ready") == "degraded"
            assert service.effective_state("stopping") == "stopping"
            cancelled = service.supervise(asyncio.create_task(asyncio.sleep(10), name="tester.other"))
            cancelled.cancel()
            await asyncio.sleep(0.05)
            assert service.errors.counts == {"task_ended": 1}  # a cancelled task is a stop, not a failure

    run(scenario())


# --- the tiny service, run as a subprocess --------------------------------------------------------------------


async def tiny_main(service: Service, mode: str) -> None:
    async def hook() -> None:
        if mode == "hang":
            await asyncio.sleep(60)
        print("HOOK RAN", flush=True)

    service.on_shutdown(hook)
    await service.ready()
    if mode == "fail":
        raise RuntimeError("the tiny service gave up")
    await asyncio.Event().wait()


@pytest.fixture
def spawn():
    """Start the tiny service; every process started is killed by pid at teardown if it still runs."""
    processes = []

    async def start(mode: str, endpoint: str) -> asyncio.subprocess.Process:
        process = await asyncio.create_subprocess_exec(
            sys.executable, __file__, mode, endpoint, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
        processes.append(process.pid)
        line = await asyncio.wait_for(process.stdout.readline(), START_TIMEOUT_S)
        assert line.decode().split() == ["READY", "tiny", str(process.pid)]
        return process

    yield start
    for pid in processes:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


async def stop(process: asyncio.subprocess.Process, sig: signal.Signals) -> tuple[int, str, str, float]:
    """Send ``sig`` by pid; return the exit code, stdout, stderr and the seconds it took."""
    start_s = time.monotonic()
    os.kill(process.pid, sig)
    out, err = await asyncio.wait_for(process.communicate(), STOP_BOUND_S)
    return process.returncode, out.decode(), err.decode(), time.monotonic() - start_s


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime + stime


async def until(condition, timeout_s: float = 5.0, what: str = "the condition") -> None:
    """Check ``condition()`` every 20 ms until it holds; fail after ``timeout_s``."""
    deadline_s = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline_s, f"{what} did not happen within {timeout_s} s"
        await asyncio.sleep(0.02)


def status_of(listener: LatestSubscriber) -> m.ServiceStatus | None:
    return listener.latest("status/tiny", 5.0, m.ServiceStatus).value if listener.received["status/tiny"] else None


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_service_is_ready_reports_idles_and_stops_cleanly(spawn, ipc_dir, sig):
    endpoint = f"ipc://{ipc_dir}/status"

    async def scenario():
        with Bus() as bus:
            listener = LatestSubscriber(bus, endpoint)
            reading = asyncio.create_task(listener.run())  # reads all along, as a launcher would
            process = await spawn("hold", endpoint)
            await until(lambda: listener.received["heartbeat/tiny"] and status_of(listener), what="status")
            status = status_of(listener)
            assert status.state == "ready" and status.pid == process.pid and status.source == "tiny"
            assert listener.latest("heartbeat/tiny", 1.0, m.Heartbeat).value.period_s == 0.05
            cpu_before_s = cpu_seconds(process.pid)
            await asyncio.sleep(IDLE_WINDOW_S)
            assert cpu_seconds(process.pid) - cpu_before_s < IDLE_CPU_LIMIT_S  # waits on timers, never spins
            code, out, err, took_s = await stop(process, sig)
            assert code == 0, err
            assert "HOOK RAN" in out and f"{sig.name} received, stopping" in err
            assert took_s < STOP_BOUND_S
            await until(lambda: status_of(listener).state == "stopping", what="the stopping status")
            assert " tiny INFO " in err  # every log line names the service
            reading.cancel()

    run(scenario())


def test_a_hanging_shutdown_hook_is_cut_off_at_its_bound(spawn, ipc_dir):
    async def scenario():
        process = await spawn("hang", f"ipc://{ipc_dir}/status")
        code, out, err, took_s = await stop(process, signal.SIGTERM)
        assert code == 1 and "HOOK RAN" not in out
        assert "did not finish within 1.0 s" in err
        assert SHUTDOWN_TIMEOUT_S <= took_s < STOP_BOUND_S

    run(scenario())


def test_a_failing_main_exits_with_an_error_after_the_hooks(spawn, ipc_dir):
    async def scenario():
        process = await spawn("fail", f"ipc://{ipc_dir}/status")
        out, err = await asyncio.wait_for(process.communicate(), STOP_BOUND_S)
        assert process.returncode == 1
        assert "HOOK RAN" in out.decode() and "the tiny service gave up" in err.decode()

    run(scenario())


if __name__ == "__main__":
    tiny_mode, status_endpoint = sys.argv[1], sys.argv[2]
    sys.exit(run_service("tiny", config(status_endpoint), lambda service: tiny_main(service, tiny_mode)))
