"""The experiment client: connect to a running stack, set a goal, start and stop it, wait for the outcome, read
status, subscribe to any topic. ``StackClient`` is async; ``BlockingClient`` wraps it for scripts.

    from hydrosoft.services.client import BlockingClient
    with BlockingClient("deploy/sim.toml") as stack:
        stack.set_goal("pushing", dx_m=0.04, tolerance_mm=5.0, timeout_s=180.0)
        stack.start()
        result = stack.wait(timeout_s=190.0)
        print(result.outcome, result.error_mm, result.solves)

``hydrosoft-stack goal TASK [--dx M] [--dy M] [--dyaw DEG] [--droll DEG] [--dpitch DEG] [--wait S] [--json]`` is
this from the command line; with ``--json`` it prints one document ``{"status", "error_mm", "elapsed_s", "solves",
"mean_solve_ms"}`` (error by the stack's own tracked pose) and in sim mode ``"true_error_mm"`` from sim_world's
``eval/object_pose``, plus ``"resumes"`` when the goal was sent again to a restarted planner and
``"reapproaches"`` when the bubble was brought back onto a lost object (``services/arm/reapproach.py``).

Goals belong to one stack launch. Every status reply names the launch (``ServiceStatus.instance``); the client
learns it from the first and stamps its goals with it (``Goal.instance``), so a planner of another launch refuses
them, and ``wait`` ends with ``StackGone`` as soon as another launch answers: a goal is never sent to another
stack. A planner that dies while a goal runs stops the arm (the commander's watchdog) and is restarted by the
launcher with no goal: ``wait`` then reports the goal ``interrupted`` (exit 1), unless ``resume`` was asked for
(``goal --resume``; off by default), which sends it again to the restarted planner of the same launch: the same
absolute target (resolved by the first Start), the rest of its timeout.

A stack that is gone is noticed within seconds, not at the end of ``--wait``: when the planner does not answer, the
launcher's pid (``RUN_DIR/launcher.lock``) is checked, and a launcher that is no longer running ends ``wait`` with
``StackGone``; without ``resume``, so does a planner silent for ``SILENT_LIMIT_S``. ``hydrosoft-stack goal`` then
prints why and exits 3.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import msgspec
import numpy as np
import torch

from hydrosoft.services.bus import messages as msg
from hydrosoft.services.bus.sockets import Bus, LatestSubscriber, RequestClient, Stale
from hydrosoft.services.bus.config import StackConfig, load_config

DEFAULT_CONFIG = "deploy/sim.toml"
CONFIG_ENV = "HYDROSOFT_CONFIG"  # the config path when --config is not given
POLL_PERIOD_S = 0.25  # s between status polls while waiting for an outcome
REQUEST_TIMEOUT_S = 3.0
#: Without ``resume``, the longest the planner may stay silent before ``wait`` gives the stack up, s (a restarted
#: planner takes longer than this to build its model, and its goal would be interrupted anyway).
SILENT_LIMIT_S = 5.0
#: The file in run_dir that holds the running launcher's pid (``commands.launch.LOCK_FILE``).
LAUNCHER_LOCK = "launcher.lock"
FINAL = ("reached", "failed", "timeout", "stopped", "interrupted")
#: Exit status of ``hydrosoft-stack goal`` when the stack is gone or was launched again.
EXIT_STACK_GONE = 3


class ClientError(RuntimeError):
    """The stack refused a request; the message says why."""


class StackGone(ClientError):
    """The stack this client set its goal on is gone (its launcher is not running, its planner silent) or was
    launched again (another instance answers); the message says which."""


def launcher_running(run_dir: str | Path) -> bool | None:
    """Whether the launcher whose pid ``RUN_DIR/launcher.lock`` holds is running: None when that cannot be told (no
    such file: the stack runs elsewhere or without a launcher)."""
    try:
        text = (Path(run_dir) / LAUNCHER_LOCK).read_text().strip()
    except OSError:
        return None
    if not text.isdigit():
        return None
    return process_running(int(text))


def process_running(pid: int) -> bool:
    """Whether process ``pid`` runs: it exists and is not a zombie (a killed launcher stays one until its parent
    reaps it; ``/proc`` tells, where there is one)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process: it exists
        pass
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()[0]
    except (OSError, IndexError):
        return True
    return state not in ("Z", "X")


