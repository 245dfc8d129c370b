"""Message kinds: wire round trips, zero-copy frames, and one specific error per kind of malformed input."""

import msgspec
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from hydrosoft.services.bus import messages as m

IDENTITY_POSE = np.array([0.1, -0.2, 0.3, 1.0, 0.0, 0.0, 0.0])


def tilted_pose(angle_rad: float = 0.3) -> np.ndarray:
    return np.array([0.4, 0.0, 0.1, np.cos(angle_rad / 2), 0.0, 0.0, np.sin(angle_rad / 2)])


def goal() -> m.Goal:
    return m.Goal(task="pushing", target_pose=tilted_pose(), tolerance_mm=5.0, timeout_s=30.0)


def status() -> m.ServiceStatus:
    return m.ServiceStatus(state="degraded", pid=1234, uptime_s=12.5, published_hz={"wrench/ft": 499.5},
                           received_hz={}, errors={"schema": 2}, last_error="schema: bad", restarts=1)


def one_of_each_kind() -> list[m.Message]:
    rng = np.random.default_rng(1)
    return [
        m.DepthFrame(bubble="left", depth=rng.integers(0, 5000, (48, 64), dtype=np.uint16), depth_scale_m=1e-4,
                     fx_px=380.0, fy_px=381.0, cx_px=32.0, cy_px=24.0, hw_stamp_ns=123),
        m.MembraneDeformation(bubble="left", deformation=rng.normal(0, 1e-3, (48, 64)).astype(np.float32),
                              reference_stamp_ns=99),
        m.TagDetections(camera="top", ids=np.array([3, 7], dtype=np.int32), corners_px=rng.uniform(0, 640, (2, 4, 2)),
                        poses=np.stack([IDENTITY_POSE, tilted_pose()]), reprojection_error_px=np.array([0.2, 0.4]),
                        ambiguity=np.array([0.1, 0.9])),
        m.ObjectPose(object="box", pose=tilted_pose(), tags_used=(3, 7), quality=0.8, hw_stamp_ns=None),
        m.Wrench(sensor="ft300", wrench=np.array([1.0, -2.0, 9.8, 0.01, 0.02, 0.03]), tared=True, hw_stamp_ns=55),
        m.ArmState(arm="ur5e", tcp_pose=IDENTITY_POSE, tcp_speed=np.zeros(6), running=True, protective_stop=False,
                   emergency_stop=False, servo_active=False, stop_reason="external stop: safeguard stop",
                   stop_owner="external", controller_stop="safeguard stop", safety_flags=("safeguard stop",),
                   latched=True),
        m.ArmTarget(arm="ur5e", tcp_pose=tilted_pose(), deadline_ns=10**12, plan_seq=4, goal_started_ns=10**11,
                    plan_done_ns=10**11 + 5),
        m.Plan(task="pushing", actions=rng.normal(0, 1e-3, (5, 2, 6)).astype(np.float32),
               predicted_object_poses=np.tile(IDENTITY_POSE, (5, 1)).astype(np.float32),
               predicted_forces=rng.normal(0, 1, (2, 30, 3)).astype(np.float32), cost=1.25, solve_ms=180.0),
        m.Heartbeat(period_s=0.1),
        status(),
        m.CommandReply(ok=False, error="no goal set"),
        m.StatusReply(ok=True, running=True, goal=goal(), status=status()),
        m.SetGoal(goal=m.Goal(task="rotation", dyaw_rad=0.5, tolerance_mm=3.0, tolerance_deg=2.0, timeout_s=20.0)),
        m.Start(),
        m.Stop(reason="operator"),
        m.GetStatus(deadline_ns=5),
        m.EnableArm(arm="ur5e", by="safety officer"),
        m.ArmEnableReply(ok=True, cleared="program paused"),
        m.EvalObjectPose(object="box", pose=tilted_pose()),
        m.EvalContactForces(bodies=("bubble", "table"), points=rng.uniform(-0.05, 0.05, (30, 3)),
                            forces=rng.normal(0, 1, (2, 30, 3))),
        m.Tare(deadline_ns=7),
        m.TareReply(ok=True, bias=np.array([1.2, -0.8, 2.5, 0.04, -0.03, 0.02]), taken_unix_ns=1_700_000_000 * 10**9),
        m.CameraImage.of("tag_camera", rng.integers(0, 256, (48, 64, 3), dtype=np.uint8), hw_stamp_ns=77),
        m.CameraImage.of("grey_camera", rng.integers(0, 256, (48, 64), dtype=np.uint8)),
    ]


