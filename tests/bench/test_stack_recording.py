"""The material fit on a stack recording (``launch --record``): synthetic press-and-shear trajectories of an NH plant
with a known, non-default material, logged by the recorder's own ``SceneLog`` as the stack publishes them (arm state,
tared wrench, tracked object pose, each with its own stamps), are read back as the fit's trajectories and the fit
recovers the material; samples without a fresh pose are dropped and counted; a file without the wrench is refused
naming the topic."""

from __future__ import annotations

import argparse
import json

import foxglove
import numpy as np
import pytest
import torch

from hydrosoft.bench.fit import RecordingReaders, add_arguments, run, run_fit
from hydrosoft.bench.stack_recording import APPROACH_SAMPLES, pose_at, read_stack_recording, split_at_free_samples
from hydrosoft.bench.synthetic_wrench import PLANT_SPACING_M, synthetic_trajectories
from hydrosoft.services.bus import messages as msg
from hydrosoft.services.recorder import RecorderOptions, SceneLog, open_sinks
from hydrosoft.services.recording.foxglove_scene import SceneBuilder, SceneGeometry

TRUTH = {"E": 3e5 * 1.7, "K": 1e5 * 0.6, "mu": 0.35}
KINDS = ["shear", "twist", "shear_twist", "shear", "shear_twist", "twist"]
STEP_NS = 50_000_000
ARM = "bubble"


@pytest.fixture(autouse=True)
def one_thread():
    torch.set_num_threads(1)


def log_messages(path, messages) -> None:
    """``(topic, message)`` pairs written by the recorder's own logging, each received 0.5 ms after its stamp."""
    context = foxglove.Context()
    geometry = SceneGeometry(bubbles={ARM: (0.06, 0.045, 0.03)}, object_triangles=np.zeros((2, 3, 3)),
                             planner_points=np.eye(3) * 0.01, planner_bodies=(ARM, "table"), static_frames={})
    log = SceneLog(context, SceneBuilder(geometry, epoch_offset_ns=10**18))
    writer, _ = open_sinks(context, RecorderOptions(record=path), path, {})
    log.writer = writer
    for topic, message in messages:
        log.log_message(topic, message, received_ns=message.stamp_ns + 500_000)
    writer.close()


def arm_state(k: int, at: int, pose) -> msg.ArmState:
    return msg.ArmState(seq=k + 1, stamp_ns=at, source=f"arm_commander-{ARM}", arm=ARM, tcp_pose=pose,
                        tcp_speed=np.zeros(6), running=True, protective_stop=False, emergency_stop=False,
                        servo_active=True)


def record(path, bubbles: np.ndarray, objects: np.ndarray, wrenches: np.ndarray, with_wrench: bool = True) -> None:
    """One trajectory (poses ``(K + 1, 7)``, wrenches ``(K + 1, 6)``) as the stack publishes it, through the
    recorder's logging: the arm state 3 ms after each wrench, the tracked pose 7 ms before it, and one last wrench
    1 s after the last pose (no fresh pose: dropped)."""
    start = 1_000_000_000
    messages = []
    for k in range(len(bubbles)):
        at = start + k * STEP_NS
        messages.append(("object_pose/object", msg.ObjectPose(
            seq=k + 1, stamp_ns=at - 7_000_000, source="tag_tracker", object="cube", pose=objects[k],
            tags_used=(0,), quality=1.0)))
        if with_wrench:
            messages.append((f"wrench/{ARM}", msg.Wrench(seq=k + 1, stamp_ns=at, source=f"ft_reader-{ARM}",
                                                         sensor=ARM, wrench=wrenches[k], tared=True)))
        messages.append((f"arm_state/{ARM}", arm_state(k, at + 3_000_000, bubbles[k])))
    if with_wrench:
        late = start + len(bubbles) * STEP_NS + 1_000_000_000
        messages.append((f"wrench/{ARM}", msg.Wrench(seq=len(bubbles) + 1, stamp_ns=late, source=f"ft_reader-{ARM}",
                                                     sensor=ARM, wrench=wrenches[-1], tared=True)))
    log_messages(path, messages)


