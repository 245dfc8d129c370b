"""Receding-horizon MPC by iterative cross-entropy + gradient descent (paper Sec. IV-E, Algorithm 1, after
Bharadhwaj et al., "Model-predictive control via cross-entropy and gradient-based optimization", 2020).

Each ``solve`` call is one time step ``h`` of Algorithm 1: sample ``B`` action sequences of ``K`` steps from a
diagonal Gaussian, improve every sequence by ``G`` Adam steps on its own rollout cost, refit the Gaussian to
the ``M`` lowest-cost sequences, return the first action of the best one (with the states its rollout passed
through: the model's prediction along the plan, at no extra cost), then shift the Gaussian and the elites one step
ahead as the warm start of the next call (where the ``B - M`` others are resampled).

The problem is given as plain differentiable functions:

- ``dynamics(state, u) -> state``: ``state`` is a tensor or a (named) tuple of tensors, each with a leading
  batch axis ``B``; ``u`` is ``(B, *action_shape)``. The batch rows must not interact (row ``b`` of the
  output depends only on row ``b`` of the inputs), so that one backward pass gives every sample's gradient.
- ``stage_cost(states, u) -> (B,)``: the summed stage costs ``sum_k l_k(x_k, u_k)`` of a rollout, ``k`` in
  ``0..K-1``, given its ``K`` states ``x_0 .. x_{K-1}`` (a list) and actions ``u (B, K, *action_shape)``: one call
  per rollout, so a cost can evaluate all steps in one batch of operations instead of ``K`` small ones.
- ``terminal_cost(state) -> (B,)``: cost ``Phi(x_K)``, called after ``stage_cost`` on the same thread.

Step sizes and spreads are fractions of the action half-range ``(high - low) / 2``, so one configuration
suits actions that mix metres and radians. An axis with ``low == high`` is held at that value.

Workers. With ``workers = W > 1`` the ``B`` samples are split into ``W`` contiguous shares, and each share's
gradient steps and final rollout run on a thread of its own, all at once (each sample's descent is its own, so
the shares meet only at the refit); sampling and the refit stay on the calling thread. With ``chunks = C > W`` the
samples are cut into ``C`` contiguous chunks instead, and each worker takes the next chunk as it finishes one (work
sharing): a worker that the machine delays takes fewer chunks, and the solve no longer waits for one fixed half. The
plan does not depend on which worker ran which chunk (every chunk runs the same arithmetic on the same shape). The rows do not interact,
so every sample's cost and gradient are what one rollout over all ``B`` gives, and so is the plan, to float
rounding. It pays where the step's kernels are too small to keep a second core busy by themselves (torch's
intra-op threads then mostly wait at each kernel's barrier): give each worker one intra-op thread
(``torch.set_num_threads(1)``). ``dynamics``, ``stage_cost`` and ``terminal_cost`` are then called from several
threads at once, so they must not keep per-call state that one share would overwrite for another.

Worker processes. Given ``processes`` (``worker_processes.WorkerProcesses``, one per worker), the shares run there
instead, each on the process's own copy of the problem: no interpreter lock or allocator is shared. Each share sends
back its sequences, their costs, and the states along its lowest-cost sequence only (``ShareResult``), which are the
returned states whenever that share holds the winner. The plan is the threads' plan (the same arithmetic per row).

Device. The solver's tensors (bounds, Gaussian, elites, samples, its random generator) live on ``device``; ``solve``
moves its start state there once, and its result stays there (the caller moves what it sends on to the CPU). A CUDA
generator draws other numbers than a CPU one from the same seed, so plans on two devices differ; on one device they
repeat. ``device_unavailable`` says why a device cannot be used here.
"""
from __future__ import annotations

import math
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Callable, NamedTuple, Protocol

import torch
from torch import Tensor
from torch.utils._pytree import tree_flatten, tree_map, tree_unflatten

State = Any
"""A tensor or a pytree (tuple, NamedTuple, dict) of tensors, each with a leading batch axis."""


def device_unavailable(device: torch.device | str) -> str | None:
    """Why torch cannot compute on ``device`` (``cpu``, ``cuda``, ``cuda:N``) on this machine, or None when it can."""
    where = torch.device(device)
    if where.type != "cuda":
        return None
    if not torch.cuda.is_available():
        return (f"CUDA is not available on this machine (torch {torch.__version__}, built with CUDA "
                f"{torch.version.cuda or 'none'})")
    if where.index is not None and where.index >= torch.cuda.device_count():
        return f"this machine has {torch.cuda.device_count()} CUDA device(s), none with index {where.index}"
    return None


