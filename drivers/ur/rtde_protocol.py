"""Pure encoding and decoding of UR's RTDE protocol (version 2), as the ``ur_rtde`` 1.6.5 client uses it.

No sockets here: the simulated controller (``simulator.py``) feeds bytes in and takes bytes out, and the tests call
these functions directly. Facts follow ``docs/devices.md`` sections 1-4 (UR's RTDE guide, UR's
``rtde/serialize.py`` and ur_rtde's ``robot_state.cpp``).

Framing: every packet is ``uint16 total size (header included) | uint8 command | payload``, all numbers big-endian.
A data package (``U``) carries one recipe-id byte, then the recipe's fields in order, each with the fixed size of
its type (``TYPE_FORMATS``). ur_rtde decodes data packages with its own name-to-type table, so a controller must
send exactly the types listed in ``OUTPUT_TYPES`` for the names it accepts.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

# Command bytes (devices.md section 1, ur_rtde rtde.h).
CMD_REQUEST_PROTOCOL_VERSION = ord("V")
CMD_GET_URCONTROL_VERSION = ord("v")
CMD_TEXT_MESSAGE = ord("M")
CMD_DATA_PACKAGE = ord("U")
CMD_SETUP_OUTPUTS = ord("O")
CMD_SETUP_INPUTS = ord("I")
CMD_START = ord("S")
CMD_PAUSE = ord("P")
KNOWN_COMMANDS = frozenset(
    {
        CMD_REQUEST_PROTOCOL_VERSION,
        CMD_GET_URCONTROL_VERSION,
        CMD_TEXT_MESSAGE,
        CMD_DATA_PACKAGE,
        CMD_SETUP_OUTPUTS,
        CMD_SETUP_INPUTS,
        CMD_START,
        CMD_PAUSE,
    }
)

HEADER = struct.Struct(">HB")
HEADER_SIZE = HEADER.size
MAX_PACKET_SIZE = 0xFFFF
SUPPORTED_PROTOCOL_VERSIONS = frozenset({1, 2})

NOT_FOUND = "NOT_FOUND"
IN_USE = "IN_USE"

# struct codes of every RTDE type (devices.md section 1, "Type sizes").
TYPE_FORMATS: dict[str, str] = {
    "VECTOR6D": "6d",
    "VECTOR3D": "3d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
    "DOUBLE": "d",
    "UINT64": "Q",
    "INT32": "i",
    "UINT32": "I",
    "UINT8": "B",
    "BOOL": "?",
}
VECTOR_LENGTHS = {"VECTOR6D": 6, "VECTOR3D": 3, "VECTOR6INT32": 6, "VECTOR6UINT32": 6}

REGISTER_COUNT = 48  # input/output int and double registers 0..47 (24..47 are the "upper range")


def _register_types(prefix: str, rtde_type: str) -> dict[str, str]:
    return {f"{prefix}_{i}": rtde_type for i in range(REGISTER_COUNT)}


# Output variables the simulated controller serves, with the types of ur_rtde's table (devices.md section 2).
OUTPUT_TYPES: dict[str, str] = {
    "timestamp": "DOUBLE",
    "target_q": "VECTOR6D",
    "target_qd": "VECTOR6D",
    "target_qdd": "VECTOR6D",
    "target_current": "VECTOR6D",
    "target_moment": "VECTOR6D",
    "actual_q": "VECTOR6D",
    "actual_qd": "VECTOR6D",
    "actual_current": "VECTOR6D",
    "joint_control_output": "VECTOR6D",
    "actual_TCP_pose": "VECTOR6D",
    "actual_TCP_speed": "VECTOR6D",
    "actual_TCP_force": "VECTOR6D",
    "target_TCP_pose": "VECTOR6D",
    "target_TCP_speed": "VECTOR6D",
    "actual_digital_input_bits": "UINT64",
    "joint_temperatures": "VECTOR6D",
    "actual_execution_time": "DOUBLE",
    "robot_mode": "INT32",
    "joint_mode": "VECTOR6INT32",
    "safety_mode": "INT32",
    "safety_status": "INT32",
    "actual_tool_accelerometer": "VECTOR3D",
    "speed_scaling": "DOUBLE",
    "target_speed_fraction": "DOUBLE",
    "actual_momentum": "DOUBLE",
    "actual_main_voltage": "DOUBLE",
    "actual_robot_voltage": "DOUBLE",
    "actual_robot_current": "DOUBLE",
    "actual_joint_voltage": "VECTOR6D",
    "actual_digital_output_bits": "UINT64",
    "runtime_state": "UINT32",
    "standard_analog_input0": "DOUBLE",
    "standard_analog_input1": "DOUBLE",
    "standard_analog_output0": "DOUBLE",
    "standard_analog_output1": "DOUBLE",
    "robot_status_bits": "UINT32",
    "safety_status_bits": "UINT32",
    "ft_raw_wrench": "VECTOR6D",
    "payload": "DOUBLE",
    "payload_cog": "VECTOR3D",
    "payload_inertia": "VECTOR6D",
    **_register_types("output_int_register", "INT32"),
    **_register_types("output_double_register", "DOUBLE"),
}

# Input variables a client may write (devices.md sections 3.3 and 4).
INPUT_TYPES: dict[str, str] = {
    **_register_types("input_int_register", "INT32"),
    **_register_types("input_double_register", "DOUBLE"),
    "standard_digital_output_mask": "UINT8",
    "standard_digital_output": "UINT8",
    "configurable_digital_output_mask": "UINT8",
    "configurable_digital_output": "UINT8",
    "tool_digital_output_mask": "UINT8",
    "tool_digital_output": "UINT8",
    "speed_slider_mask": "UINT32",
    "speed_slider_fraction": "DOUBLE",
    "standard_analog_output_mask": "UINT8",
    "standard_analog_output_type": "UINT8",
    "standard_analog_output_0": "DOUBLE",
    "standard_analog_output_1": "DOUBLE",
    "external_force_torque": "VECTOR6D",
}


class RtdeProtocolError(ValueError):
    """Bytes that do not form a valid RTDE packet or payload; the message says what was wrong."""


@dataclass(frozen=True)
class Packet:
    """One RTDE packet: ``command`` byte and its ``payload`` (header stripped)."""

    command: int
    payload: bytes


def encode_packet(command: int, payload: bytes = b"") -> bytes:
    """Frame ``payload`` as one packet: big-endian u16 total size (3 + len(payload)), u8 command, payload."""
    size = HEADER_SIZE + len(payload)
    if size > MAX_PACKET_SIZE:
        raise RtdeProtocolError(f"RTDE packet of {size} bytes exceeds the {MAX_PACKET_SIZE}-byte limit")
    return HEADER.pack(size, command) + payload


class PacketReader:
    """Splits a byte stream into packets. ``feed`` bytes as they arrive, then iterate ``packets()``.

    A size field below the header size can never resync, so it raises ``RtdeProtocolError`` (the connection must
    be closed). Unknown command bytes are returned as packets; the caller decides what to do with them.
    """

    def __init__(self) -> None:
        self._buffer = bytearray()

    def feed(self, data: bytes) -> None:
        self._buffer.extend(data)

    def packets(self) -> list[Packet]:
        """Every complete packet buffered so far, in order; a partial packet stays buffered."""
        out: list[Packet] = []
        while len(self._buffer) >= HEADER_SIZE:
            size, command = HEADER.unpack_from(self._buffer)
            if size < HEADER_SIZE:
                raise RtdeProtocolError(f"RTDE header declares {size} bytes, less than the 3-byte header")
            if len(self._buffer) < size:
                break
            out.append(Packet(command, bytes(self._buffer[HEADER_SIZE:size])))
            del self._buffer[:size]
        return out


# ---------------------------------------------------------------------------------------------------------------
# Handshake payloads
# ---------------------------------------------------------------------------------------------------------------


def decode_protocol_version_request(payload: bytes) -> int:
    """The u16 protocol version a client asks for in ``V`` (ur_rtde sends 2)."""
    if len(payload) != 2:
        raise RtdeProtocolError(f"'V' payload must be 2 bytes (u16 version), got {len(payload)}")
    return struct.unpack(">H", payload)[0]


def encode_protocol_version_reply(accepted: bool) -> bytes:
    """``V`` reply: one byte, 1 = accepted."""
    return encode_packet(CMD_REQUEST_PROTOCOL_VERSION, bytes([1 if accepted else 0]))


def encode_controller_version_reply(major: int, minor: int, bugfix: int, build: int) -> bytes:
    """``v`` reply: four big-endian u32, e.g. 5, 15, 0, 0 for PolyScope 5.15."""
    return encode_packet(CMD_GET_URCONTROL_VERSION, struct.pack(">IIII", major, minor, bugfix, build))


def decode_output_setup(payload: bytes) -> tuple[float, list[str]]:
    """``O`` request: (frequency in Hz, variable names). Names are comma separated; ur_rtde adds a trailing comma."""
    if len(payload) < 8:
        raise RtdeProtocolError(f"'O' payload must start with an 8-byte frequency, got {len(payload)} bytes")
    (frequency_hz,) = struct.unpack_from(">d", payload)
    return frequency_hz, _split_names(payload[8:])


def decode_input_setup(payload: bytes) -> list[str]:
    """``I`` request: the variable names (comma separated, trailing comma allowed)."""
    return _split_names(payload)


def _split_names(raw: bytes) -> list[str]:
    try:
        text = raw.decode("ascii")
    except UnicodeDecodeError as exc:
        raise RtdeProtocolError(f"RTDE variable list is not ASCII: {raw[:40]!r}") from exc
    names = [name.strip() for name in text.split(",") if name.strip()]
    if not names:
        raise RtdeProtocolError("RTDE setup request names no variables")
    return names


def encode_setup_reply(command: int, recipe_id: int, types: list[str]) -> bytes:
    """``O`` or ``I`` reply: recipe-id byte, then the types joined by commas (``NOT_FOUND``/``IN_USE`` in place)."""
    return encode_packet(command, bytes([recipe_id]) + ",".join(types).encode("ascii"))


def encode_start_reply(accepted: bool) -> bytes:
    """``S`` reply: one byte, 1 = started."""
    return encode_packet(CMD_START, bytes([1 if accepted else 0]))


def encode_pause_reply(accepted: bool) -> bytes:
    """``P`` reply: one byte, 1 = paused."""
    return encode_packet(CMD_PAUSE, bytes([1 if accepted else 0]))


# ---------------------------------------------------------------------------------------------------------------
# Recipes and data packages
# ---------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Recipe:
    """An agreed list of variables with their types; ``codec`` packs ``recipe id byte + fields`` big-endian."""

    recipe_id: int
    names: tuple[str, ...]
    types: tuple[str, ...]
    codec: struct.Struct

    @classmethod
    def build(cls, recipe_id: int, names: list[str], table: dict[str, str]) -> Recipe:
        """Recipe of ``names`` typed from ``table``; every name must be in it (check with ``unknown_names``)."""
        types = tuple(table[name] for name in names)
        return cls(recipe_id, tuple(names), types, struct.Struct(">B" + "".join(TYPE_FORMATS[t] for t in types)))

    @property
    def body_size(self) -> int:
        """Bytes of a data package's payload: 1 recipe-id byte plus the fields."""
        return self.codec.size