def test_the_fit_recovers_a_non_default_material_from_stack_recordings_and_counts_dropped_samples(tmp_path):
    _, bubbles, objects, measured = synthetic_trajectories("cube", TRUTH, KINDS, steps=12, seed=1)
    paths = []
    for i in range(len(KINDS)):
        paths.append(tmp_path / f"run-{i}.mcap")
        record(paths[-1], bubbles[i], objects[i], measured[i])
    read = read_stack_recording(paths[0], clamped=True)
    assert (read.arm, read.info.object, read.kept, read.dropped) == (ARM, "cube", 13, 1)
    np.testing.assert_array_equal(read.trajectory.bubble_poses, bubbles[0])
    np.testing.assert_array_equal(read.trajectory.wrenches, measured[0])
    assert read_stack_recording(paths[0], clamped=True, max_gap_s=0.005).kept == 13  # the arm state is 3 ms off
    with pytest.raises(ValueError, match=r"0 sample\(s\).*14 dropped"):  # tracked: the object pose is 7 ms off
        read_stack_recording(paths[0], max_gap_s=0.005)
    document = run_fit(paths, "nh", ["E", "K", "mu"], holdout=0.0, spacing=PLANT_SPACING_M,
                       stack_options={"clamped": True})
    for name, true in TRUTH.items():
        p = document["parameters"][name]
        assert abs(p["start"] / true - 1) > 0.3  # starts far off
        assert p["value"] == pytest.approx(true, rel=0.03), name
        assert p["identified"], name
    stack = document["settings"]["stack_recordings"]
    assert len(stack) == len(KINDS) and all(s["kept"] == 13 and s["dropped"] == 1 for s in stack.values())


def test_a_stack_recording_without_the_wrench_topic_is_refused_naming_it(tmp_path):
    _, bubbles, objects, measured = synthetic_trajectories("cube", TRUTH, ["shear"], steps=4, seed=1)
    path = tmp_path / "no-wrench.mcap"
    record(path, bubbles[0], objects[0], measured[0], with_wrench=False)
    before = path.read_bytes()
    with pytest.raises(ValueError, match=rf"no-wrench.mcap.*no topic wrench/{ARM}"):
        run_fit([path], "nh", ["E"], holdout=0.0, stack_options={"arm": None})
    with pytest.raises(ValueError, match=rf"no topic wrench/{ARM}"):
        read_stack_recording(path, arm=ARM)
    assert path.read_bytes() == before


def test_the_fit_command_takes_a_stack_recording_and_refuses_one_without_the_wrench_with_exit_code_2(tmp_path,
                                                                                                     capsys):
    _, bubbles, objects, measured = synthetic_trajectories("cube", TRUTH, ["shear", "twist"], steps=4, seed=1)
    good, other, bad = tmp_path / "run.mcap", tmp_path / "run-2.mcap", tmp_path / "no-wrench.mcap"
    record(good, bubbles[0], objects[0], measured[0])
    record(other, bubbles[1], objects[1], measured[1])
    record(bad, bubbles[0], objects[0], measured[0], with_wrench=False)
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    assert run(parser.parse_args([str(bad), "--clamped"])) == 2
    assert f"no topic wrench/{ARM}" in capsys.readouterr().err
    assert run(parser.parse_args([str(good), "--max-gap", "-1"])) == 2
    assert "--max-gap must be a positive number of seconds" in capsys.readouterr().err
    tracked = read_stack_recording(good)  # tracked: each sample takes the pose recorded with it
    np.testing.assert_array_equal(tracked.trajectory.object_poses, objects[0])
    args = parser.parse_args([str(good), str(other), "--params", "E", "--holdout", "0.5", "--substeps", "1",
                              "--spacing", str(PLANT_SPACING_M), "--json"])
    assert run(args) == 0
    document = json.loads(capsys.readouterr().out)
    assert document["settings"]["stack_recordings"][str(good)]["kept"] == 5
    assert document["split"]["fit"] and document["split"]["held_out"]


def _turn_z(angle: float) -> np.ndarray:
    return np.array([np.cos(angle / 2), 0.0, 0.0, np.sin(angle / 2)])


