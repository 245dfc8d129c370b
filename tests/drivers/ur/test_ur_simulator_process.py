"""The simulator as a server: its hooks in-process, ``simulate ur`` options, exit on SIGTERM, bad input survived."""

from __future__ import annotations

import argparse
import asyncio
import json
import signal
import socket

import numpy as np
import pytest

from hydrosoft.drivers.ur import rtde_protocol as rtde
from hydrosoft.drivers.ur import simulator
from hydrosoft.drivers.ur.config import DASHBOARD_PORT, RTDE_PORT, SIM_CONTROL_PORT
from hydrosoft.drivers.ur.simulator import SimulatedURController


def test_hooks_read_and_impose_the_tcp_in_process(free_host):
    async def scenario():
        ticks = []
        async with SimulatedURController(host=free_host, tcp_pose=[0.1, 0.2, 0.3, 1.0, 0.0, 0.0, 0.0]) as sim:
            sim.add_tick_listener(lambda now_ns, pose, twist: ticks.append((now_ns, pose[0], twist[0])))
            await asyncio.sleep(0.05)
            sim.impose_tcp_pose(np.array([0.5, 0.2, 0.3, 1.0, 0.0, 0.0, 0.0]))
            await asyncio.sleep(0.01)
            reader, writer = await asyncio.open_connection(free_host, DASHBOARD_PORT)
            banner = await reader.readline()
            writer.close()
            return ticks, sim.tcp_pose(), sim.tcp_twist(), banner

    ticks, pose, twist, banner = asyncio.run(asyncio.wait_for(scenario(), 5.0))
    assert len(ticks) > 10  # 500 Hz ticks
    assert all(b[0] > a[0] for a, b in zip(ticks, ticks[1:]))
    assert ticks[0][1] == 0.1 and ticks[-1][1] == 0.5
    np.testing.assert_array_equal(pose, [0.5, 0.2, 0.3, 1.0, 0.0, 0.0, 0.0])
    np.testing.assert_array_equal(twist, np.zeros(6))
    assert banner == b"Connected: Universal Robots Dashboard Server\n"


def parse(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    simulator.add_arguments(parser)
    return parser.parse_args(argv)


def test_pose_option_is_a_ur_pose():
    args = parse("--host", "127.0.0.9", "--pose", "0.1,0.2,0.3,0,3.141592653589793,0")
    np.testing.assert_allclose(args.pose, [0.1, 0.2, 0.3, 0, 0, 1, 0], atol=1e-15)
    with pytest.raises(SystemExit):
        parse("--pose", "0.1,0.2")


def test_non_loopback_host_is_refused(capsys):
    assert simulator.run(parse("--host", "10.0.0.5")) == 2
    assert "127.0.0.0/8" in capsys.readouterr().err


def test_simulator_exits_cleanly_on_sigterm(start_simulator, free_host):
    process = start_simulator(free_host)
    process.proc.send_signal(signal.SIGTERM)
    assert process.proc.wait(5.0) == 0


def test_bad_input_is_refused_counted_and_survived(start_simulator, free_host):
    process = start_simulator(free_host)
    with socket.create_connection((free_host, RTDE_PORT), timeout=2.0) as conn:
        conn.sendall(rtde.encode_packet(rtde.CMD_DATA_PACKAGE, b"\x07\x00\x00\x00\x01"))  # no such recipe
        conn.sendall(rtde.encode_packet(rtde.CMD_SETUP_INPUTS, b"input_int_register_0,bogus"))
        reply = _read_packet(conn)
        assert reply.command == rtde.CMD_SETUP_INPUTS
        assert reply.payload == b"\x00INT32,NOT_FOUND"
        conn.sendall(bytes.fromhex("000155"))  # a size below the header: the controller hangs up
        assert conn.recv(64) == b""
    with socket.create_connection((free_host, SIM_CONTROL_PORT), timeout=2.0) as conn:
        lines = conn.makefile("rw")
        for bad in ("not json", '{"op": "stall", "duration_s": -1}', '{"op": "warp"}', "[1, 2]"):
            lines.write(bad + "\n")
            lines.flush()
            reply = json.loads(lines.readline())
            assert reply["ok"] is False and reply["error"]
    counters = process.state()["counters"]
    assert counters["rtde_input_unknown_recipe"] == 1
    assert counters["rtde_input_refused"] == 1
    assert counters["rtde_bad_framing"] == 1
    assert counters["control_bad_request"] == 4
    assert process.state()["faults"] == {}


def _read_packet(conn: socket.socket) -> rtde.Packet:
    reader = rtde.PacketReader()
    while not (packets := reader.packets()):
        reader.feed(conn.recv(4096))
    return packets[0]
