"""Re-approach waypoints: up, across, down onto the object, following it, ending at the scene's pressing pose."""

import pytest
import torch

from hydrosoft.services.arm.reapproach import (
    ARRIVED_M,
    CLEARANCE_M,
    CONTACT_DEPTH_M,
    LOST_AFTER_S,
    ContactWatch,
    Reapproach,
    grasp_offset,
    in_contact,
    waypoint,
)

QUAT = [0.9238795, 0.0, 0.0, 0.3826834]  # the TCP's orientation: 45 deg about z, kept throughout
SCENE_OBJECT = torch.tensor([0.0, 0.0, 0.024, 1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
SCENE_TCP = torch.tensor([0.0, 0.0, 0.074, *QUAT], dtype=torch.float64)


def pose(x, y, z):
    return torch.tensor([x, y, z, *QUAT], dtype=torch.float64)


def object_at(x, y):
    return torch.tensor([x, y, 0.024, 1.0, 0.0, 0.0, 0.0], dtype=torch.float64)


def test_contact_needs_a_point_deeper_than_the_threshold():
    assert not in_contact(torch.zeros(1, 50))
    assert not in_contact(torch.full((1, 50), 0.9 * CONTACT_DEPTH_M))  # depth noise alone
    depths = torch.zeros(2, 50)
    depths[1, 7] = 2 * CONTACT_DEPTH_M
    assert in_contact(depths)


def test_the_waypoints_go_up_across_and_down_onto_the_object():
    offset = grasp_offset(SCENE_OBJECT, SCENE_TCP)
    torch.testing.assert_close(offset, torch.tensor([0.0, 0.0, 0.05], dtype=torch.float64))
    obj, tcp = object_at(0.03, 0.06), pose(-0.01, 0.0, 0.074)
    lift = waypoint("lift", obj, tcp, offset)
    cross = waypoint("cross", obj, tcp, offset)
    press = waypoint("press", obj, tcp, offset)
    torch.testing.assert_close(lift, pose(-0.01, 0.0, 0.074 + CLEARANCE_M))
    torch.testing.assert_close(cross, pose(0.03, 0.06, 0.074 + CLEARANCE_M))
    torch.testing.assert_close(press, pose(0.03, 0.06, 0.074))
    high = pose(-0.01, 0.0, 0.2)  # above the crossing height already: no lift, and no descent before crossing
    torch.testing.assert_close(waypoint("lift", obj, high, offset), high)
    with pytest.raises(ValueError, match="phase"):
        waypoint("hover", obj, tcp, offset)


def test_a_reapproach_passes_each_waypoint_in_turn_and_follows_a_moving_object():
    run = Reapproach(grasp_offset(SCENE_OBJECT, SCENE_TCP))
    obj, tcp = object_at(0.0, 0.06), pose(0.0, 0.0, 0.074)
    target = run.target(obj, tcp)
    assert run.phase_name == "lift"
    torch.testing.assert_close(target, pose(0.0, 0.0, 0.074 + CLEARANCE_M))
    tcp = pose(0.0, 0.0, 0.074 + CLEARANCE_M - 0.5 * ARRIVED_M)  # close enough: on to crossing
    target = run.target(obj, tcp)
    assert run.phase_name == "cross"
    torch.testing.assert_close(target, pose(0.0, 0.06, 0.074 + CLEARANCE_M))
    obj = object_at(0.01, 0.07)  # someone moves the object meanwhile: the target follows it
    tcp = pose(0.0, 0.03, 0.074 + CLEARANCE_M)
    torch.testing.assert_close(run.target(obj, tcp), pose(0.01, 0.07, 0.074 + CLEARANCE_M))
    assert run.phase_name == "cross"
    tcp = pose(0.01, 0.07, 0.074 + CLEARANCE_M)
    torch.testing.assert_close(run.target(obj, tcp), pose(0.01, 0.07, 0.074))
    assert run.phase_name == "press"
    assert run.target(obj, pose(0.01, 0.07, 0.0745)) is None  # pressed: done
    assert run.phase_name == "done"



def depths(deep: bool) -> torch.Tensor:
    """Penetration ``(1, 20)`` (m): one point 2 mm inside the membrane, or none inside."""
    values = torch.zeros(1, 20, dtype=torch.float64)
    values[0, 3] = 0.002 if deep else 0.0
    return values


def test_a_goal_plans_in_contact_waits_briefly_out_of_it_then_reapproaches():
    watch = ContactWatch(grasp_offset(SCENE_OBJECT, SCENE_TCP), allowed=2)
    assert watch.decide(depths(True), -0.3) == "plan"
    assert watch.decide(depths(False), -0.2) == "wait"
    assert watch.decide(depths(True), -0.1) == "plan"  # a passing slip: the clock starts again
    assert watch.decide(depths(False), 0.0) == "wait"
    assert watch.decide(depths(False), 0.9 * LOST_AFTER_S) == "wait"
    assert watch.decide(depths(False), LOST_AFTER_S) == "start" and watch.count == 1
    obj = object_at(0.0, 0.06)
    tcp = pose(0.0, 0.0, 0.074)
    visited = []
    for _ in range(10):  # the arm reaches each target it is sent
        assert watch.decide(depths(False), 11.0) == "approach"  # no contact yet, but a re-approach is running
        target = watch.target(obj, tcp)
        if target is None:
            break
        visited.append(target[:3].tolist())
        tcp = target
    torch.testing.assert_close(torch.tensor(visited, dtype=torch.float64), torch.tensor(
        [[0.0, 0.0, 0.074 + CLEARANCE_M], [0.0, 0.06, 0.074 + CLEARANCE_M], [0.0, 0.06, 0.074]], dtype=torch.float64))
    assert watch.reapproach is None and watch.out_of_contact_since is None
    assert watch.decide(depths(True), 12.0) == "plan"


def test_a_goal_gives_up_once_its_reapproaches_are_spent():
    watch = ContactWatch(grasp_offset(SCENE_OBJECT, SCENE_TCP), allowed=1)
    assert watch.decide(depths(False), 0.0) == "wait"
    assert watch.decide(depths(False), LOST_AFTER_S) == "start"
    target, sent = SCENE_TCP, 0
    while target is not None:  # the arm reaches each target it is sent, and the bubble is still off the object
        target, sent = watch.target(SCENE_OBJECT, target), sent + 1
    assert sent == 3  # up, then down again: from above the object, crossing is no move
    assert watch.decide(depths(False), 5.0) == "wait"
    assert watch.decide(depths(False), 6.0) == "lost" and watch.count == 1
    never = ContactWatch(grasp_offset(SCENE_OBJECT, SCENE_TCP), allowed=0)
    assert never.decide(depths(False), 0.0) == "wait"
    assert never.decide(depths(False), LOST_AFTER_S) == "lost" and never.count == 0