@dataclass(frozen=True)
class Pursuit:
    """A goal this client started: the planner (pid) that accepted it, the goal with its target resolved to an
    absolute pose (so a resumed goal aims where the first one did, not relative to where the object is now) and its
    stack launch (``goal.instance``), and when it started (``time.monotonic()``, s)."""

    planner_pid: int
    goal: msg.Goal
    started_s: float


class StackClient:
    """An async connection to a running stack's planner (requests) and to any service's topics.

    ``resumes`` counts the goals ``wait`` re-sent to a restarted planner; ``instance`` is the stack launch this
    client talks to, learned from the first status reply (None before)."""

    def __init__(self, config: StackConfig | str | Path) -> None:
        self.config = config if isinstance(config, StackConfig) else load_config(config)
        self.bus = Bus(curve=self.config.curve_keys())
        self.requests = RequestClient(self.bus, self.config.endpoint("planner", "cmd"), source="client",
                                      timeout_s=REQUEST_TIMEOUT_S)
        self.pursuit: Pursuit | None = None
        self.resumes = 0
        self.instance: str | None = None

    def close(self) -> None:
        self.bus.close()

    async def __aenter__(self) -> StackClient:
        return self

    async def __aexit__(self, *exc_info: object) -> None:
        self.close()

    async def _command(self, request: msg.Request) -> msg.Reply:
        reply = await self.requests.request(request)
        if not reply.ok:
            raise ClientError(reply.error)
        return reply

    async def set_goal(self, task: str, *, dx_m: float = 0.0, dy_m: float = 0.0, dyaw_rad: float = 0.0,
                       droll_rad: float = 0.0, dpitch_rad: float = 0.0, target_pose: np.ndarray | None = None,
                       tolerance_mm: float = 5.0, timeout_s: float = 180.0) -> None:
        """Set the planner's goal (a displacement from the object's pose at ``start``, or an absolute pose; see
        ``messages.Goal``), for the stack launch this client talks to (a planner of another launch refuses it)."""
        if self.instance is None:
            await self.status()  # learns the launch the goal is for
        goal = msg.Goal(task=task, target_pose=target_pose, dx_m=dx_m, dy_m=dy_m, dyaw_rad=dyaw_rad,
                        droll_rad=droll_rad, dpitch_rad=dpitch_rad, tolerance_mm=tolerance_mm, timeout_s=timeout_s,
                        instance=self.instance or "")
        await self._command(msg.SetGoal(goal=goal))

    async def start(self) -> None:
        """Start pursuing the goal, and remember it (``pursuit``) so that ``wait`` can resume it."""
        await self._command(msg.Start())
        reply = await self.status()
        if reply.goal is not None and reply.goal.target_pose is not None and reply.status is not None:
            self.pursuit = Pursuit(reply.status.pid, reply.goal, time.monotonic())

    async def stop(self, reason: str = "client") -> None:
        """Stop pursuing the goal; the arm stops when the last target's deadline passes."""
        self.pursuit = None
        await self._command(msg.Stop(reason=reason))

    async def status(self) -> msg.StatusReply:
        """The planner's status: outcome, error, solves. The first reply sets ``instance``; a reply from another
        stack launch raises StackGone."""
        reply = await self._command(msg.GetStatus())
        instance = reply.status.instance if reply.status is not None else ""
        if self.instance is None:
            self.instance = instance
        elif instance != self.instance:
            raise StackGone(f"the stack was launched again (launch {instance!r} answers; this client's goal was set "
                            f"on launch {self.instance!r}): the goal is not sent to the new stack")
        return reply

    async def wait(self, timeout_s: float, resume: bool = False) -> msg.StatusReply:
        """Poll the status until the goal ends or ``timeout_s`` passes (then the last status, outcome running).

        A planner that does not answer is polled again while its launcher runs, until the deadline (which then
        raises TimeoutError); a launcher that is gone, or without ``resume`` a planner silent for
        ``SILENT_LIMIT_S``, raises StackGone at once, as does an answer from another stack launch. A goal this
        client started that a restarted planner (another pid, same launch) no longer pursues is ``interrupted``
        (the reply says so); with ``resume`` it is sent to it again, with the same absolute target and what is
        left of its timeout (``resume_goal``); the arm is stopped meanwhile by the commander's watchdog.
        """
        deadline = time.monotonic() + timeout_s
        answered_s = time.monotonic()
        while True:
            try:
                reply = await self.status()
            except TimeoutError as error:
                self._check_alive(time.monotonic() - answered_s, resume, error)
                if time.monotonic() >= deadline:
                    raise
                continue
            answered_s = time.monotonic()
            if self._lost_by_restart(reply):
                if not resume:
                    return self._interrupted(reply)
                if await self.resume_goal():
                    continue
            if reply.outcome in FINAL or time.monotonic() >= deadline:
                return reply
            await asyncio.sleep(POLL_PERIOD_S)

    def _check_alive(self, silent_s: float, resume: bool, error: TimeoutError) -> None:
        """Raise StackGone when a planner silent for ``silent_s`` s means the stack is gone: its launcher is not
        running, or (without ``resume``) it has been silent for ``SILENT_LIMIT_S``."""
        running = launcher_running(self.config.run_dir)
        if running is False:
            lock = Path(self.config.run_dir) / LAUNCHER_LOCK
            raise StackGone(f"the stack is gone: its launcher is not running ({lock} names a pid that has exited) "
                            f"and the planner did not answer ({error}); its goal was not finished") from None
        if not resume and silent_s >= SILENT_LIMIT_S:
            raise StackGone(f"the planner has not answered for {silent_s:.1f} s ({error}): the stack is gone or "
                            "the planner died (its goal is then interrupted; goal --resume waits for a restarted "
                            "planner)") from None

    def _interrupted(self, reply: msg.StatusReply) -> msg.StatusReply:
        """``reply`` of a restarted planner, as the verdict on this client's goal: ``interrupted``."""
        pid = self.pursuit.planner_pid
        self.pursuit = None
        return msgspec.structs.replace(
            reply, outcome="interrupted", outcome_reason=f"the planner restarted (pid {pid} -> {reply.status.pid}) "
                                                         "and the goal was not resumed (goal --resume)")

    def _lost_by_restart(self, reply: msg.StatusReply) -> bool:
        """Whether ``reply`` comes from a planner other than the one pursuing this client's goal, and idle."""
        return (self.pursuit is not None and reply.status is not None and not reply.running
                and reply.status.pid != self.pursuit.planner_pid)

    async def resume_goal(self) -> bool:
        """Send the pursued goal again (absolute target, the rest of its timeout) and start it. False when its
        time is up (the pursuit is then dropped) or when the planner has no fresh input yet (``NO_FRESH_INPUT``:
        restarted a moment ago, before the first pose reached it; the pursuit is kept and ``wait`` tries again at
        its next poll)."""
        pursuit = self.pursuit
        left_s = pursuit.goal.timeout_s - (time.monotonic() - pursuit.started_s)
        if left_s <= 0:
            self.pursuit = None
            return False
        goal = msgspec.structs.replace(pursuit.goal, timeout_s=left_s)
        await self._command(msg.SetGoal(goal=goal))
        try:
            await self._command(msg.Start())
        except ClientError as error:
            if str(error).startswith(msg.NO_FRESH_INPUT):
                return False
            raise
        reply = await self.status()
        self.pursuit = Pursuit(reply.status.pid, goal, time.monotonic())
        self.resumes += 1
        return True

    def subscribe(self, service: str, topics: tuple[str, ...] = ("",)) -> LatestSubscriber:
        """A latest-value subscriber to ``service``'s data topics (``await sub.wait()``, then ``sub.latest``)."""
        return LatestSubscriber(self.bus, self.config.endpoint(service), topics)


