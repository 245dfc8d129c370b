"""Re-approach: bring the bubble of a one-arm scene back onto an object it has lost.

Pushing, rotation and rolling act on the object only through the bubble pressed onto it, and their actions cannot
bring back a bubble that slid off: pushing's and rotation's never move it vertically, and none crosses more than a
few millimetres per step. ``ContactWatch`` tells the planner, at each tick of a goal, what to do: plan while the
bubble touches the object (some planner point deeper than ``CONTACT_DEPTH_M`` inside the membrane: ``in_contact``),
wait while it has been out of contact for less than ``LOST_AFTER_S``, and then, the object lost, drive the arm
through ``Reapproach``'s waypoints: up to ``CLEARANCE_M`` above the pressing height, across to above the object,
and down to the scene's pressing pose relative to the object (``grasp_offset``). Then it plans again from the new
contact. Past the goal's allowance of re-approaches a lost object is ``lost``: the goal fails.

Every waypoint is computed from the latest tracked object pose, so an object that moves meanwhile is followed; the
TCP keeps its orientation (the scenes press from above, so the offset is a position in the task frame, whatever
the object's yaw). Poses are task-frame ``(7,)`` ``[x, y, z, qw, qx, qy, qz]``, z up from the table, in metres.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

CONTACT_DEPTH_M = 0.5e-3  # in contact while a planner point is this deep inside a membrane (the scenes press 5-7 mm)
LOST_AFTER_S = 0.3  # out of contact this long: the object is lost (depth noise and a passing slip are not)
CLEARANCE_M = 0.02  # height above the pressing pose at which the TCP crosses to the object
ARRIVED_M = 1e-3  # a waypoint is passed once the TCP is this close to it
PHASES = ("lift", "cross", "press")

#: What a goal does on one tick (``ContactWatch.decide``): solve and send the plan; send nothing (out of contact for
#: less than ``LOST_AFTER_S``); start a re-approach; go on with the running one; give up (``allowed`` exhausted).
Decision = Literal["plan", "wait", "start", "approach", "lost"]


def in_contact(penetration: Tensor) -> bool:
    """Whether some planner point lies deeper than ``CONTACT_DEPTH_M`` inside some sensor's membrane;
    ``penetration (S, N)`` in metres (``Planner.penetration``)."""
    return bool((penetration > CONTACT_DEPTH_M).any())


def grasp_offset(object_pose: Tensor, tcp_pose: Tensor) -> Tensor:
    """``(3,)`` m: the TCP's position relative to the object's centre, task frame, for the scene's ``object_pose
    (7,)`` and the arm's ``tcp_pose (7,)`` (the pressing pose ``Reapproach`` returns to)."""
    return tcp_pose[:3] - object_pose[:3]


def waypoint(phase: str, object_pose: Tensor, tcp_pose: Tensor, offset: Tensor) -> Tensor:
    """The TCP pose ``(7,)`` that ends ``phase`` (one of ``PHASES``) for the object at ``object_pose (7,)`` and the TCP
    at ``tcp_pose (7,)``: ``lift`` straight up to the crossing height (or stay, when higher already), ``cross`` to
    above the pressing pose, ``press`` down to it (``object_pose``'s position plus ``offset (3,)``)."""
    press = object_pose[:3] + offset
    crossing_z = press[2] + CLEARANCE_M
    if phase == "lift":
        position = torch.stack([tcp_pose[0], tcp_pose[1], torch.maximum(tcp_pose[2], crossing_z)])
    elif phase == "cross":
        position = torch.stack([press[0], press[1], crossing_z])
    elif phase == "press":
        position = press
    else:
        raise ValueError(f"unknown re-approach phase {phase!r}; the phases are {', '.join(PHASES)}")
    return torch.cat([position, tcp_pose[3:]])


@dataclass
class Reapproach:
    """One re-approach in progress: ``offset (3,)`` (``grasp_offset``) and the index of the current phase."""

    offset: Tensor
    phase: int = 0

    def target(self, object_pose: Tensor, tcp_pose: Tensor) -> Tensor | None:
        """The TCP target ``(7,)`` now: the current phase's waypoint, after moving past every waypoint the TCP is
        within ``ARRIVED_M`` of; ``None`` once the TCP has arrived at the pressing pose (the re-approach is over)."""
        while self.phase < len(PHASES):
            target = waypoint(PHASES[self.phase], object_pose, tcp_pose, self.offset)
            if float(torch.linalg.vector_norm(target[:3] - tcp_pose[:3])) > ARRIVED_M:
                return target
            self.phase += 1
        return None

    @property
    def phase_name(self) -> str:
        return PHASES[self.phase] if self.phase < len(PHASES) else "done"


@dataclass
class ContactWatch:
    """One goal's contact bookkeeping. ``offset (3,)``: the pressing pose (``grasp_offset``); ``allowed``: the most
    re-approaches the goal may run; ``count``: how many it started; ``reapproach``: the running one, if any;
    ``out_of_contact_since``: when the bubble last left the object (s, the caller's clock), ``None`` in contact."""

    offset: Tensor
    allowed: int
    count: int = 0
    reapproach: Reapproach | None = None
    out_of_contact_since: float | None = None

    def decide(self, penetration: Tensor, now_s: float) -> Decision:
        """What the goal does this tick, given the planner points' depths ``penetration (S, N)`` (m) inside the
        membranes at time ``now_s`` (s); ``start`` begins a re-approach (``target`` gives its waypoints)."""
        if self.reapproach is not None:
            return "approach"
        if in_contact(penetration):
            self.out_of_contact_since = None
            return "plan"
        if self.out_of_contact_since is None:
            self.out_of_contact_since = now_s
        if now_s - self.out_of_contact_since < LOST_AFTER_S:
            return "wait"
        if self.count >= self.allowed:
            return "lost"
        self.count += 1
        self.reapproach = Reapproach(self.offset)
        return "start"

    def target(self, object_pose: Tensor, tcp_pose: Tensor) -> Tensor | None:
        """The running re-approach's TCP target ``(7,)`` (``Reapproach.target``); ``None`` once it has pressed the
        bubble onto the object again, which ends it (the next ``decide`` plans)."""
        target = self.reapproach.target(object_pose, tcp_pose)
        if target is None:
            self.reapproach = self.out_of_contact_since = None
        return target