def assert_same(a: object, b: object) -> None:
    """Field-by-field equality, arrays by dtype, shape and values."""
    assert type(a) is type(b)
    if isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and a.shape == b.shape
        np.testing.assert_array_equal(a, b)
    elif isinstance(a, msgspec.Struct):
        for name in a.__struct_fields__:
            assert_same(getattr(a, name), getattr(b, name))
    else:
        assert a == b


def as_bytes(frames: list) -> list[bytes]:
    return [bytes(frame) for frame in frames]


def test_the_samples_cover_every_registered_kind():
    assert {type(msg) for msg in one_of_each_kind()} == set(m.KINDS.values())


@pytest.mark.parametrize("msg", one_of_each_kind(), ids=lambda msg: type(msg).__name__)
def test_every_kind_survives_the_wire(msg):
    topic, back = m.decode(as_bytes(m.encode(msg)))
    assert topic == msg.topic
    assert_same(msg, back)


def test_instance_topics_resolve_to_their_kind():
    depth = one_of_each_kind()[0]
    topic, back = m.decode(as_bytes(m.encode(depth, m.topic_for(m.DepthFrame, "left"))))
    assert topic == "depth/left" and isinstance(back, m.DepthFrame)
    assert m.kind_for_topic("eval/object_pose") is m.EvalObjectPose
    assert m.kind_for_topic("eval/object_pose/box") is m.EvalObjectPose
    assert m.kind_for_topic("status/planner") is m.ServiceStatus
    with pytest.raises(m.UnknownTopic):
        m.kind_for_topic("depthx")
    with pytest.raises(m.UnknownTopic):
        m.kind_for_topic("eval")


def test_arrays_are_sent_without_copy_and_received_as_read_only_views():
    depth = one_of_each_kind()[0]
    frames = m.encode(depth)
    assert frames[2] is depth.depth  # the array itself goes to ZeroMQ
    wire = as_bytes(frames)
    _, back = m.decode(wire)
    assert not back.depth.flags.writeable
    assert np.shares_memory(back.depth, np.frombuffer(wire[2], dtype=np.uint8))


def test_a_non_contiguous_array_is_made_contiguous_on_the_wire():
    depth = np.arange(64 * 48, dtype=np.uint16).reshape(64, 48).T  # (48, 64) view, Fortran order
    msg = one_of_each_kind()[0]
    msg = msgspec.structs.replace(msg, depth=depth)
    _, back = m.decode(as_bytes(m.encode(msg)))
    np.testing.assert_array_equal(back.depth, depth)


def test_an_empty_detection_survives_the_wire():
    empty = m.TagDetections(camera="top", ids=np.zeros(0, np.int32), corners_px=np.zeros((0, 4, 2)),
                            poses=np.zeros((0, 7)), reprojection_error_px=np.zeros(0), ambiguity=np.zeros(0))
    _, back = m.decode(as_bytes(m.encode(empty)))
    assert back.poses.shape == (0, 7)


@given(st.lists(st.floats(-1e6, 1e6), min_size=6, max_size=6),
       st.lists(st.floats(-1.0, 1.0), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 1e-3))
def test_finite_wrenches_and_normalised_poses_round_trip_exactly(wrench, quaternion):
    pose = np.concatenate([[0.1, 0.2, 0.3], np.asarray(quaternion) / np.linalg.norm(quaternion)])
    for msg in (m.Wrench(sensor="ft", wrench=np.asarray(wrench), tared=False),
                m.ObjectPose(object="box", pose=pose, tags_used=(), quality=1.0)):
        assert_same(msg, m.decode(as_bytes(m.encode(msg)))[1])


# --- malformed input: each kind of problem raises its own error --------------------------------------------------


def wire(msg: m.Message, topic: str | None = None, header: dict | None = None, arrays: list | None = None):
    """The frames of ``msg`` with header fields replaced by ``header`` and the array frames by ``arrays``."""
    frames = as_bytes(m.encode(msg))
    fields = msgspec.msgpack.decode(frames[1])
    fields.update(header or {})
    return [(topic or msg.topic).encode(), msgspec.msgpack.encode(fields), *(frames[2:] if arrays is None else arrays)]