def test_poses_are_interpolated_to_the_wrench_stamps_within_the_max_gap_and_else_the_nearest_or_none():
    stamps = np.array([0, 30_000_000])
    poses = np.stack([np.r_[0.0, 0.0, 0.1, _turn_z(0.0)], np.r_[0.03, 0.0, 0.1, _turn_z(0.9)]])
    at_10 = pose_at(stamps, poses, 10_000_000, max_gap_ns=20_000_000)  # 30 ms apart: interpolated
    np.testing.assert_allclose(at_10, np.r_[0.01, 0.0, 0.1, _turn_z(0.3)], atol=1e-12)  # a third: 0.3 of 0.9 rad
    np.testing.assert_array_equal(pose_at(stamps, poses, 30_000_000, 20_000_000), poses[1])
    np.testing.assert_array_equal(pose_at(stamps, poses, 10_000_000, 10_000_000), poses[0])  # too far apart: nearest
    assert pose_at(stamps, poses, 15_000_000, 10_000_000) is None  # ... when within the max gap
    np.testing.assert_array_equal(pose_at(stamps, poses, 45_000_000, 20_000_000), poses[1])  # past the end
    assert pose_at(stamps, poses, 51_000_000, 20_000_000) is None


def test_a_long_stack_recording_is_cut_into_one_trajectory_per_contact_each_with_its_tare_and_interpolated_poses(
        tmp_path):
    _, bubbles, objects, measured = synthetic_trajectories("cube", TRUTH, ["shear", "twist", "shear_twist"], steps=5,
                                                           seed=1)
    # one run: the end of a contact (the recording starts in it), then the three trajectories back to back, each
    # after a pause out of contact longer than the approach the fit keeps
    rows = [(bubbles[0, k], measured[0, k]) for k in (4, 5)]
    for i in range(3):
        rows += [(bubbles[i, 0], np.zeros(6))] * (APPROACH_SAMPLES + 2) + list(zip(bubbles[i], measured[i]))
    path = tmp_path / "long.mcap"
    start, messages = 1_000_000_000, []
    for k, (bubble, wrench) in enumerate(rows):
        at = start + k * STEP_NS
        messages.append((f"wrench/{ARM}", msg.Wrench(seq=k + 1, stamp_ns=at, source=f"ft_reader-{ARM}", sensor=ARM,
                                                     wrench=wrench, tared=True)))
        # the arm state 10 ms before and 15 ms after each wrench, 25 ms apart, moving 1 mm in x between them
        for offset, dx in ((-10_000_000, -0.0004), (15_000_000, 0.0006)):
            messages.append((f"arm_state/{ARM}", arm_state(2 * k + (offset > 0), at + offset,
                                                           bubble + np.r_[dx, np.zeros(6)])))
    messages.append(("object_pose/object", msg.ObjectPose(seq=1, stamp_ns=start, source="tag_tracker",
                                                          object="cube", pose=objects[0, 0], tags_used=(0,),
                                                          quality=1.0)))
    log_messages(path, messages)
    whole = read_stack_recording(path, clamped=True)
    assert whole.kept == len(rows) and whole.dropped == 0
    np.testing.assert_allclose(whole.trajectory.bubble_poses, np.stack([b for b, _ in rows]), atol=1e-12)
    pieces, skipped = split_at_free_samples(whole.trajectory)
    assert skipped == 1 and len(pieces) == 3  # the contact the recording starts in has no tare before it
    for i, piece in enumerate(pieces):
        approach = APPROACH_SAMPLES - 1  # the pause's samples kept before the trajectory's own tare row
        np.testing.assert_array_equal(piece.wrenches[approach:], measured[i])
        np.testing.assert_allclose(piece.bubble_poses[approach:], bubbles[i], atol=1e-12)
        assert piece.phases[0] == "start" and not piece.wrenches[0].any()
    readers = RecordingReaders({"clamped": True})
    info, trajectories = readers(path)
    assert [t.index for t in trajectories] == [1000, 1001, 1002] and info.object == "cube"
    assert readers.stack[str(path)]["trajectories"] == 3 and readers.stack[str(path)]["skipped_in_contact"] == 1
    _, whole_again = RecordingReaders({"clamped": True, "contact_force_n": 0.0})(path)
    assert len(whole_again) == 1 and len(whole_again[0].wrenches) == len(rows)