class BlockingClient:
    """``StackClient`` for plain scripts: every method blocks until done."""

    def __init__(self, config: StackConfig | str | Path) -> None:
        self._loop = asyncio.new_event_loop()
        self._client = StackClient(config)

    def __enter__(self) -> BlockingClient:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def close(self) -> None:
        self._client.close()
        self._loop.close()

    def set_goal(self, task: str, **kwargs) -> None:
        self._loop.run_until_complete(self._client.set_goal(task, **kwargs))

    def start(self) -> None:
        self._loop.run_until_complete(self._client.start())

    def stop(self, reason: str = "client") -> None:
        self._loop.run_until_complete(self._client.stop(reason))

    def status(self) -> msg.StatusReply:
        return self._loop.run_until_complete(self._client.status())

    def wait(self, timeout_s: float, resume: bool = False) -> msg.StatusReply:
        return self._loop.run_until_complete(self._client.wait(timeout_s, resume))


async def true_error_mm(client: StackClient, target: np.ndarray, task: str, wait_s: float = 1.0) -> float | None:
    """The ADD error (mm) of sim_world's true object pose against ``target (7,)``, or None without sim_world."""
    from hydrosoft.scene import build_surface
    from hydrosoft.tasks import make_task
    from hydrosoft.tasks.base import mean_point_distance
    from hydrosoft.tasks.evaluation import METRIC_SPACING_M

    if client.config.mode != "sim":
        return None
    sub = client.subscribe("sim_world", ("eval/object_pose",))
    try:
        await sub.wait(wait_s)
        truth = sub.latest("eval/object_pose", max_age_s=wait_s + 1.0).value.pose
    except Stale:
        return None
    scene_object = make_task(task).scene.object
    points = build_surface(msgspec.structs.replace(scene_object, spacing=METRIC_SPACING_M)).points
    return 1e3 * float(mean_point_distance(points, torch.as_tensor(np.array(truth)), torch.as_tensor(np.array(target))))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``hydrosoft-stack goal``."""
    parser.add_argument("task", help="pushing, rotation, rolling or in_hand (the running stack's scene.task)")
    parser.add_argument("--config", default=os.environ.get(CONFIG_ENV, DEFAULT_CONFIG),
                        help=f"the running stack's config (default ${CONFIG_ENV} or {DEFAULT_CONFIG})")
    parser.add_argument("--dx", type=float, default=0.0, help="object displacement along base x, m")
    parser.add_argument("--dy", type=float, default=0.0, help="object displacement along base y, m")
    parser.add_argument("--dyaw", type=float, default=0.0, help="object rotation about base z, degrees")
    parser.add_argument("--droll", type=float, default=0.0,
                        help="object rotation about base x, degrees (in_hand: about the grasp axis)")
    parser.add_argument("--dpitch", type=float, default=0.0,
                        help="object rotation about base y, degrees (rolling: a cylinder of radius r rolled by --dx d "
                        "turns d / r rad; the sim cylinder's r is 0.025 m, so --dx 0.03 --dpitch 68.75)")
    parser.add_argument("--tolerance-mm", type=float, default=5.0, help="success when the ADD error is below (mm)")
    parser.add_argument("--timeout", type=float, default=None, help="the stack gives up after this long (s; default --wait or 180)")
    parser.add_argument("--wait", type=float, default=0.0, help="wait up to this long for the outcome (s); 0: start and return")
    parser.add_argument("--resume", action="store_true",
                        help="while waiting, send the goal again to a planner the launcher restarted (same launch "
                        "only); without it such a goal ends interrupted")
    parser.add_argument("--json", action="store_true", help="print one JSON document")


async def _goal(args: argparse.Namespace) -> dict:
    timeout_s = args.timeout if args.timeout is not None else (args.wait or 180.0)
    async with StackClient(args.config) as client:
        await client.set_goal(args.task, dx_m=args.dx, dy_m=args.dy, dyaw_rad=math.radians(args.dyaw),
                              droll_rad=math.radians(args.droll), dpitch_rad=math.radians(args.dpitch),
                              tolerance_mm=args.tolerance_mm, timeout_s=timeout_s)
        await client.start()
        reply = await (client.wait(args.wait, resume=args.resume) if args.wait > 0 else client.status())
        result = {"status": reply.outcome, "error_mm": reply.error_mm, "elapsed_s": reply.elapsed_s,
                  "solves": reply.solves, "mean_solve_ms": reply.mean_solve_ms}
        if reply.outcome_reason:
            result["reason"] = reply.outcome_reason
        if reply.reapproaches:
            result["reapproaches"] = reply.reapproaches
        if client.resumes:
            result["resumes"] = client.resumes
        if reply.goal is not None and reply.goal.target_pose is not None:
            true = await true_error_mm(client, reply.goal.target_pose, args.task)
            if true is not None:
                result["true_error_mm"] = true
        return result


def run(args: argparse.Namespace) -> int:
    """``hydrosoft-stack goal``: exit 0 when reached (or started, without --wait), 1 otherwise, 2 when refused, 3
    when the stack is gone or was launched again (``StackGone``)."""
    try:
        result = asyncio.run(_goal(args))
    except StackGone as err:
        print(f"hydrosoft-stack goal: {err}", file=sys.stderr)
        return EXIT_STACK_GONE
    except (ClientError, TimeoutError) as err:
        print(f"hydrosoft-stack goal: {err}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(result))
    else:
        print(", ".join(f"{key} {value:.2f}" if isinstance(value, float) else f"{key} {value}"
                        for key, value in result.items()))
    return 0 if result["status"] in ("reached", "running") else 1
