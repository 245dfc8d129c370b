"""Malformed bus messages for the fault tests: one function per malformation, each turning a valid message of any
kind into the raw multipart frames of a broken one, and the error kind the receiver must count it under.

A malformation that does not apply to a kind (a non-unit quaternion for a kind without poses) returns None. The
frames go out as they are (``socket.send_multipart``), so nothing on the sending side checks them.

A frame larger than ``MAX_FRAME_BYTES`` is not in the table (its size makes it one per socket, not one per round):
``oversized_frame`` builds one, which the receiver counts as ``oversized_frame`` (it stays below the receiving
socket's ``MAXMSGSIZE``, ``bus.MAX_RECEIVE_BYTES``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import msgspec
import numpy as np

from hydrosoft.services.bus import messages as msg
from hydrosoft.services.bus.sockets import FUTURE_STAMP_TOLERANCE_NS, FutureStamp, StaleStamp

Frames = list[bytes]
Header = dict[str, Any]


@dataclass(frozen=True)
class Malformed:
    """One broken message: ``name`` of its malformation, the error ``kind`` its receiver counts, its ``frames``."""

    name: str
    kind: str
    frames: Frames


def frames_of(message: msg.Message, topic: str) -> Frames:
    """The valid frames of ``message`` on ``topic``, stamped now (as a publisher would send them)."""
    stamped = msgspec.structs.replace(message, seq=1, stamp_ns=time.monotonic_ns(), source="fuzz")
    return [bytes(memoryview(frame)) for frame in msg.encode(stamped, topic)]


def _header(frames: Frames) -> Header:
    return msgspec.msgpack.decode(frames[1])


def _with_header(frames: Frames, header: Header, arrays: Frames | None = None) -> Frames:
    return [frames[0], msgspec.msgpack.encode(header), *(frames[2:] if arrays is None else arrays)]


def _arrays(kind: type[msg.Message]) -> list[str]:
    """The array fields of ``kind`` in the order their frames travel (the struct's field order)."""
    return [name for name in kind.__struct_fields__ if name in kind.ARRAYS]


def _first_array(kind: type[msg.Message], header: Header,
                 test: Callable[[msg.ArraySpec], bool] = lambda spec: True) -> tuple[int, str] | None:
    """``(index among the sent arrays, field name)`` of the first array field of ``kind`` whose spec passes
    ``test``; None when no sent array does."""
    sent = [name for name in _arrays(kind) if header.get(name) is not None]
    return next(((index, name) for index, name in enumerate(sent) if test(kind.ARRAYS[name])), None)


# --- the malformations --------------------------------------------------------------------------------------------


def garbage_header(kind: type[msg.Message], frames: Frames) -> Frames:
    """A header frame that is not msgpack."""
    return [frames[0], b"\xc1\xc1 not msgpack \xff", *frames[2:]]


def garbage_topic(kind: type[msg.Message], frames: Frames) -> Frames:
    """The right topic followed by bytes that are not UTF-8 (subscription prefixes still match)."""
    return [frames[0] + b"\xff\xfe", *frames[1:]]


def header_only(kind: type[msg.Message], frames: Frames) -> Frames | None:
    """The topic frame alone."""
    return [frames[0]]


def missing_array(kind: type[msg.Message], frames: Frames) -> Frames | None:
    """The last array frame left out."""
    return frames[:-1] if len(frames) > 2 else None


def extra_frame(kind: type[msg.Message], frames: Frames) -> Frames:
    """One frame more than the header describes."""
    return [*frames, b"\x00" * 8]


def wrong_schema(kind: type[msg.Message], frames: Frames) -> Frames:
    """A msgpack header of another schema: an unknown field, the kind's own fields missing."""
    return _with_header(frames, {"not_a_field": 1, "seq": 1}, arrays=[])


def wrong_field_type(kind: type[msg.Message], frames: Frames) -> Frames:
    """The ``source`` string replaced by a list."""
    header = _header(frames)
    header["source"] = [1, 2, 3]
    return _with_header(frames, header)


def wrong_dtype(kind: type[msg.Message], frames: Frames) -> Frames | None:
    """An array declared (and sent) in a dtype its field does not accept, with the right byte length."""
    header = _header(frames)
    found = _first_array(kind, header)
    if found is None:
        return None
    index, name = found
    dtype, shape = header[name]
    accepted = {np.dtype(d) for d in kind.ARRAYS[name].dtypes}
    other = next(d for d in (np.dtype("<i8"), np.dtype("<u2"), np.dtype("<f4"), np.dtype("<f8"), np.dtype("u1"))
                 if d not in accepted)
    arrays = frames[2:]
    arrays[index] = np.zeros(shape, other).tobytes()
    header[name] = [other.str, shape]
    return _with_header(frames, header, arrays)


def wrong_shape(kind: type[msg.Message], frames: Frames) -> Frames | None:
    """An array with one axis more than its field allows (the same bytes)."""
    header = _header(frames)
    found = _first_array(kind, header)
    if found is None:
        return None
    index, name = found
    header[name] = [header[name][0], [1, *header[name][1]]]
    return _with_header(frames, header)


def length_mismatch(kind: type[msg.Message], frames: Frames) -> Frames | None:
    """An array frame one byte shorter than its shape and dtype need."""
    if len(frames) < 3:
        return None
    return [*frames[:-1], frames[-1][:-1]]


def oversized_array(kind: type[msg.Message], frames: Frames) -> Frames | None:
    """An array longer along its first axis than the field's limit (fixed size or maximum), within the frame size
    limit."""
    header = _header(frames)
    found = _first_array(kind, header)
    if found is None:
        return None
    index, name = found
    dtype, shape = header[name]
    rule = kind.ARRAYS[name].shape[0]
    limit = rule.max if isinstance(rule, msg.Dim) else rule
    big = [limit + 1, *shape[1:]]
    if math.prod(big) * np.dtype(dtype).itemsize > msg.MAX_FRAME_BYTES:
        big = [limit + 1] + [1] * (len(shape) - 1)
    arrays = frames[2:]
    arrays[index] = np.zeros(big, np.dtype(dtype)).tobytes()
    header[name] = [dtype, big]
    return _with_header(frames, header, arrays)


def oversized_header(kind: type[msg.Message], frames: Frames) -> Frames:
    """A header frame larger than ``MAX_HEADER_BYTES``."""
    header = _header(frames)
    header["source"] = "x" * (msg.MAX_HEADER_BYTES + 1)
    return _with_header(frames, header)


def _float_array(kind: type[msg.Message], header: Header) -> tuple[int, str] | None:
    return _first_array(kind, header, lambda spec: spec.finite and any(d.startswith("float") for d in spec.dtypes))


def _with_value(frames: Frames, kind: type[msg.Message], value: float) -> Frames | None:
    """``value`` in the first finite float array, else in the first float scalar (of a nested struct too)."""
    header = _header(frames)
    found = _float_array(kind, header)
    if found is not None:
        index, name = found
        dtype, shape = header[name]
        array = np.frombuffer(frames[2 + index], np.dtype(dtype)).copy()
        array[0] = value
        arrays = frames[2:]
        arrays[index] = array.tobytes()
        return _with_header(frames, header, arrays)
    return _with_header(frames, header) if _set_first_float(header, value) else None


def _set_first_float(fields: Header, value: float) -> bool:
    """Set the first float scalar of ``fields`` (depth first through nested structs) to ``value``; whether one was
    found."""
    for name, current in fields.items():
        if isinstance(current, float):
            fields[name] = value
            return True
        if isinstance(current, dict) and _set_first_float(current, value):
            return True
    return False


def nan_value(kind: type[msg.Message], frames: Frames) -> Frames | None:
    """NaN in the first finite float array (a pose's x, a wrench's Fx) or float scalar."""
    return _with_value(frames, kind, math.nan)


def inf_value(kind: type[msg.Message], frames: Frames) -> Frames | None:
    """+Inf in the first finite float array or float scalar."""
    return _with_value(frames, kind, math.inf)


def non_unit_quaternion(kind: type[msg.Message], frames: Frames) -> Frames | None:
    """A pose whose quaternion has norm 2."""
    header = _header(frames)
    found = _first_array(kind, header, lambda spec: spec.unit_quaternion)
    if found is None:
        return None
    index, name = found
    dtype, _ = header[name]
    array = np.frombuffer(frames[2 + index], np.dtype(dtype)).copy()
    if array.size == 0:
        return None
    array.reshape(-1, 7)[:, 3:] *= 2.0
    arrays = frames[2:]
    arrays[index] = array.tobytes()
    return _with_header(frames, header, arrays)


def future_stamp(kind: type[msg.Message], frames: Frames) -> Frames:
    """Stamped one second in the future of the receiver's clock."""
    header = _header(frames)
    header["stamp_ns"] = time.monotonic_ns() + 1_000_000_000 + FUTURE_STAMP_TOLERANCE_NS
    return _with_header(frames, header)


def stale_stamp(kind: type[msg.Message], frames: Frames) -> Frames:
    """Stamped ten seconds ago (older than anything its receiver already holds on the topic)."""
    header = _header(frames)
    header["stamp_ns"] = time.monotonic_ns() - 10_000_000_000
    return _with_header(frames, header)


#: Every malformation and the error kind (``MessageError.kind``) a subscriber counts it under.
MALFORMATIONS: dict[str, tuple[Callable[[type[msg.Message], Frames], Frames | None], str]] = {
    "garbage_header": (garbage_header, msg.GarbageBytes.kind),
    "garbage_topic": (garbage_topic, msg.GarbageBytes.kind),
    "header_only": (header_only, msg.FrameCountError.kind),
    "missing_array": (missing_array, msg.FrameCountError.kind),
    "extra_frame": (extra_frame, msg.FrameCountError.kind),
    "wrong_schema": (wrong_schema, msg.SchemaError.kind),
    "wrong_field_type": (wrong_field_type, msg.SchemaError.kind),
    "wrong_dtype": (wrong_dtype, msg.DtypeError.kind),
    "wrong_shape": (wrong_shape, msg.ShapeError.kind),
    "length_mismatch": (length_mismatch, msg.LengthMismatch.kind),
    "oversized_array": (oversized_array, msg.ShapeError.kind),
    "oversized_header": (oversized_header, msg.OversizedFrame.kind),
    "nan": (nan_value, msg.NonFinite.kind),
    "inf": (inf_value, msg.NonFinite.kind),
    "non_unit_quaternion": (non_unit_quaternion, msg.NonUnitQuaternion.kind),
    "future_stamp": (future_stamp, FutureStamp.kind),
    "stale_stamp": (stale_stamp, StaleStamp.kind),
}


def malformed(message: msg.Message, topic: str) -> list[Malformed]:
    """Every malformation that applies to ``message``'s kind, each built from ``message`` on ``topic`` stamped
    now (so build them again for every round: stamps age)."""
    frames = frames_of(message, topic)
    broken = []
    for name, (make, kind) in MALFORMATIONS.items():
        made = make(type(message), list(frames))
        if made is not None:
            broken.append(Malformed(name, kind, made))
    return broken


def oversized_frame(topic: str) -> Frames:
    """A message whose one array frame is larger than ``MAX_FRAME_BYTES`` (and below ``bus.MAX_RECEIVE_BYTES``)."""
    return [topic.encode(), b"\x80", bytes(msg.MAX_FRAME_BYTES + 1)]