def pieces(workers: int, chunks: int) -> int:
    """How many contiguous pieces a solve of ``workers`` workers cuts its samples into: ``chunks`` (``workers`` when 0),
    1 with one worker (its batch is never cut)."""
    return 1 if workers == 1 else chunks or workers


@dataclass(frozen=True)
class CemGdConfig:
    """Solver settings. ``lr``, ``init_std`` and ``min_std`` are fractions of the action half-range."""

    samples: int = 64  # B, parallel action sequences
    elites: int = 8  # M <= B, sequences that refit the Gaussian and are kept for the next call
    horizon: int = 10  # K, steps per sequence
    grad_steps: int = 2  # G, Adam steps per CEM iteration (0: pure CEM)
    cem_iterations: int = 1  # sample / descend / refit rounds per solve call
    lr: float = 0.05  # Adam step size, fraction of the half-range per step
    grad_clip: float = 100.0  # max per-sample gradient norm w.r.t. the half-range-normalized actions (cost)
    init_std: float = 0.5  # initial sampling std, fraction of the half-range
    min_std: float = 0.05  # floor of the refitted std, fraction of the half-range
    adam_betas: tuple[float, float] = (0.9, 0.999)
    adam_eps: float = 1e-8  # in cost units, like the normalized gradient
    seed: int = 0  # seed of the solver's private generator
    workers: int = 1  # W <= B, threads that each roll out a share of the samples (module docstring)
    chunks: int = 0  # C, W <= C <= B: pieces the samples are cut into, taken by whichever worker is free; 0: W

    @property
    def pieces(self) -> int:
        """How many contiguous pieces a solve cuts the samples into (``pieces``)."""
        return pieces(self.workers, self.chunks)

    def __post_init__(self) -> None:
        if not 1 <= self.elites <= self.samples:
            raise ValueError(f"need 1 <= elites <= samples, got elites={self.elites}, samples={self.samples}")
        if not 1 <= self.workers <= self.samples:
            raise ValueError(f"need 1 <= workers <= samples, got workers={self.workers}, samples={self.samples}")
        if self.chunks and not self.workers <= self.chunks <= self.samples:
            raise ValueError(f"need chunks = 0 or workers <= chunks <= samples, got chunks={self.chunks}, "
                             f"workers={self.workers}, samples={self.samples}")
        if self.horizon < 1 or self.grad_steps < 0 or self.cem_iterations < 1:
            raise ValueError("need horizon >= 1, grad_steps >= 0 and cem_iterations >= 1")
        if self.lr < 0 or self.grad_clip <= 0 or self.init_std < 0 or self.min_std < 0:
            raise ValueError("need lr >= 0, grad_clip > 0, init_std >= 0 and min_std >= 0")


class PlanResult(NamedTuple):
    """Outcome of one ``CemGd.solve`` call; tensors in the solver's dtype and device."""

    action: Tensor  # (*action_shape), first action of the best sequence, to apply now
    plan: Tensor  # (K, *action_shape), the best sequence
    cost: float  # its cost J; inf when no sample had a finite cost
    status: str  # "ok" or "no_finite_sample" (then action and plan are the rest action)
    timings: dict[str, float]  # wall s: rollout_s (forward), backward_s (gradients + Adam), cem_s; the busiest worker's
    states: list[State]  # x_1 .. x_K (batch 1) along plan, from the rollout that scored it; [] with no finite sample


class ShareResult(NamedTuple):
    """One share's part of a CEM round (``CemGd.improve``): its ``b`` improved sequences and their costs, and the
    states along its lowest-cost one, the only ones the solver may return."""

    u: Tensor  # (b, K, *action_shape), after the G Adam steps
    cost: Tensor  # (b,), each sequence's J after them (non-finite where the rollout failed)
    best: int | None  # index in the share of the lowest finite cost (first of equals); None when none is finite
    best_states: list[State]  # x_1 .. x_K (batch 1, copies) along sequence ``best``; [] when it is None
    timings: dict[str, float]  # wall s: rollout_s, backward_s


class ShareProcesses(Protocol):
    """What the solver needs of its worker processes (``worker_processes.WorkerProcesses`` is one), so that the
    worker module depends on the solver and not both ways."""

    workers: int
    assignment: list[int]  # per share of the last ``improve``, the process that ran it

    def improve(self, x0: State, shares: list[Tensor]) -> list[ShareResult]:
        """Each share ``(b_i, K, *action_shape)`` improved from ``x0`` (batch 1) by one of the processes, whichever
        is free; the results in the shares' order."""