WRENCH = m.Wrench(sensor="ft", wrench=np.arange(6.0), tared=True)
POSE = m.ObjectPose(object="box", pose=IDENTITY_POSE, tags_used=(1,), quality=0.5)


def f8(*values: float) -> bytes:
    return np.array(values, dtype=np.float64).tobytes()


MALFORMED = {
    "garbage header": (m.GarbageBytes, [b"wrench", b"\xc1\xff\x00 not msgpack", f8(*range(6))]),
    "topic not utf-8": (m.GarbageBytes, [b"\xff\xfe", b"\x80"]),
    "unknown topic": (m.UnknownTopic, [b"torque", msgspec.msgpack.encode({})]),
    "empty topic": (m.UnknownTopic, [b"", msgspec.msgpack.encode({})]),
    "only a topic": (m.FrameCountError, [b"wrench"]),
    "missing array frame": (m.FrameCountError, wire(WRENCH, arrays=[])),
    "extra array frame": (m.FrameCountError, wire(WRENCH, arrays=[f8(*range(6)), b"extra"])),
    "another kind's header": (m.SchemaError, [b"wrench", as_bytes(m.encode(m.Heartbeat(period_s=1.0)))[1]]),
    "missing field": (m.SchemaError, [b"heartbeat", msgspec.msgpack.encode({"seq": 1})]),
    "unknown field": (m.SchemaError, wire(m.Heartbeat(period_s=1.0), header={"colour": "red"})),
    "mistyped field": (m.SchemaError, wire(WRENCH, header={"tared": "yes"})),
    "state not in the list": (m.SchemaError, wire(status(), header={"state": "sleepy"})),
    "array meta not a meta": (m.SchemaError, wire(WRENCH, header={"wrench": "six floats"})),
    "negative array size": (m.SchemaError, wire(WRENCH, header={"wrench": ["<f8", [-6]]})),
    "dtype the field refuses": (m.DtypeError, wire(WRENCH, header={"wrench": ["<f4", [6]]},
                                                   arrays=[np.zeros(6, np.float32).tobytes()])),
    "object dtype": (m.DtypeError, wire(WRENCH, header={"wrench": ["|O", [6]]})),
    "big-endian dtype": (m.DtypeError, wire(WRENCH, header={"wrench": [">f8", [6]]})),
    "not a dtype": (m.DtypeError, wire(WRENCH, header={"wrench": ["float99", [6]]})),
    "wrong shape": (m.ShapeError, wire(WRENCH, header={"wrench": ["<f8", [7]]}, arrays=[f8(*range(7))])),
    "wrong number of axes": (m.ShapeError, wire(WRENCH, header={"wrench": ["<f8", [2, 3]]})),
    "image side above its limit": (m.ShapeError, wire(
        one_of_each_kind()[0], header={"depth": ["<u2", [3000, 2]]}, arrays=[np.zeros(6000, np.uint16).tobytes()])),
    "tag count differs between fields": (m.ShapeError, wire(
        one_of_each_kind()[2], header={"ids": ["<i4", [3]]}, arrays=[
            np.zeros(3, np.int32).tobytes(), *as_bytes(m.encode(one_of_each_kind()[2]))[3:]])),
    "frame shorter than its shape": (m.LengthMismatch, wire(WRENCH, arrays=[f8(*range(5))])),
    "frame longer than its shape": (m.LengthMismatch, wire(WRENCH, arrays=[f8(*range(6)) + b"\x00"])),
    "oversized array frame": (m.OversizedFrame, wire(WRENCH, arrays=[bytes(m.MAX_FRAME_BYTES + 1)])),
    "oversized header": (m.OversizedFrame, [b"heartbeat", bytes(m.MAX_HEADER_BYTES + 1)]),
    "oversized topic": (m.OversizedFrame, [b"x" * (m.MAX_TOPIC_BYTES + 1), b"\x80"]),
    "NaN in a pose": (m.NonFinite, wire(POSE, arrays=[f8(np.nan, 0, 0, 1, 0, 0, 0)])),
    "Inf in a wrench": (m.NonFinite, wire(WRENCH, arrays=[f8(0, 0, np.inf, 0, 0, 0)])),
    "NaN in a target": (m.NonFinite, wire(one_of_each_kind()[6], arrays=[f8(0, 0, 0, np.nan, 0, 0, 0)])),
    "NaN scalar": (m.NonFinite, wire(m.Heartbeat(period_s=1.0), header={"period_s": float("nan")})),
    "non-unit quaternion": (m.NonUnitQuaternion, wire(POSE, arrays=[f8(0, 0, 0, 1, 1, 0, 0)])),
    "zero quaternion": (m.NonUnitQuaternion, wire(POSE, arrays=[f8(0, 0, 0, 0, 0, 0, 0)])),
    "non-unit quaternion in a plan": (m.NonUnitQuaternion, wire(one_of_each_kind()[7], arrays=[
        *as_bytes(m.encode(one_of_each_kind()[7]))[2:3], np.full((5, 7), 0.9, np.float32).tobytes(),
        *as_bytes(m.encode(one_of_each_kind()[7]))[4:]])),
    "depth scale zero": (m.OutOfRange, wire(one_of_each_kind()[0], header={"depth_scale_m": 0.0})),
    "image of two channels": (m.ShapeError, wire(one_of_each_kind()[-1], header={"image": ["|u1", [4, 4, 2]]},
                                                 arrays=[bytes(32)])),
    "image of 16-bit pixels": (m.DtypeError, wire(one_of_each_kind()[-1], header={"image": ["<u2", [4, 4, 1]]},
                                                  arrays=[bytes(32)])),
    "quality above one": (m.OutOfRange, wire(POSE, header={"quality": 1.5})),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_input_raises_its_specific_error(case):
    error_type, frames = MALFORMED[case]
    with pytest.raises(error_type) as caught:
        m.decode(frames)
    assert type(caught.value) is error_type  # not just a parent class
    assert str(caught.value)  # a clear text, not an empty message


def test_a_grey_camera_image_travels_with_one_channel_and_reads_back_as_h_by_w():
    grey = np.arange(12, dtype=np.uint8).reshape(3, 4)
    _, back = m.decode(as_bytes(m.encode(m.CameraImage.of("top", grey), "image/top")))
    assert back.image.shape == (3, 4, 1)
    np.testing.assert_array_equal(back.frame, grey)
    bgr = np.zeros((3, 4, 3), np.uint8)
    assert m.CameraImage.of("top", bgr).frame is bgr


def test_a_quaternion_within_the_tolerance_is_accepted():
    q = np.array([1.0, 1e-3, 0.0, 0.0])
    nearly = q / np.linalg.norm(q) * (1 + 0.5 * m.QUATERNION_NORM_TOLERANCE)
    _, back = m.decode(wire(POSE, arrays=[f8(0, 0, 0, *nearly)]))
    np.testing.assert_allclose(back.pose[3:], nearly)


def test_error_kinds_are_distinct_names():
    kinds = [cls.kind for cls in m.MessageError.__subclasses__()]
    assert len(kinds) == len(set(kinds)) and "message" not in kinds


def test_encode_refuses_what_decode_would_refuse():
    with pytest.raises(m.DtypeError, match="float64"):
        m.encode(m.Wrench(sensor="ft", wrench=np.zeros(6, np.float32), tared=True))
    with pytest.raises(m.SchemaError, match="numpy array"):
        m.encode(m.Wrench(sensor="ft", wrench=[0.0] * 6, tared=True))
    with pytest.raises(m.NonUnitQuaternion):
        m.encode(m.ArmTarget(arm="ur5e", tcp_pose=np.zeros(7), deadline_ns=1, plan_seq=1))
    with pytest.raises(m.UnknownTopic, match="belongs to DepthFrame"):
        m.encode(WRENCH, "depth/left")
    with pytest.raises(m.OutOfRange, match="either target_pose or"):
        m.encode(m.SetGoal(goal=m.Goal(task="pushing", target_pose=IDENTITY_POSE, dx_m=0.1, tolerance_mm=1.0,
                                       timeout_s=1.0)))
    with pytest.raises(m.ShapeError, match="2 bodies but forces for 1"):
        m.encode(m.EvalContactForces(bodies=("a", "b"), points=np.zeros((3, 3)), forces=np.zeros((1, 3, 3))))
