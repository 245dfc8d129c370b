"""Worker processes for ``CemGd``: each share of the samples descends and rolls out in a process of its own.

The solver's worker threads split the samples but share one interpreter: with the compiled step, each thread held
the interpreter lock about half the wall time, and memory allocation and the lock kept two B = 32 shares at
0.7-0.9 of the speed each has alone (docs/decisions.md, "the solver's shares may run in worker processes,
and a faster `malloc` is preloaded"). Processes share nothing, so each runs its share at
its own speed; the price is a copy of the problem per process (its model, compiled step and costs, built there from
a picklable description) and a few hundred microseconds of messages per solve.

``WorkerProcesses(build, workers, ...)`` starts ``workers`` processes: fresh interpreters that import this module and
serve (``python -c "from hydrosoft.control.worker_processes import serve_fd; serve_fd(FD)"``; run as ``-m`` it was
imported twice, and runpy warned of it), each talking to its parent over a socket pair. (A fork of a process that
runs torch's threads is unsafe, and multiprocessing's ``spawn`` re-imports the parent's main script, which a script
without a ``__main__`` guard cannot survive.) Each starts in a session of its own: where the kernel schedules each
session as one group (Linux's autogroup, on by default in Ubuntu's kernels), a worker then competes with the other
programs as a program of its own, and its niceness can be set against theirs (a group's niceness,
``/proc/PID/autogroup``); in its parent's group the two workers shared one program's share, and their niceness
counted only against their parent's threads. ``set_problem(problem)`` has each call ``build(problem) -> (dynamics,
stage_cost, terminal_cost)`` and keep a ``CemGd`` of its own on it (one worker, the parent's bounds, dtype and
settings), as for a new goal; ``build`` must be a module-level function and ``problem`` picklable, and ``build`` may
keep what does not change between problems (the model and its compiled step). ``improve(x0, shares)`` shares the
work: it sends the batch-1 start state and one share (a chunk) of the sequences to each process, whose solver's
``improve`` runs it, then gives the next share to whichever process answers first, until every share is done, and
returns their ``ShareResult``s in the shares' order. With more shares than processes, a process that the machine
delays takes fewer of them, and the solve no longer ends with the later of two fixed halves. Which process ran which
share (``assignment``) does not change a result: each runs the same compiled step on the same shape. The first
``improve`` compiles, in every process at once (or, with a precompiled directory
set in the parent's environment, which they inherit, loads the step and costs from their files:
``compilation.use_precompiled``). Messages are pickled with the standard pickler and sent as bytes through the sockets,
the per-solve tensors as NumPy arrays (multiprocessing's own pickler would move each tensor through a shared-memory
file, slower for a few kilobytes).

A worker's compiled parts (the problem's step and costs, when they are ``compilation.FallsBack``) may fall back to
eager in the worker, where the parent would not see it: each ``improve`` answer says which of them run eager and
why, which the parent keeps in ``fallbacks`` (worker index -> reason) and reports once through ``on_fallback``. Each
answer also carries the worker's count of precompiled functions (``compilation.PRECOMPILED``: loaded, built, traced
instead), summed over the workers by ``precompiled()``, so that the parent can say whether its workers loaded their
step and costs whole or traced them.

``settle()`` has each process settle its garbage collector (``garbage_collection.settle_garbage_collector``): call it
once the solves that compile are done (the planner's start-up does), so that the first settle, which walks the
compiler's half a million objects, falls on no goal.

A worker's error is raised in the parent as ``WorkerError`` with the worker's message; a worker that dies, or does
not answer within ``timeout_s``, raises it too, and ``close`` (also on garbage collection and at exit) stops all
of them. A worker exits by itself when its socket closes, so none outlives its parent, even one killed.
"""
from __future__ import annotations

import gc
import pickle
import socket
import subprocess
import sys
import traceback
import weakref
from collections import Counter
from collections.abc import Callable
from dataclasses import replace
from multiprocessing.connection import Connection, wait
from typing import Any

