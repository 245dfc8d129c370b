"""One RTDE connection of the simulated controller, driven packet by packet without sockets."""

from __future__ import annotations

import struct
from collections import Counter

import numpy as np

from hydrosoft.drivers.ur import rtde_protocol as rtde
from hydrosoft.drivers.ur.controller import URControllerModel
from hydrosoft.drivers.ur.rtde_session import MAX_BACKLOG_BYTES, RtdeSession

START = np.array([0.3, -0.2, 0.4, 0.0, 0.0, 1.0, 0.0])
MS = 1_000_000


class Client:
    """A session plus what it sent back, decoded into packets."""

    def __init__(self, session_id: int, model: URControllerModel, owners: dict[str, int], counters: Counter):
        self.reader = rtde.PacketReader()
        self.session = RtdeSession(session_id, model, owners, counters, 500.0, self.reader.feed)

    def ask(self, command: int, payload: bytes = b"", now_ns: int = 0) -> list[rtde.Packet]:
        self.session.handle(rtde.Packet(command, payload), now_ns)
        return self.reader.packets()


def rig():
    model = URControllerModel(START, now_ns=0)
    owners: dict[str, int] = {}
    counters: Counter = Counter()
    return model, owners, counters, Client(1, model, owners, counters)


def test_handshake_and_stream_at_the_requested_rate():
    model, _, counters, client = rig()
    assert client.ask(rtde.CMD_REQUEST_PROTOCOL_VERSION, struct.pack(">H", 2))[0].payload == b"\x01"
    (version,) = client.ask(rtde.CMD_GET_URCONTROL_VERSION)
    assert struct.unpack(">IIII", version.payload) == (5, 15, 0, 0)
    (setup,) = client.ask(rtde.CMD_SETUP_OUTPUTS, struct.pack(">d", 250.0) + b"timestamp,actual_TCP_pose,")
    assert setup.payload == b"\x01DOUBLE,VECTOR6D"
    assert client.ask(rtde.CMD_START)[0].payload == b"\x01"
    sent = 0
    for tick in range(0, 100 * MS, 2 * MS):  # 500 Hz ticks for 0.1 s
        if client.session.due(tick):
            client.session.stream(tick, model.output_values(), backlog_bytes=0)
        sent += len(client.reader.packets())
    assert sent == 25  # 250 Hz
    client.session.stream(200 * MS, model.output_values(), backlog_bytes=MAX_BACKLOG_BYTES + 1)
    assert client.reader.packets() == []
    assert counters["rtde_output_dropped"] == 1
    assert client.ask(rtde.CMD_PAUSE)[0].payload == b"\x01"
    assert not client.session.due(300 * MS)


def test_unknown_outputs_and_rates_are_answered_not_fatal():
    _, _, counters, client = rig()
    (reply,) = client.ask(rtde.CMD_SETUP_OUTPUTS, struct.pack(">d", 125.0) + b"timestamp,warp_factor")
    assert reply.payload == b"\x00DOUBLE,NOT_FOUND"
    (reply,) = client.ask(rtde.CMD_SETUP_OUTPUTS, struct.pack(">d", 9000.0) + b"timestamp")
    assert reply.payload == b"\x01DOUBLE"
    assert counters["rtde_output_not_found"] == 1
    assert counters["rtde_output_rate_capped"] == 1


def test_inputs_are_owned_per_connection_and_released():
    model, owners, counters, first = rig()
    second = Client(2, model, owners, counters)
    assert first.ask(rtde.CMD_SETUP_INPUTS, b"input_int_register_0,input_double_register_0")[0].payload == \
        b"\x01INT32,DOUBLE"
    assert first.ask(rtde.CMD_SETUP_INPUTS, b"input_int_register_0")[0].payload == b"\x02INT32"  # same owner
    assert second.ask(rtde.CMD_SETUP_INPUTS, b"input_int_register_23,input_int_register_0")[0].payload == \
        b"\x00INT32,IN_USE"
    package = rtde.encode_packet(rtde.CMD_DATA_PACKAGE, struct.pack(">Bid", 1, 24, 0.5))
    first.session.handle(rtde.Packet(rtde.CMD_DATA_PACKAGE, package[3:]), 7 * MS)
    assert model.registers.int_in[0] == 24 and model.registers.double_in[0] == 0.5
    assert model.registers.int_in_written_ns[0] == 7 * MS
    first.session.release()
    assert second.ask(rtde.CMD_SETUP_INPUTS, b"input_int_register_0")[0].payload == b"\x01INT32"
    assert counters["rtde_input_refused"] == 1