@pytest.mark.parametrize("camera_clock", ["host", "camera"])
def test_tracked_poses_stand_at_their_images_exposure_when_it_is_on_the_hosts_clock(tmp_path, camera_clock):
    """A cube sliding 1 mm per 50 ms, each pose published 45 ms after its image's exposure (the tracker's latency),
    the exposure at a wrench's stamp: with exposures on the host's clock (the sim camera's) each wrench gets the
    pose of its own instant; with a camera's own clock (ms since its stream began) the poses keep their publishing
    stamps, and each wrench gets the pose exposed one step before it (published 5 ms before the wrench)."""
    start, count = 1_000_000_000, 8
    bubble = np.r_[0.0, 0.0, 0.1, 1.0, 0.0, 0.0, 0.0]
    objects = np.stack([np.r_[0.001 * k, 0.0, 0.025, 1.0, 0.0, 0.0, 0.0] for k in range(count)])
    messages = []
    for k in range(count):
        at = start + k * STEP_NS
        exposure = at if camera_clock == "host" else 33_000_000 + k * STEP_NS
        messages.append(("object_pose/object", msg.ObjectPose(
            seq=k + 1, stamp_ns=at + 45_000_000, source="tag_tracker", object="cube", pose=objects[k],
            tags_used=(0,), quality=1.0, hw_stamp_ns=exposure)))
        messages.append((f"wrench/{ARM}", msg.Wrench(seq=k + 1, stamp_ns=at, source=f"ft_reader-{ARM}", sensor=ARM,
                                                     wrench=np.zeros(6), tared=True)))
        messages.append((f"arm_state/{ARM}", arm_state(k, at + 3_000_000, bubble)))
    path = tmp_path / "sliding.mcap"
    messages.sort(key=lambda topic_message: topic_message[1].stamp_ns)
    log_messages(path, messages)
    read = read_stack_recording(path, period_s=0.0)
    if camera_clock == "host":
        assert read.at_exposure and read.kept == count and read.dropped == 0
        np.testing.assert_array_equal(read.trajectory.object_poses, objects)
    else:
        assert not read.at_exposure and read.kept == count - 1 and read.dropped == 1  # the first has no pose yet
        np.testing.assert_array_equal(read.trajectory.object_poses, objects[:-1])


def test_a_recording_that_starts_pressed_in_is_fitted_with_start_pressed_and_skipped_without(tmp_path):
    # as the sim scenes start: the bubble already pressed straight into the cube, the stream tared out of contact
    params, bubbles, objects, measured = synthetic_trajectories("cube", TRUTH, KINDS[:3], steps=10, seed=1)
    paths = []
    for i, p in enumerate(params):
        rows = slice(p.press_steps, None)  # from the end of the press on: no sample out of contact
        paths.append(tmp_path / f"pressed-{i}.mcap")
        record(paths[-1], bubbles[i, rows], objects[i, rows], measured[i, rows])
    with pytest.raises(ValueError, match="1 contact.*from the start: --start-pressed"):
        run_fit(paths[:1], "nh", ["E"], holdout=0.0, stack_options={"clamped": True})
    readers = RecordingReaders({"clamped": True, "start_pressed": True})
    _, [trajectory] = readers(paths[0])
    assert trajectory.pretared and np.linalg.norm(trajectory.wrenches[0, :3]) > 1.0  # row 0 in contact, kept as is
    assert readers.stack[str(paths[0])]["start_pressed"] == 1 and readers.stack[str(paths[0])]["skipped_in_contact"] == 0
    document = run_fit(paths, "nh", ["E", "K", "mu"], holdout=0.0, spacing=PLANT_SPACING_M, substeps=2,
                       stack_options={"clamped": True, "start_pressed": True})
    for name, true in TRUTH.items():
        assert document["parameters"][name]["value"] == pytest.approx(true, rel=0.03), name