class CemGd:
    """Cross-entropy + gradient-descent MPC over action sequences ``(K, *action_shape)`` within box bounds.

    ``action_low, action_high``: bounds ``(*action_shape)`` with ``low <= high``; every sampled, optimized
    and returned action lies within them. The "rest" action is zero projected into the bounds: it seeds
    the Gaussian mean and fills the step appended when the warm start is shifted.

    Attributes ``mean`` and ``std`` ``(K, *action_shape)`` (action units) are the Gaussian that the next
    ``solve`` samples from.

    ``processes``: worker processes (``worker_processes.WorkerProcesses`` with ``config.workers`` processes, already
    given this problem by ``set_problem``) that run the shares instead of threads (module docstring); the solver does
    not own them, so its caller stops them.
    """

    def __init__(
        self,
        dynamics: Callable[[State, Tensor], State],
        stage_cost: Callable[[list[State], Tensor], Tensor],
        terminal_cost: Callable[[State], Tensor],
        action_low: Tensor,
        action_high: Tensor,
        config: CemGdConfig = CemGdConfig(),
        dtype: torch.dtype = torch.float64,
        device: torch.device | str = "cpu",
        processes: ShareProcesses | None = None,
    ) -> None:
        self.dynamics = dynamics
        self.stage_cost = stage_cost
        self.terminal_cost = terminal_cost
        self.config = config
        self.dtype = dtype
        self.device = torch.device(device)
        self.low = torch.as_tensor(action_low, dtype=dtype, device=self.device)
        self.high = torch.as_tensor(action_high, dtype=dtype, device=self.device)
        finite = torch.isfinite(self.low).all() & torch.isfinite(self.high).all()
        if self.low.shape != self.high.shape or not bool(finite & (self.low <= self.high).all()):
            raise ValueError("action_low and action_high need the same shape, finite values and low <= high")
        self.action_shape = self.low.shape
        self._half = (self.high - self.low) / 2
        self._rest = torch.zeros_like(self.low).clamp(self.low, self.high)
        self._generator = torch.Generator(device=self.device)
        self.processes = processes
        if processes is not None and processes.workers != config.workers:
            raise ValueError(f"{processes.workers} worker processes for workers={config.workers}")
        threads = config.workers > 1 and processes is None
        self._pool = ThreadPoolExecutor(config.workers, "cem-gd") if threads else None
        self.reset()

    def reset(self) -> None:
        """Forget the warm start (Gaussian back to rest mean and ``init_std``, no elites) and reseed."""
        horizon = self.config.horizon
        self._generator.manual_seed(self.config.seed)
        self.mean = self._rest.expand(horizon, *self.action_shape).clone()
        self.std = (self.config.init_std * self._half).expand(horizon, *self.action_shape).clone()
        self._elites: Tensor | None = None  # (n <= M, K, *action_shape), already shifted

    def solve(self, x0: State) -> PlanResult:
        """Plan from the measured state ``x0`` (its tensors have batch size 1) and advance the warm start.

        Floating-point tensors of ``x0`` are cast to the solver's dtype, all of them moved to its device.
        Samples with a non-finite cost are never elites nor returned; their gradients, and any non-finite
        gradient, are zeroed. Runs with gradients enabled even when called under ``torch.no_grad()``.
        """
        cfg = self.config
        timings = {"rollout_s": 0.0, "backward_s": 0.0, "cem_s": 0.0}
        if self.processes is None:
            x0 = self.expand_state(x0, cfg.samples)
        best_cost, best_plan, best_states = math.inf, None, []
        for _ in range(cfg.cem_iterations):
            tic = self._clock()
            u = self._sample()
            timings["cem_s"] += self._clock() - tic
            if self.processes is None:
                shares, ran_on = self._map(self.improve, self._shares(x0, u))
            else:
                shares = self.processes.improve(x0, list(u.tensor_split(cfg.pieces)))
                ran_on = self.processes.assignment
            u, cost = torch.cat([share.u for share in shares]), torch.cat([share.cost for share in shares])
            busiest = _busiest_worker(shares, ran_on)
            timings["rollout_s"] += busiest["rollout_s"]
            timings["backward_s"] += busiest["backward_s"]

            tic = self._clock()
            cost = torch.where(torch.isfinite(cost), cost, math.inf)
            n_finite = int(torch.isfinite(cost).sum())
            if n_finite > 0:
                order = torch.argsort(cost, stable=True)
                lowest = cost[order[0]].item()
                if lowest < best_cost:
                    best_cost, best_plan = lowest, u[order[0]]
                    best_states = _winner_states(shares, int(order[0]))
                self._elites = u[order[: min(cfg.elites, n_finite)]]
                self.mean = self._elites.mean(0)
                self.std = self._elites.std(0, correction=0).maximum(cfg.min_std * self._half)
            timings["cem_s"] += self._clock() - tic

        if best_plan is None:
            self.reset()
            plan = self._rest.expand(cfg.horizon, *self.action_shape).clone()
            return PlanResult(plan[0].clone(), plan, math.inf, "no_finite_sample", timings, [])

        tic = self._clock()
        self._shift()
        timings["cem_s"] += self._clock() - tic
        return PlanResult(best_plan[0].clone(), best_plan, best_cost, "ok", timings, best_states)

    def expand_state(self, x0: State, batch: int) -> State:
        """Batch-1 state ``x0`` -> each tensor a ``(batch, ...)`` contiguous copy on the solver's device, floats in its
        dtype: the start of ``batch`` rollouts (all samples here, or one share in a worker process)."""

        def expand(leaf: Any) -> Any:
            if not isinstance(leaf, Tensor):
                return leaf
            leaf = leaf.to(device=self.device, dtype=self.dtype if leaf.is_floating_point() else None)
            return leaf.expand(batch, *leaf.shape[1:]).contiguous()

        return tree_map(expand, x0)

    def _sample(self) -> Tensor:
        """Kept elites followed by fresh draws from N(mean, std) clamped to the bounds: ``(B, K, *A)``."""
        kept = 0 if self._elites is None else self._elites.shape[0]
        noise = torch.randn(
            (self.config.samples - kept, *self.mean.shape),
            generator=self._generator, dtype=self.dtype, device=self.device,
        )
        fresh = (self.mean + self.std * noise).clamp(self.low, self.high)
        return fresh if self._elites is None else torch.cat([self._elites, fresh])

    def _rollout(self, x: State, u: Tensor) -> tuple[Tensor, list[State]]:
        """Total cost ``J (B,)`` of sequences ``u (B, K, *A)`` from states ``x`` (batch B), eq. 21, and the states
        ``x_1 .. x_K`` the rollout passed through."""
        states = [x]
        for k in range(u.shape[1]):
            states.append(self.dynamics(states[-1], u[:, k]))
        cost = self.stage_cost(states[:-1], u) + self.terminal_cost(states[-1])
        if cost.shape != (u.shape[0],):
            raise ValueError(f"costs must have shape (B,) = ({u.shape[0]},), got {tuple(cost.shape)}")
        return cost, states[1:]

    def improve(self, x0: State, u: Tensor) -> ShareResult:
        """One share's part of a CEM round: its ``G`` Adam steps from ``u (b, K, *A)`` and the rollout of the result,
        from ``x0`` (batch ``b``). Every sample's descent is its own, so shares need not meet until the refit. (The
        solver's worker threads call it, and ``WorkerProcesses``' processes on their own solver.)"""
        timings = {"rollout_s": 0.0, "backward_s": 0.0}
        u = self._descend(x0, u, timings)
        tic = self._clock()
        with torch.no_grad():  # grad mode is per thread: set here, on the worker
            cost, states = self._rollout(x0, u)
        timings["rollout_s"] += self._clock() - tic
        scored = torch.where(torch.isfinite(cost), cost, math.inf)  # as ``solve`` ranks them
        best = int(torch.argsort(scored, stable=True)[0]) if bool(torch.isfinite(scored).any()) else None
        best_states = [] if best is None else [
            tree_map(lambda t: t[best:best + 1].clone() if isinstance(t, Tensor) else t, state) for state in states]
        return ShareResult(u, cost, best, best_states, timings)

    def _shares(self, x: State, u: Tensor) -> list[tuple[State, Tensor]]:
        """The batch ``(x, u)`` as ``config.pieces`` contiguous shares (one share, unsplit, with one worker)."""
        pieces = self.config.pieces
        if pieces == 1:
            return [(x, u)]
        leaves, spec = tree_flatten(x)
        cut = [leaf.tensor_split(pieces) if isinstance(leaf, Tensor) else [leaf] * pieces for leaf in leaves]
        return [(tree_unflatten([parts[i] for parts in cut], spec), piece)
                for i, piece in enumerate(u.tensor_split(pieces))]

    def _map(self, fn: Callable[..., Any], items: list[tuple]) -> tuple[list, list[int]]:
        """``fn(*item)`` for each item, on the worker threads when there are several (each takes the next item as it
        finishes one); the results in order, and the identity of the thread that ran each."""
        if self._pool is None:
            return [fn(*item) for item in items], [threading.get_ident()] * len(items)
        ran = list(self._pool.map(lambda item: (fn(*item), threading.get_ident()), items))
        return [result for result, _ in ran], [thread for _, thread in ran]

    def _descend(self, x0: State, u: Tensor, timings: dict[str, float]) -> Tensor:
        """``G`` Adam steps on each sample's own cost, in half-range-normalized coordinates, kept in bounds.

        The per-sample gradient is taken w.r.t. ``z = u / half``; a sample whose cost or gradient is not
        finite gets a zero gradient, and each sample's gradient norm is clipped to ``grad_clip``.
        """
        cfg = self.config
        beta1, beta2 = cfg.adam_betas
        step = cfg.lr * self._half
        per_sample = (-1,) + (1,) * (u.dim() - 1)
        m = torch.zeros_like(u)
        v = torch.zeros_like(u)
        for i in range(1, cfg.grad_steps + 1):
            tic = self._clock()
            with torch.enable_grad():
                leaf = u.detach().requires_grad_(True)
                cost, _ = self._rollout(x0, leaf)
                timings["rollout_s"] += self._clock() - tic
                tic = self._clock()
                finite = torch.isfinite(cost)
                (grad,) = torch.autograd.grad(torch.where(finite, cost, 0.0).sum(), leaf)
            grad = grad * self._half
            ok = finite & torch.isfinite(grad).flatten(1).all(1)
            grad = torch.where(ok.view(per_sample), grad, 0.0)
            norm = grad.flatten(1).norm(dim=1).clamp_min(torch.finfo(self.dtype).tiny)
            grad = grad * (cfg.grad_clip / norm).clamp(max=1.0).view(per_sample)
            m.lerp_(grad, 1 - beta1)
            v.lerp_(grad.square(), 1 - beta2)
            m_hat = m / (1 - beta1**i)
            v_hat = v / (1 - beta2**i)
            u = (u - step * m_hat / (v_hat.sqrt() + cfg.adam_eps)).clamp(self.low, self.high)
            timings["backward_s"] += self._clock() - tic
        return u

    def _shift(self) -> None:
        """Advance the warm start one step: drop step 0 of mean, std and elites, append the rest action."""
        tail = self._rest.unsqueeze(0)
        self.mean = torch.cat([self.mean[1:], tail])
        self.std = torch.cat([self.std[1:], (self.config.init_std * self._half).unsqueeze(0)])
        kept = self._elites.shape[0]
        self._elites = torch.cat([self._elites[:, 1:], tail.expand(kept, *tail.shape)], dim=1)

    def _clock(self) -> float:
        """Wall time (s), after waiting for queued CUDA work so that the phases are timed correctly."""
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        return time.perf_counter()


def _busiest_worker(shares: list[ShareResult], ran_on: list[int]) -> dict[str, float]:
    """The ``rollout_s`` and ``backward_s`` of the worker that computed longest, each summed over the shares it ran
    (``ran_on``: the worker of each share): the solve waits for that one."""
    per_worker: dict[int, dict[str, float]] = {}
    for share, worker in zip(shares, ran_on, strict=True):
        total = per_worker.setdefault(worker, {"rollout_s": 0.0, "backward_s": 0.0})
        for key in total:
            total[key] += share.timings[key]
    return max(per_worker.values(), key=lambda t: t["rollout_s"] + t["backward_s"])


def _winner_states(shares: list[ShareResult], index: int) -> list[State]:
    """The states ``x_1 .. x_K`` of sample ``index`` of the whole batch, the lowest cost of all (first of equals): it
    is the lowest of its own share too, whose ``best_states`` are therefore its states."""
    for share in shares:
        if index < share.u.shape[0]:
            if share.best != index:
                raise RuntimeError(f"the lowest-cost sample {index} is not its share's lowest ({share.best})")
            return share.best_states
        index -= share.u.shape[0]
    raise IndexError("sample index past the shares")