def unknown_names(names: list[str], table: dict[str, str]) -> list[str]:
    """The names that ``table`` does not know, in order."""
    return [name for name in names if name not in table]


def encode_data_package(recipe: Recipe, values: dict[str, object]) -> bytes:
    """``U`` packet with ``recipe``'s fields taken from ``values`` (vectors as sequences of the right length)."""
    flat: list[object] = [recipe.recipe_id]
    for name, rtde_type in zip(recipe.names, recipe.types):
        value = values[name]
        if rtde_type in VECTOR_LENGTHS:
            flat.extend(value)  # type: ignore[arg-type]
        else:
            flat.append(value)
    return encode_packet(CMD_DATA_PACKAGE, recipe.codec.pack(*flat))


def decode_data_package(recipe: Recipe, payload: bytes) -> dict[str, object]:
    """Fields of a ``U`` payload (recipe-id byte first) as ``name -> value`` (vectors as tuples).

    Raises ``RtdeProtocolError`` when the size does not match the recipe or the recipe id differs.
    """
    if len(payload) != recipe.body_size:
        raise RtdeProtocolError(
            f"data package for recipe {recipe.recipe_id} has {len(payload)} bytes, expected {recipe.body_size}"
        )
    flat = recipe.codec.unpack(payload)
    if flat[0] != recipe.recipe_id:
        raise RtdeProtocolError(f"data package carries recipe id {flat[0]}, expected {recipe.recipe_id}")
    values: dict[str, object] = {}
    index = 1
    for name, rtde_type in zip(recipe.names, recipe.types):
        length = VECTOR_LENGTHS.get(rtde_type)
        if length is None:
            values[name] = flat[index]
            index += 1
        else:
            values[name] = tuple(flat[index : index + length])
            index += length
    return values


def data_package_recipe_id(payload: bytes) -> int:
    """The recipe id of a ``U`` payload (its first byte)."""
    if not payload:
        raise RtdeProtocolError("empty data package")
    return payload[0]