import numpy as np
import torch
from torch import Tensor
from torch.utils._pytree import tree_map

from hydrosoft.compilation import PRECOMPILED
from hydrosoft.garbage_collection import settle_garbage_collector
from hydrosoft.control.cem_gd import CemGd, CemGdConfig, ShareResult

Problem = tuple[Callable, Callable, Callable]
"""``(dynamics, stage_cost, terminal_cost)`` as ``CemGd`` takes them."""


STDERR_FD = 2
"""Where a worker's standard output goes: the parent's standard error, so that nothing a worker prints can land in a
command's output (``bench control --json`` writes its document there)."""


class WorkerError(RuntimeError):
    """A worker process failed, died or did not answer in time."""


def _to_numpy(tree: Any) -> Any:
    return tree_map(lambda t: t.detach().cpu().numpy() if isinstance(t, Tensor) else t, tree)


def _to_torch(tree: Any, device: torch.device) -> Any:
    return tree_map(lambda a: torch.from_numpy(a).to(device) if isinstance(a, np.ndarray) else a, tree)


class WorkerProcesses:
    """``workers`` processes that each improve one share of ``CemGd``'s samples (module docstring).

    ``low, high``: the action bounds, ``config``: the solver's settings and ``dtype`` its float type (each process's
    own solver has them, with one worker); ``threads``: torch's intra-op threads per process; ``timeout_s``: how long
    to wait for a process to start (build and compile) and for each answer. ``device``: where each process's solver
    computes (its ``build`` puts the problem's model there too); the per-solve messages between the processes are
    NumPy arrays, so the states and sequences cross on the CPU and each side moves them to its own device once.
    ``fallbacks``: for each process whose compiled parts fell back to eager, which and why (``on_fallback(index,
    reason)`` is called when one first does).
    """

    def __init__(self, build: Callable[[Any], Problem], workers: int, low: Tensor, high: Tensor,
                 config: CemGdConfig, dtype: torch.dtype, threads: int = 1, timeout_s: float = 900.0,
                 device: torch.device | str = "cpu") -> None:
        if getattr(build, "__module__", "__main__") == "__main__":
            raise ValueError(f"build {build!r} must be importable by its module's name, not defined in __main__ (a "
                             f"worker process runs another main module)")
        self.workers = workers
        self.timeout_s = timeout_s
        self.fallbacks: dict[int, str] = {}
        self._precompiled: dict[int, dict[str, int]] = {}  # worker index -> its PRECOMPILED at its last answer
        self.assignment: list[int] = []  # per share of the last ``improve``, the index of the process that ran it
        self.on_fallback: Callable[[int, str], None] | None = None
        self._pipes: list[Connection] = []
        self._processes: list[subprocess.Popen] = []
        self._finalizer = weakref.finalize(self, _stop, self._pipes, self._processes)
        solver = (build, low.cpu().numpy(), high.cpu().numpy(), replace(config, workers=1, chunks=0), dtype, threads,
                  str(device))
        for _ in range(workers):
            ours, theirs = socket.socketpair()
            with theirs:
                self._processes.append(subprocess.Popen(
                    [sys.executable, "-c", f"from {__name__} import serve_fd; serve_fd({theirs.fileno()})"],
                    pass_fds=[theirs.fileno()], stdout=STDERR_FD, start_new_session=True))
            self._pipes.append(Connection(ours.detach()))
        self._broadcast("start", [solver] * workers)

    @property
    def pids(self) -> list[int]:
        """The worker processes' pids."""
        return [process.pid for process in self._processes]

    def precompiled(self) -> Counter:
        """The worker processes' precompiled functions (``compilation.PRECOMPILED``: ``loaded``, ``built``, ``jit``),
        summed, as of each one's last ``improve`` answer."""
        return sum(map(Counter, self._precompiled.values()), Counter())

    def set_problem(self, problem: Any) -> None:
        """Rebuild every process's problem from ``problem`` (``build(problem)``), as for a new goal."""
        self._broadcast("problem", [problem] * self.workers)

    def settle(self) -> list[int]:
        """Have each process settle its garbage collector (``settle_garbage_collector``): how many objects each one
        froze (``gc.get_freeze_count``'s growth; the first settle freezes the compiler's objects, later ones little)."""
        return self._broadcast("settle", [None] * self.workers)

    def improve(self, x0: Any, shares: list[Tensor]) -> list[ShareResult]:
        """Each share ``(b_i, K, *A)`` improved from ``x0`` (batch 1) by whichever process is free (module
        docstring): their ``ShareResult``s, in the shares' order. ``assignment`` then says which process ran each."""
        start = _to_numpy(x0)
        results: list = [None] * len(shares)
        assignment = [-1] * len(shares)
        busy: dict[int, int] = {}  # worker index -> the share it runs
        waiting = iter(range(len(shares)))

        def give(index: int) -> None:
            share = next(waiting, None)
            if share is not None:
                busy[index], assignment[share] = share, index
                self._send(index, "improve", (start, shares[share].cpu().numpy()))

        for index in range(min(self.workers, len(shares))):
            give(index)
        while busy:
            index = self._first_answer(list(busy), "improve")
            answer = self._answer(index, "improve")
            results[busy.pop(index)] = answer
            give(index)
        self.assignment = assignment
        for index, (*_, eager, precompiled) in zip(assignment, results):
            self._precompiled[index] = precompiled
            if eager and self.fallbacks.get(index) != eager:
                self.fallbacks[index] = eager
                if self.on_fallback is not None:
                    self.on_fallback(index, eager)
        return [ShareResult(torch.from_numpy(u).to(share), torch.from_numpy(cost).to(share.device), best,
                            _to_torch(states, share.device), timings)
                for (u, cost, best, states, timings, _, _), share in zip(results, shares)]

    def close(self) -> None:
        """Stop the processes (their pipes close; any still running after 5 s is killed)."""
        self._finalizer()

    def _broadcast(self, kind: str, payloads: list) -> list:
        """Send ``(kind, payload)`` to each process, then gather each one's answer, in order. Any error, death or
        timeout stops them all and raises ``WorkerError``."""
        for index, payload in enumerate(payloads):
            self._send(index, kind, payload)
        return [self._answer(index, kind) for index in range(self.workers)]

    def _send(self, index: int, kind: str, payload: Any) -> None:
        """Send ``(kind, payload)`` to process ``index`` (``WorkerError`` if it died)."""
        try:
            self._pipes[index].send_bytes(pickle.dumps((kind, payload), protocol=pickle.HIGHEST_PROTOCOL))
        except (BrokenPipeError, OSError) as err:
            self._fail(index, kind, f"it died ({err})")

    def _first_answer(self, indices: list[int], kind: str) -> int:
        """The first of processes ``indices`` with an answer ready, within ``timeout_s`` (else ``WorkerError``)."""
        ready = wait([self._pipes[index] for index in indices], self.timeout_s)
        if not ready:
            self._fail(indices[0], kind, f"no answer within {self.timeout_s:g} s")
        return next(index for index in indices if self._pipes[index] in ready)

    def _answer(self, index: int, kind: str) -> Any:
        """Process ``index``'s answer to its ``kind`` message, within ``timeout_s``; an error, its death or no
        answer stops them all and raises ``WorkerError``."""
        pipe = self._pipes[index]
        try:
            ready = pipe.poll(self.timeout_s)
            status, answer = pickle.loads(pipe.recv_bytes()) if ready else ("timeout", None)
        except (EOFError, OSError):
            status, answer = "died", None
        if status != "ok":
            self._fail(index, kind, {"timeout": f"no answer within {self.timeout_s:g} s",
                                     "died": "it died"}.get(status, answer))
        return answer

    def _fail(self, index: int, kind: str, detail: str) -> None:
        """Stop every process, then raise ``WorkerError`` for process ``index``'s failure at message ``kind``."""
        self.close()
        raise WorkerError(f"solver worker process {index} failed at {kind}: {detail} (exit codes "
                          f"{self._exit_codes()})")

    def _exit_codes(self) -> list[int | None]:
        return [process.poll() for process in self._processes]


