"""RTDE packet encoding against the bytes devices.md captured from the real ur_rtde 1.6.5 client."""

from __future__ import annotations

import struct

import pytest

from hydrosoft.drivers.ur import rtde_protocol as rtde


def test_version_handshake_bytes_match_the_capture():
    assert rtde.encode_packet(rtde.CMD_REQUEST_PROTOCOL_VERSION, struct.pack(">H", 2)) == bytes.fromhex("0005560002")
    assert rtde.decode_protocol_version_request(bytes.fromhex("0002")) == 2
    assert rtde.encode_protocol_version_reply(True) == bytes.fromhex("00045601")
    assert rtde.encode_controller_version_reply(5, 15, 0, 0) == bytes.fromhex(
        "0013" "76" "00000005" "0000000f" "00000000" "00000000"
    )


def test_output_setup_request_and_reply_match_the_capture():
    names = b"timestamp,actual_TCP_pose,runtime_state,"
    packet = bytes.fromhex("00334f405f400000000000") + names
    (parsed,) = _packets(packet)
    assert parsed.command == rtde.CMD_SETUP_OUTPUTS
    frequency_hz, variables = rtde.decode_output_setup(parsed.payload)
    assert frequency_hz == 125.0
    assert variables == ["timestamp", "actual_TCP_pose", "runtime_state"]
    reply = rtde.encode_setup_reply(rtde.CMD_SETUP_OUTPUTS, 1, ["DOUBLE", "VECTOR6D", "UINT32"])
    assert reply == bytes.fromhex("001a4f01") + b"DOUBLE,VECTOR6D,UINT32"


def test_data_package_sizes_match_the_client():
    receive = rtde.Recipe.build(1, ["timestamp", "actual_TCP_pose", "runtime_state"], rtde.OUTPUT_TYPES)
    packet = rtde.encode_data_package(receive, {"timestamp": 1.5, "actual_TCP_pose": [0.3, -0.2, 0.4, 0, 3.14, 0],
                                                "runtime_state": 2})
    assert packet[:4] == bytes.fromhex("00405501")  # 64 bytes in all, as captured
    regs = [f"input_double_register_{i}" for i in range(11)]
    movel = rtde.Recipe.build(1, ["input_int_register_0", *regs[:8], "input_int_register_1"], rtde.INPUT_TYPES)
    servol = rtde.Recipe.build(2, ["input_int_register_0", *regs], rtde.INPUT_TYPES)
    stop = rtde.Recipe.build(8, ["input_int_register_0", "input_double_register_0"], rtde.INPUT_TYPES)
    assert (movel.body_size, servol.body_size, stop.body_size) == (73, 93, 13)  # devices.md 3.3
    clear = rtde.Recipe.build(4, ["input_int_register_0"], rtde.INPUT_TYPES)
    assert rtde.encode_data_package(clear, {"input_int_register_0": 0}) == bytes.fromhex("0008550400000000")


def test_data_package_round_trip_and_checks():
    recipe = rtde.Recipe.build(3, ["input_int_register_0", "input_double_register_0", "external_force_torque"],
                               rtde.INPUT_TYPES)
    values = {"input_int_register_0": 24, "input_double_register_0": -0.5,
              "external_force_torque": (1.0, 2.0, 3.0, 4.0, 5.0, 6.0)}
    payload = rtde.encode_data_package(recipe, values)[rtde.HEADER_SIZE:]
    assert rtde.data_package_recipe_id(payload) == 3
    assert rtde.decode_data_package(recipe, payload) == values
    with pytest.raises(rtde.RtdeProtocolError, match="expected 61"):
        rtde.decode_data_package(recipe, payload[:-1])
    other = rtde.Recipe.build(4, list(recipe.names), rtde.INPUT_TYPES)
    with pytest.raises(rtde.RtdeProtocolError, match="recipe id 3, expected 4"):
        rtde.decode_data_package(other, payload)


def test_type_sizes_follow_the_rtde_guide():
    sizes = {t: struct.calcsize(">" + code) for t, code in rtde.TYPE_FORMATS.items()}
    assert sizes == {"VECTOR6D": 48, "VECTOR3D": 24, "VECTOR6INT32": 24, "VECTOR6UINT32": 24, "DOUBLE": 8,
                     "UINT64": 8, "INT32": 4, "UINT32": 4, "UINT8": 1, "BOOL": 1}


def test_packet_reader_reassembles_split_and_joined_packets():
    stream = rtde.encode_packet(rtde.CMD_START) + rtde.encode_packet(rtde.CMD_TEXT_MESSAGE, b"hello")
    reader = rtde.PacketReader()
    reader.feed(stream[:4])
    assert [p.command for p in reader.packets()] == [rtde.CMD_START]
    reader.feed(stream[4:6])
    assert reader.packets() == []
    reader.feed(stream[6:])
    assert reader.packets() == [rtde.Packet(rtde.CMD_TEXT_MESSAGE, b"hello")]


def test_packet_reader_rejects_a_size_below_the_header():
    reader = rtde.PacketReader()
    reader.feed(bytes.fromhex("000255"))
    with pytest.raises(rtde.RtdeProtocolError, match="less than the 3-byte header"):
        reader.packets()


def test_setup_requests_reject_bad_payloads():
    with pytest.raises(rtde.RtdeProtocolError, match="8-byte frequency"):
        rtde.decode_output_setup(b"\x00\x01")
    with pytest.raises(rtde.RtdeProtocolError, match="names no variables"):
        rtde.decode_input_setup(b",,")
    with pytest.raises(rtde.RtdeProtocolError, match="not ASCII"):
        rtde.decode_input_setup("input_int_register_0,\u00e9".encode())
    assert rtde.unknown_names(["timestamp", "bogus", "runtime_state"], rtde.OUTPUT_TYPES) == ["bogus"]


def _packets(data: bytes) -> list[rtde.Packet]:
    reader = rtde.PacketReader()
    reader.feed(data)
    return reader.packets()