def _stop(pipes: list[Connection], processes: list[subprocess.Popen]) -> None:
    for pipe in pipes:
        pipe.close()
    for process in processes:
        try:
            process.wait(5.0)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(5.0)


PART_NAMES = ("step", "stage cost", "terminal cost")
"""The problem's parts, as ``build`` returns them."""


def eager_parts(parts: Problem) -> str:
    """Which of a problem's compiled parts (``compilation.FallsBack``) fell back to eager, and why: '' when none
    did (plain functions are eager by design and not named). The planner names its own parts with it too."""
    return "; ".join(f"{name}: {part.fallback_reason}" for name, part in zip(PART_NAMES, parts)
                     if getattr(part, "fallback_reason", None) is not None)


def settle_after_compiling(processes: WorkerProcesses | None) -> None:
    """Settle the garbage collector of each solver worker process in ``processes`` (``WorkerProcesses.settle``; None:
    a solver without processes) and then of this process (``settle_garbage_collector``): once the solves that compile
    are done, as the planner's start-up and ``bench control``'s warm-up do."""
    if processes is not None:
        processes.settle()
    settle_garbage_collector()


def _reply(pipe: Connection, message: tuple) -> None:
    pipe.send_bytes(pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL))


def _serve(pipe: Connection) -> None:
    """A worker process: take the ``start`` message, then answer ``problem``, ``improve`` and ``settle`` messages until
    the socket closes."""
    kind, (build, low, high, config, dtype, threads, device) = pickle.loads(pipe.recv_bytes())
    torch.set_num_threads(threads)

    def make(description: Any) -> tuple[CemGd, Problem]:
        parts = build(description)
        return CemGd(*parts, torch.from_numpy(low), torch.from_numpy(high), config=config, dtype=dtype,
                     device=device), parts

    cem, parts = None, ()
    _reply(pipe, ("ok", None) if kind == "start" else ("error", f"expected start, got {kind!r}"))
    while True:
        try:
            kind, payload = pickle.loads(pipe.recv_bytes())
        except (EOFError, OSError):
            return
        try:
            if kind == "problem":
                cem, parts = make(payload)
                _reply(pipe, ("ok", None))
            elif kind == "settle":
                frozen = gc.get_freeze_count()
                settle_garbage_collector()
                _reply(pipe, ("ok", gc.get_freeze_count() - frozen))
            elif kind == "improve" and cem is None:
                _reply(pipe, ("error", "improve before any problem was set (set_problem)"))
            elif kind == "improve":
                start, u = payload
                u = torch.from_numpy(u).to(cem.device)
                share = cem.improve(cem.expand_state(_to_torch(start, cem.device), u.shape[0]), u)
                _reply(pipe, ("ok", (*_to_numpy((share.u, share.cost)), share.best, _to_numpy(share.best_states),
                                  share.timings, eager_parts(parts), dict(PRECOMPILED))))
            else:
                _reply(pipe, ("error", f"unknown message {kind!r}"))
        except Exception:  # noqa: BLE001 - reported to the parent, which raises it
            _reply(pipe, ("error", traceback.format_exc()))


def serve_fd(fd: int) -> None:
    """A worker process's body: serve its parent over the socket ``fd`` until the parent stops (or interrupts it)."""
    try:
        _serve(Connection(fd))
    except (KeyboardInterrupt, EOFError, OSError):  # the parent stopped, or was interrupted with us
        pass
