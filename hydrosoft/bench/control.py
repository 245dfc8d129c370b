"""``hydrosoft-stack bench control``: open- and closed-loop MPC error per task and planner model (paper Table III,
simulation rows), and the closed-loop replanning rate.

For each task and planner contact model, ``--goals`` seeded goals (goal ``g`` is ``Task.sample_goal(g)``) are
run open loop (one solve over the whole episode, then executed) and closed loop (one solve per control step
from the tactile state estimate) on each plant of ``--plants`` (``hydrosoft.tasks.evaluation``): ``finer``, an NH
model at half the planner's spacing and time step, and ``same``, the planner's own model and resolution (the
paper's simulation setting), so that the table separates what model mismatch costs from what the controller
achieves. ``--plant`` picks the finer plant's contact model, ``--pose-noise-mm``, ``--pose-noise-deg``,
``--deformation-noise-mm`` the seeded sensor noise. Reported per (plant, task, model, loop): the final ADD error in
mm (mean and sample std over goals), the mean solve time in ms (and its split into rollout, backward and CEM), the
success rate (final ADD <= the task's threshold), the statuses and the episode lengths (``Task.episode_steps``).

Settings. Full (default): planner surface spacing 8.4 mm (216 points on the 5 cm cube; pruning keeps the 132
that can touch a body in pushing and rotation), B = 64 samples, 8 elites, horizon K = 10, G = 2 gradient steps,
4 CEM rounds for the open-loop solve, 10 goals. ``--quick``: spacing 12.5 mm (96 points), B = 16, 4 elites, K = 6,
G = 1, 3 open-loop rounds, 2 goals, replanning rate from 3 solves. The small planner makes each solve cheap, not
the run short: with the default tasks, models and plants it is 96 episodes (CI runs pieces of it with ``--steps 1``
or 2, ``tests/bench``).
The replanning rate is always measured with the full planner (B = 64, K = 10, G = 2, 132 active points, 3
sub-steps) on closed-loop planar pushing, once per ``--rate-dtypes`` entry, ``--rate-sdf-solver-steps`` entry
(the bubble's closest-point solve converged, or in a fixed number of steps) and ``--rate-workers`` entry (the
solver's threads, each rolling out a share of the samples) and ``--rate-object-updates`` entry (the planner
model's object update, explicit or linearly implicit: ``PlannerSettings.object_update``; ``--object-update`` sets the
episodes') in the same run: the first solve is
reported apart (``first_solve_ms``: a warm-up, and with ``--compile`` the compilation unless an episode planner
of the same shapes compiled the step before), then the mean of the timed solves (``solve_ms``, ``rate_hz``; each
a closed-loop cycle: state estimate, solve and prediction, ``replanning_rate``) and its rollout / backward / CEM
split.

``--compile`` (``PlannerSettings.compile``) runs the planner's step through ``torch.compile`` (inductor, C++
wrapper): the first solve of each new planner shape compiles four sub-step graphs (with and without gradients,
each for a rollout's first step and for the later ones) and the backward graphs, one to three minutes on one
thread; after that a full-planner pushing solve takes ~0.24 s (float64, 1 thread). With ``--compile`` each task
and model first runs an untimed one-step closed-loop episode that compiles its planner, so the reported solve
times are steady-state ones.

Run times (single thread). ``--quick``: 96 episodes of 20-56 control steps (3,336 in all, half of them closed
loop, a solve each), about 40 minutes of one core: its first 10 episodes (pushing) took 184 s of CPU, and the
rolling and PF episodes cost more (docs/benchmarks.md). It once took 3.5 min, with half the episodes (one plant),
fixed 20-40 step episodes (1,440 steps) and rolling at 2 sub-steps. The full setting with ``--compile``, two
processes sharing 2 cores: rolling 50 min, the other three tasks 41 min (NH and PFF, docs/results-table3.md). Run
tasks as separate processes (``--tasks pushing`` ...) to use both cores.

GPU. ``--device cuda`` (or ``cuda:N``) measures the replanning rate with the planner's model, step, costs and solver
on that GPU (the plant and its observation stay on the CPU; the state estimate moves to the GPU once per solve, the
action back), ``--rate-samples 64,1024`` with the paper's B = 64 samples and 16 times more in the same run: the
measurement a lab with a GPU runs (docs/lab-setup.md). The episodes stay on the CPU, and with ``--compile`` their
planner compiles for the CPU before the rate's compiles for the GPU: ``--rate-only`` runs no episodes (no table rows,
no figures), only the rate. On CUDA the rows give the most
GPU memory the solves held (``gpu_memory_mib``), and no ``step_forward_ms``/``cost_forward_ms`` (a call returns
before its kernels end). Worker processes take no ``--device``.

``--episodes FILE`` makes a run resumable (``hydrosoft.bench.episode_log``): each finished episode is appended
to FILE as one JSON line, and a later run with the same FILE and settings reuses those episodes and runs only the
rest, so a table of many hours can be run in pieces (stopped with Ctrl-C, on several machines, across days).
Each row then also reports ``episodes_wall_s``, its episodes' own wall times, and ``settings.episodes`` says how
many were reused and at which commits they ran. ``--goal-indices 5,6,7`` runs only those goals (in that order),
so one cell's goals can be split over processes (each with its own FILE, concatenated afterwards); its rows then
cover only those goals, and a last run over all goals with the concatenated FILE prints the whole table.

Torch runs single-threaded by default (``--threads``): on 2 shared cores the OpenMP intra-op threads stall
behind other processes (a B = 64 step took 250 ms with 2 threads and 22 ms with 1).

Output: a table laid out like Table III (stdout), or with ``--json`` exactly one JSON document
``{"rows": [...], "replanning": [{...} per --rate-dtypes] or null, "settings": {...}}``; one PNG per task in ``--out`` (final error per goal,
open vs closed loop, per model); progress on stderr.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

TASK_TITLES = {
    "pushing": "Planar Pushing",
    "rotation": "Planar Rotation",
    "rolling": "Rolling",
    "in_hand": "In-hand Rotation",
}
MODEL_TITLES = {"nh": "Non-holonomic", "snh": "Smoothed NH", "pf": "Pressure Field", "pff": "PF Frictionless",
                "nh_pressure_normal": "NH, pressure normal"}
FULL = {"spacing": 0.0084, "samples": 64, "elites": 8, "horizon": 10, "grad_steps": 2, "open_loop_iterations": 4,
        "goals": 10, "rate_solves": 5}
QUICK = {"spacing": 0.0125, "samples": 16, "elites": 4, "horizon": 6, "grad_steps": 1, "open_loop_iterations": 3,
         "goals": 2, "rate_solves": 3}


def _csv(text: str) -> list[str]:
    return [part.strip() for part in text.split(",") if part.strip()]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Register the benchmark's options on ``parser``."""
    parser.add_argument("--tasks", type=_csv, default=list(TASK_TITLES), metavar="T1,T2",
                        help="tasks: pushing,rotation,rolling,in_hand (default all)")
    parser.add_argument("--models", type=_csv, default=["nh", "pf", "pff"], metavar="M1,M2",
                        help="planner contact models: nh,snh,pf,pff,nh_pressure_normal (default nh,pf,pff)")
    parser.add_argument("--loops", type=_csv, default=["open", "closed"], metavar="L1,L2",
                        help="open,closed (default both)")
    parser.add_argument("--goals", type=int, default=None, help="seeded goals per task (default 10, quick 2)")
    parser.add_argument("--quick", action="store_true",
                        help="small planner (B = 16, K = 6, G = 1) and 2 goals: 96 episodes with the default tasks, "
                             "models and plants, about 40 min of one core; split it with --tasks over processes")
    parser.add_argument("--json", action="store_true", help="print exactly one JSON document instead of the table")
    parser.add_argument("--out", type=Path, default=Path("out/bench-control"), help="folder for the PNGs")
    parser.add_argument("--plant", default="nh", help="the finer plant's contact model, or 'same' as the planner (default nh)")
    parser.add_argument("--plants", type=_csv, default=["finer", "same"], metavar="P1,P2",
                        help="plant settings: finer (half the planner's spacing and step), same (the planner's own "
                             "model); default both")
    parser.add_argument("--same-models", type=_csv, default=None, metavar="M1,M2",
                        help="planner models that also run on the 'same' plant (default: every --models entry)")
    parser.add_argument("--steps", type=int, default=None, help="control steps per episode (default: the task's)")
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads (default 1)")
    parser.add_argument("--pose-noise-mm", type=float, default=0.0,
                        help="std of the observed object position noise, mm per axis (default 0)")
    parser.add_argument("--pose-noise-deg", type=float, default=0.0,
                        help="std of the observed object orientation noise, deg per axis (default 0)")
    parser.add_argument("--deformation-noise-mm", type=float, default=0.0,
                        help="std of the observed membrane deformation noise at contact, mm per axis (default 0)")
    parser.add_argument("--compile", action="store_true",
                        help="planner step through torch.compile (PlannerSettings.compile): the first solve of "
                             "each task and model compiles, about a minute per signature pair on a CPU")
    parser.add_argument("--rate-only", action="store_true",
                        help="measure only the replanning rate: no episodes, no table rows, no figures (the GPU "
                             "measurement: --device cuda --compile --rate-only compiles on the GPU alone)")
    parser.add_argument("--rate-solves", type=int, default=None,
                        help="closed-loop pushing solves timed for the replanning rate with the full planner "
                             "(default 5, quick 3; 0 skips it)")
    parser.add_argument("--rate-dtypes", type=_csv, default=["float64", "float32"], metavar="D1,D2",
                        help="planner float types whose replanning rate is measured, in one run so that their "
                             "ratio holds (default float64,float32; the episodes plan in float64)")
    parser.add_argument("--rate-sdf-solver-steps", type=_csv, default=None, metavar="S1,S2",
                        help="the planner's bubble ellipsoid solve for the replanning rate, one measurement each in "
                             "the same run: 'converged' or a fixed step count (default: --sdf-solver-steps)")
    parser.add_argument("--rate-workers", type=_csv, default=["1"], metavar="W1,W2",
                        help="solver worker threads for the replanning rate (each rolls out a share of the 64 "
                             "samples; PlannerSettings.workers), one measurement each in the same run (default 1); "
                             "give each worker one torch thread: --threads 1")
    parser.add_argument("--rate-worker-kinds", type=_csv, default=["threads"], metavar="threads,processes",
                        help="where the --rate-workers shares run: threads of the planner's process, or processes "
                             "of their own (control.WorkerProcesses, each with its own copy of the step, compiled "
                             "there); one measurement each (default threads)")
    parser.add_argument("--rate-chunks", type=_csv, default=["0"], metavar="C1,C2",
                        help="with two --rate-workers or more: the pieces the samples are cut into, each taken by "
                             "whichever worker is free (PlannerSettings.chunks; 0: one per worker, the default), "
                             "one measurement each in the same run")
    parser.add_argument("--rate-activation-budgets", type=_csv, default=["0"], metavar="B1,B2",
                        help="with --compile: the compiled step's activation_memory_budget for the replanning rate "
                             "(0: the backward recomputes the forward's intermediates, the default; 1: torch's "
                             "default saving), one measurement each in the same run")
    parser.add_argument("--rate-costs", type=_csv, default=["compiled"], metavar="C1,C2",
                        help="with --compile: the planner's costs for the replanning rate, 'compiled' (the default, "
                             "as the planner runs them) or 'eager', one measurement each in the same run")
    parser.add_argument("--device", default="cpu",
                        help="where the replanning rate's planner computes: cpu (default), cuda or cuda:N; the "
                             "episodes and the plant stay on the CPU")
    parser.add_argument("--rate-samples", type=_csv, default=["64"], metavar="B1,B2",
                        help="sample counts B for the replanning rate, one measurement each in the same run "
                             "(default 64, the paper's; 64,1024 for B and 16 B)")
    parser.add_argument("--object-update", default="explicit",
                        help="the episode planners' object update (PlannerSettings.object_update): explicit, "
                             "sub-stepped as the scene needs (default), or linearly_implicit, one sub-step per "
                             "control step (NH and SNH planners only)")
    parser.add_argument("--rate-object-updates", type=_csv, default=None, metavar="U1,U2",
                        help="the planner's object update for the replanning rate, one measurement each in the "
                             "same run: explicit, linearly_implicit (default: --object-update)")
    parser.add_argument("--episodes", type=Path, default=None, metavar="FILE",
                        help="append each finished episode to FILE (JSON lines) and reuse the episodes already in "
                             "it that ran with the same settings: a long run can stop and resume")
    parser.add_argument("--goal-indices", type=_csv, default=None, metavar="G1,G2",
                        help="run only these goal indices, in this order (each below --goals): split one cell's "
                             "goals over processes, each with its own --episodes file")
    parser.add_argument("--sdf-solver-steps", type=int, default=None, metavar="N",
                        help="the planner's bubble ellipsoid in N fixed solver steps (PlannerSettings."
                             "sdf_solver_steps; 2-3 are exact to rounding near the membrane) instead of solving "
                             "to convergence; the plants always converge")


def _log(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def mean_and_std(values: list[float]) -> tuple[float, float]:
    """Mean and sample standard deviation (0 for one value)."""
    return statistics.fmean(values), statistics.stdev(values) if len(values) > 1 else 0.0


def _row(plant: str, task: str, model: str, loop: str, results: list) -> dict:
    errors = [r.error_mm for r in results]
    mean, std = mean_and_std(errors)
    statuses: dict[str, int] = {}
    for r in results:
        statuses[r.status] = statuses.get(r.status, 0) + 1
    per_solve = lambda key: 1e3 * sum(getattr(r, key) for r in results) / len(results)  # noqa: E731
    return {
        "plant": plant, "task": task, "model": model, "loop": loop,
        "error_mm_mean": mean, "error_mm_std": std,
        "solve_ms": per_solve("solve_s"), "rollout_ms": per_solve("rollout_s"),
        "backward_ms": per_solve("backward_s"), "cem_ms": per_solve("cem_s"),
        "success_rate": sum(r.success for r in results) / len(results), "goals": len(results),
        "position_mm_mean": mean_and_std([r.position_mm for r in results])[0],
        "angle_deg_mean": mean_and_std([r.angle_deg for r in results])[0],
        "initial_error_mm_mean": mean_and_std([r.initial_error_mm for r in results])[0],
        "statuses": statuses, "errors_mm": errors, "steps": [len(r.errors_mm) - 1 for r in results],
    }


def replanning_rate(solves: int, compile: bool = False, dtype: str = "float64",
                    sdf_solver_steps: int | None = None, workers: int = 1,
                    activation_budget: float = 0.0, object_update: str = "explicit", compiled_costs: bool = True,
                    worker_kind: str = "threads", device: str = "cpu", samples: int = 64, chunks: int = 0) -> dict:
    """Closed-loop planar pushing with the full planner (B = ``samples``, 64 by default, K = 10, G = 2, 216 surface
    points of which the
    132 that can touch a body are kept, each against its one body) in ``dtype``: the
    first solve (a warm-up; with ``compile`` it also compiles the step, reported as ``first_solve_ms``), with
    several workers a second warm-up solve (``warmup_solves_ms`` lists both: a worker's compiled copy of the step
    that did not run a graph in the first solve, because the other worker's copy ran it alone, compiles it the first
    time both need it at once, measured at 19 s in the second solve), then the mean of ``solves`` timed solves
    (``solve_ms``, ms; their median and slowest too) split into rollout / backward / CEM, and the replanning
    rate (Hz) it allows, and how much of a solve the forward calls of the step (``step_forward_ms``: compiled
    sub-steps and the stability checks) and of the stage and terminal costs (``cost_forward_ms``) take, summed over
    the workers' threads; the backward passes through both are in ``backward_ms``. ``sdf_solver_steps``: the
    planner's bubble ellipsoid solve; ``workers``: the solver's threads, each rolling out a share of the samples
    (both ``PlannerSettings``); ``chunks``: the pieces the samples are cut into, each taken by whichever worker is free
    (``PlannerSettings.chunks``; the result says how many a solve used: 1 with one worker); ``activation_budget``: the compiled step's ``activation_memory_budget``;
    ``object_update``: the planner model's (``PlannerSettings.object_update``); ``compiled_costs``: with ``compile``,
    the costs through the setup's compiled cost terms (as the planner runs them) or eager; ``preloaded``: the
    process's ``LD_PRELOAD`` (the allocator ``hydrosoft-stack`` preloads, ``hydrosoft.services.bus.allocator``), or None.

    After the warm-up solves the process's garbage collector is settled
    (``garbage_collection.settle_garbage_collector``), and its worker processes', as the stack's planner does once it
    has compiled. A timed
    solve is one cycle of the closed loop, as ``evaluation.run_episode`` runs it: the state estimate from the
    plant's sensors and the planner's prediction of this instant (``observed_state``; ``estimate_ms``), the solve,
    and the prediction of the applied action for the next estimate (``predict_ms``: taken from the solve's own
    rollout of its plan, ``PlanResult.states``, it costs next to nothing; an eager step took 4.7 ms). Only the first
    estimate, with no prediction yet, presses the bodies in from contact-free (``dynamics.press_in``). The costs'
    drift is anchored at the plant's initial state, as an episode's is (and the stack's, at the state its goal
    started from), through the setup's cost terms (compiled with ``compile``). ``plan_costs``: each timed solve's
    plan cost ``J``, in order, so that two settings' plans can be compared along the same loop. ``worker_kind``:
    ``threads`` or ``processes`` (``PlannerSettings.worker_processes``); with processes the step and cost calls run
    there, and ``step_forward_ms`` and ``cost_forward_ms`` are None. ``device``: where the planner's model, step,
    costs and solver compute (``on_device``; threads only); on CUDA ``step_forward_ms`` and ``cost_forward_ms`` are
    None too (the calls return before their kernels end) and ``gpu_memory_mib`` is the most memory the solves
    held."""
    import torch

    from hydrosoft.tasks import make_task
    from hydrosoft.tasks.evaluation import PlannerSettings, prepare

    if worker_kind not in ("threads", "processes"):
        raise ValueError(f"worker_kind is threads or processes, got {worker_kind!r}")
    task = make_task("pushing")
    if device != "cpu" and worker_kind != "threads":
        raise ValueError(f"worker processes compute on the CPU; --device {device} takes worker threads")
    settings = PlannerSettings(model="nh", spacing=FULL["spacing"], samples=samples, elites=8, horizon=10, grad_steps=2,
                               compile=compile, dtype=getattr(torch, dtype), sdf_solver_steps=sdf_solver_steps,
                               workers=workers, chunks=chunks, object_update=object_update,
                               worker_processes=worker_kind == "processes")
    options = {"activation_memory_budget": activation_budget}
    setup = on_device(prepare(task, settings, compile_options=options), torch.device(device), options)
    if setup.planner_model.device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(setup.planner_model.device)
    try:
        return _timed_solves(setup, solves, compile, dtype, sdf_solver_steps, activation_budget, compiled_costs)
    finally:
        setup.close()


def on_device(setup, device, compile_options: dict):
    """``setup`` (``evaluation.Setup``) with the planner's model, step, costs and sensor indices on ``device`` (a
    ``torch.device``); the plant stays on the CPU. The same setup on the CPU."""
    from hydrosoft.tasks.evaluation import planner_calls

    if setup.planner_model.device == device:
        return setup
    model = setup.planner_model.to(device=device)
    dynamics, cost_terms = planner_calls(model, setup.planner, compile_options)
    return replace(setup, planner_model=model, dynamics=dynamics, cost_terms=cost_terms,
                   sensors=setup.sensors.to(device))


def observed_state_on_device(setup, prediction):
    """``evaluation.observed_state`` for a planner on any device: the plant observes on the CPU, and its observation
    moves to the planner's device once (``on_device``)."""
    import torch

    from hydrosoft.tactile import TactileObservation, estimate_state

    model, cpu = setup.planner_model, torch.device("cpu")
    seen = setup.plant.observe(model.points.to(cpu), setup.body_index, setup.sensors.to(cpu))
    seen = TactileObservation(*(t.to(device=model.device, dtype=model.dtype) for t in seen))
    return estimate_state(model, seen, setup.sensors, prediction)


def _timed_solves(setup, solves: int, compile: bool, dtype: str, sdf_solver_steps: int | None,
                  activation_budget: float, compiled_costs: bool) -> dict:
    """``replanning_rate``'s solves on its prepared ``setup``."""
    import msgspec
    import torch

    from hydrosoft.control import CemGd
    from hydrosoft.control.worker_processes import settle_after_compiling
    from hydrosoft.dynamics import pair_counts
    from hydrosoft.scene import build_surface
    from hydrosoft.tactile import carry_over
    from hydrosoft.tasks.base import EAGER_COST_TERMS
    from hydrosoft.tasks.evaluation import solver_processes

    task, settings = setup.task, setup.planner
    workers, kind = settings.workers, "processes" if settings.worker_processes else "threads"
    model = setup.planner_model
    device, cuda = model.device, model.device.type == "cuda"
    surface_points = build_surface(msgspec.structs.replace(task.scene.object, spacing=settings.spacing)).n_points
    pairs = sum(pair_counts(model))
    low, high = task.bounds(model.body_names, model.dtype)
    plant = setup.plant
    anchor = (plant.initial.object_pose[0].to(device),  # as run_episode's
              plant.initial.body_poses[0, setup.body_index].to(device))
    terms = setup.cost_terms if compiled_costs else EAGER_COST_TERMS
    goal = task.sample_goal(0).to(device)
    stage, terminal = task.costs(model, goal, anchor=anchor, terms=terms)
    step_calls, stage_calls, terminal_calls = Stopwatch(setup.dynamics), Stopwatch(stage), Stopwatch(terminal)
    solver = CemGd(step_calls, stage_calls, terminal_calls, low, high,
                   config=settings.config(settings.horizon, 1), dtype=model.dtype, device=device,
                   processes=solver_processes(setup, goal, anchor, eager_costs=not compiled_costs))
    warmups = 1 if workers == 1 else 2
    warmup_s, times, prediction = [], [], None
    for k in range(solves + warmups):
        for watch in (step_calls, stage_calls, terminal_calls):
            watch.seconds = 0.0
        tic = time.perf_counter()
        state = observed_state_on_device(setup, prediction)
        estimated = time.perf_counter()
        result = solver.solve(state)
        solved = time.perf_counter()
        prediction = carry_over(result.states, 1)
        wall = time.perf_counter() - tic
        setup.plant.apply(torch.zeros(setup.plant.model.n_bodies, 6, dtype=torch.float64).index_copy(
            0, setup.body_index, result.action.to("cpu", torch.float64)))  # the solver's output, to the plant
        if k < warmups:
            warmup_s.append(wall)
            if k == warmups - 1:
                settle_after_compiling(solver.processes)
        else:
            times.append({**result.timings, "solve_s": wall, "step_s": step_calls.seconds,
                          "cost_s": stage_calls.seconds + terminal_calls.seconds, "estimate_s": estimated - tic,
                          "predict_s": wall - (solved - tic), "plan_cost": result.cost})
        _log(f"[rate] {device}, B = {settings.samples}, {dtype}, {workers} worker {kind}, {settings.object_update} object update, solve {k}"
             f"{' (warm-up)' if k < warmups else ''}: {1e3 * wall:.0f} ms")
    mean = {key: sum(t[key] for t in times) / len(times) for key in times[0]}
    compiled = getattr(setup.dynamics, "compiled", False)
    return {
        "task": "pushing", "dtype": dtype, "samples": settings.samples, "device": str(device),
        "gpu_memory_mib": torch.cuda.max_memory_allocated(device) / 2**20 if cuda else None, "horizon": 10, "grad_steps": 2,
        "surface_points": surface_points, "points": model.n_points, "pairs": pairs, "substeps": model.substeps,
        "sdf_solver_steps": sdf_solver_steps, "solves": solves, "compiled": compiled,
        "first_solve_ms": 1e3 * warmup_s[0], "warmup_solves_ms": [1e3 * t for t in warmup_s],
        "median_solve_ms": 1e3 * statistics.median(t["solve_s"] for t in times),
        "slowest_solve_ms": 1e3 * max(t["solve_s"] for t in times),
        "solve_ms": 1e3 * mean["solve_s"], "rate_hz": 1.0 / mean["solve_s"], "rollout_ms": 1e3 * mean["rollout_s"],
        "backward_ms": 1e3 * mean["backward_s"], "cem_ms": 1e3 * mean["cem_s"], "threads": torch.get_num_threads(),
        "preloaded": os.environ.get("LD_PRELOAD") or None, "workers": workers, "worker_kind": kind,
        "chunks": settings.config(settings.horizon, 1).pieces,
        "activation_budget": activation_budget if compile else None, "object_update": settings.object_update,
        "compiled_costs": compiled and compiled_costs,
        "step_forward_ms": None if settings.worker_processes or cuda else 1e3 * mean["step_s"],
        "cost_forward_ms": None if settings.worker_processes or cuda else 1e3 * mean["cost_s"],
        "estimate_ms": 1e3 * mean["estimate_s"], "predict_ms": 1e3 * mean["predict_s"],
        "plan_costs": [t["plan_cost"] for t in times],
    }


def _device_problem(device: str) -> str | None:
    """Why ``device`` (``--device``) cannot run here, or None."""
    import torch

    from hydrosoft.control import device_unavailable

    try:
        torch.device(device)
    except (RuntimeError, ValueError):
        return "not a torch device (cpu, cuda or cuda:N)"
    return device_unavailable(device)


def _gpu_memory(row: dict) -> str:
    """`` (N MiB of GPU memory at most)`` of a replanning row on CUDA, or nothing."""
    return "" if row["gpu_memory_mib"] is None else f" ({row['gpu_memory_mib']:.0f} MiB of GPU memory at most)"


def _call_split(row: dict) -> str:
    """`` (step calls X, cost calls Y)`` of a replanning row, or nothing where they ran in worker processes."""
    if row["step_forward_ms"] is None:
        return ""
    return f" (step calls {row['step_forward_ms']:.0f}, cost calls {row['cost_forward_ms']:.0f})"


class Stopwatch:
    """A callable that calls ``fn`` and adds the wall seconds of its calls to ``seconds`` (from any thread; summed
    over the threads that call it at once)."""

    def __init__(self, fn) -> None:
        self.fn, self.seconds, self._lock = fn, 0.0, threading.Lock()

    def __call__(self, *args):
        tic = time.perf_counter()
        try:
            return self.fn(*args)
        finally:
            elapsed = time.perf_counter() - tic
            with self._lock:
                self.seconds += elapsed


def _table(rows: list[dict], models: list[str]) -> str:
    """Table III layout per plant: one line per task; per model OL mean, std and CL mean, std (mm)."""
    return "\n\n".join(f"plant: {plant}\n" + _plant_table([r for r in rows if r["plant"] == plant], models)
                       for plant in dict.fromkeys(r["plant"] for r in rows))


def _plant_table(rows: list[dict], models: list[str]) -> str:
    """One plant's rows in Table III's layout."""
    index = {(r["task"], r["model"], r["loop"]): r for r in rows}
    tasks = [t for t in TASK_TITLES if any(r["task"] == t for r in rows)]
    width = 31
    head1 = f"{'Task':<18}" + "".join(f"| {MODEL_TITLES.get(m, m):^{width - 2}} " for m in models)
    head2 = f"{'':<18}" + "".join(f"| {'OL Error [mm]':^14} {'CL Error [mm]':^14} " for _ in models)
    head3 = f"{'':<18}" + "".join(f"| {'Mean':>7}{'Std':>7} {'Mean':>7}{'Std':>7} " for _ in models)
    lines = [head1, head2, head3, "-" * len(head3)]

    def cell(task: str, model: str, loop: str, key: str) -> str:
        """One figure, 3 significant digits, in 7 characters: the widest (0.0123) keeps a space before it."""
        row = index.get((task, model, loop))
        return f"{row[key]:>7.3g}" if row else f"{'-':>7}"

    for task in tasks:
        line = f"{TASK_TITLES[task]:<18}"
        for m in models:
            line += (f"| {cell(task, m, 'open', 'error_mm_mean')}{cell(task, m, 'open', 'error_mm_std')} "
                     f"{cell(task, m, 'closed', 'error_mm_mean')}{cell(task, m, 'closed', 'error_mm_std')} ")
        lines.append(line)
    lines += ["", f"{'task':<10}{'model':<6}{'loop':<8}{'solve ms':>9}{'rollout':>9}{'backward':>9}{'cem':>6}"
                  f"{'success':>9}  statuses"]
    for r in rows:
        lines.append(f"{r['task']:<10}{r['model']:<6}{r['loop']:<8}{r['solve_ms']:>9.1f}{r['rollout_ms']:>9.1f}"
                     f"{r['backward_ms']:>9.1f}{r['cem_ms']:>6.1f}{r['success_rate']:>9.0%}  "
                     + ", ".join(f"{k} {v}" for k, v in sorted(r["statuses"].items())))
    return "\n".join(lines)


def _plot(rows: list[dict], task: str, out: Path) -> Path:
    """PNG of the final error per goal, open vs closed loop, one panel per model."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    task_rows = [r for r in rows if r["task"] == task and r["plant"] == rows[0]["plant"]]
    models = list(dict.fromkeys(r["model"] for r in task_rows))
    fig, axes = plt.subplots(1, len(models), figsize=(4 * len(models), 3.2), squeeze=False, sharey=True)
    for ax, model in zip(axes[0], models):
        for offset, loop in ((-0.2, "open"), (0.2, "closed")):
            row = next((r for r in task_rows if r["model"] == model and r["loop"] == loop), None)
            if row:
                ax.bar([g + offset for g in range(len(row["errors_mm"]))], row["errors_mm"], width=0.4,
                       label=f"{loop} loop")
        ax.set_xticks(range(max((len(r["errors_mm"]) for r in task_rows), default=0)))
        ax.set_title(MODEL_TITLES.get(model, model))
        ax.set_xlabel("goal")
        ax.legend(fontsize=8)
    axes[0][0].set_ylabel("final ADD error [mm]")
    fig.suptitle(TASK_TITLES[task])
    fig.tight_layout()
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{task}.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def run(args: argparse.Namespace) -> int:
    """Run the benchmark; returns the process exit status (2 for a bad option)."""
    import torch

    from hydrosoft.bench.episode_log import EpisodeLog
    from hydrosoft.dynamics import LINEARLY_IMPLICIT_CONTACTS, OBJECT_UPDATES
    from hydrosoft.tasks import TASKS, make_task
    from hydrosoft.tasks.evaluation import PlannerSettings, PlantSettings, prepare, run_episode

    bad = ([t for t in args.tasks if t not in TASKS] + [m for m in args.models if m not in MODEL_TITLES]
           + [loop for loop in args.loops if loop not in ("open", "closed")]
           + [p for p in args.plants if p not in ("finer", "same")]
           + [d for d in args.rate_dtypes if d not in ("float64", "float32")]
           + [c for c in args.rate_costs if c not in ("compiled", "eager")])
    if bad or args.plant not in (*MODEL_TITLES, "same"):
        _log(f"bench control: unknown task, model, loop, rate dtype, rate costs or plant: "
             f"{', '.join(bad) or args.plant}")
        return 2
    try:
        rate_sdf = ([args.sdf_solver_steps] if args.rate_sdf_solver_steps is None else
                    [None if text == "converged" else int(text) for text in args.rate_sdf_solver_steps])
    except ValueError:
        _log(f"bench control: --rate-sdf-solver-steps takes 'converged' or step counts, got "
             f"{','.join(args.rate_sdf_solver_steps)!r}")
        return 2
    if not all(text.isdigit() and int(text) >= 1 for text in args.rate_workers):
        _log(f"bench control: --rate-workers takes positive counts, got {','.join(args.rate_workers)!r}")
        return 2
    if not all(text.isdigit() for text in args.rate_chunks):
        _log(f"bench control: --rate-chunks takes counts (0: one per worker), got {','.join(args.rate_chunks)!r}")
        return 2
    if not set(args.rate_worker_kinds) <= {"threads", "processes"}:
        _log(f"bench control: --rate-worker-kinds takes threads and processes, got "
             f"{','.join(args.rate_worker_kinds)!r}")
        return 2
    try:
        budgets = [float(text) for text in args.rate_activation_budgets]
        budgets_ok = all(0.0 <= budget <= 1.0 for budget in budgets)
    except ValueError:
        budgets_ok = False
    if not budgets_ok:
        _log(f"bench control: --rate-activation-budgets takes numbers from 0 to 1, got "
             f"{','.join(args.rate_activation_budgets)!r}")
        return 2
    rate_updates = [args.object_update] if args.rate_object_updates is None else args.rate_object_updates
    if not {args.object_update, *rate_updates} <= set(OBJECT_UPDATES):
        _log(f"bench control: --object-update and --rate-object-updates take {', '.join(OBJECT_UPDATES)}, got "
             f"{args.object_update!r} and {','.join(rate_updates)!r}")
        return 2
    if args.object_update != "explicit" and not set(args.models) <= set(LINEARLY_IMPLICIT_CONTACTS):
        _log(f"bench control: --object-update {args.object_update} needs NH or SNH planners, got models "
             f"{','.join(args.models)}")
        return 2
    problem = _device_problem(args.device)
    if problem is not None:
        _log(f"bench control: --device {args.device}: {problem}")
        return 2
    if args.device != "cpu" and "processes" in args.rate_worker_kinds:
        _log(f"bench control: --device {args.device} takes worker threads only (--rate-worker-kinds threads)")
        return 2
    if not all(text.isdigit() and int(text) >= 8 for text in args.rate_samples):
        _log(f"bench control: --rate-samples takes counts of at least 8 (the elites), got "
             f"{','.join(args.rate_samples)!r}")
        return 2
    torch.set_num_threads(args.threads)
    preset = QUICK if args.quick else FULL
    goals = args.goals if args.goals is not None else preset["goals"]
    try:
        indices = list(range(goals)) if args.goal_indices is None else [int(g) for g in args.goal_indices]
    except ValueError:
        indices = []
    if args.goal_indices is not None and (not indices or any(not 0 <= g < goals for g in indices)
                                          or len(set(indices)) < len(indices)):
        _log(f"bench control: --goal-indices must be distinct integers from 0 to {goals - 1} (--goals {goals}), "
             f"got {','.join(args.goal_indices or [])!r}")
        return 2
    rate_solves = args.rate_solves if args.rate_solves is not None else preset["rate_solves"]
    started = time.perf_counter()
    rows = []
    same_models = args.models if args.same_models is None else args.same_models
    runs = [] if args.rate_only else [(plant, model) for model in args.models for plant in args.plants
                                      if plant != "same" or model in same_models]
    noise = {"pose_noise_m": args.pose_noise_mm / 1e3, "pose_noise_rad": math.radians(args.pose_noise_deg),
             "deformation_noise_m": args.deformation_noise_mm / 1e3}
    planner_keys = ("spacing", "samples", "elites", "horizon", "grad_steps", "open_loop_iterations")
    log = None
    if args.episodes is not None:
        log = EpisodeLog(args.episodes, {**{k: preset[k] for k in planner_keys}, "compile": args.compile,
                                         "sdf_solver_steps": args.sdf_solver_steps, "steps": args.steps,
                                         "plant": args.plant, "noise": noise,
                                         # only when not the default, so that logs from before the option still match
                                         **({"object_update": args.object_update}
                                            if args.object_update != "explicit" else {})})
        _log(f"bench control: {len(log.episodes)} episodes with these settings in {args.episodes}"
             + (f" ({log.other_settings} lines of other settings and {log.malformed} malformed lines not used)"
                if log.other_settings or log.malformed else ""))
    total = len(runs) * len(args.tasks) * len(args.loops) * len(indices)
    done = reused = 0
    for name in args.tasks:
        task = make_task(name, args.steps)
        for model in args.models:
            planner = PlannerSettings(model=model, compile=args.compile, sdf_solver_steps=args.sdf_solver_steps,
                                      object_update=args.object_update, **{k: preset[k] for k in planner_keys})
            plants = {"finer": PlantSettings(model=model if args.plant == "same" else args.plant, **noise),
                      "same": replace(PlantSettings.same_as_planner(model), **noise)}
            compiled = None
            for plant_name in [plant for plant, m in runs if m == model]:
                keys = [(plant_name, name, model, loop, g) for loop in args.loops for g in indices]
                setup = None
                if log is None or any(log.get(key) is None for key in keys):
                    setup = prepare(task, planner, plants[plant_name])
                    if compiled is not None:  # one compiled planner step and costs per task and model, for all plants
                        setup = replace(setup, dynamics=compiled[0], cost_terms=compiled[1])
                    elif args.compile:  # compile outside the timed episodes: a one-step closed-loop warm-up
                        run_episode(setup, task.sample_goal(0), "closed", steps=1)
                        compiled = setup.dynamics, setup.cost_terms
                for loop in args.loops:
                    results, walls = [], []
                    for g in indices:
                        key = (plant_name, name, model, loop, g)
                        logged = log.get(key) if log is not None else None
                        if logged is None:
                            tic = time.perf_counter()
                            result = run_episode(setup, task.sample_goal(g), loop, steps=args.steps)
                            wall = time.perf_counter() - tic
                            if log is not None:
                                log.append(key, result, wall)
                        else:
                            result, wall = logged.result, logged.wall_s
                            reused += 1
                        results.append(result)
                        walls.append(wall)
                        done += 1
                        _log(f"[{done}/{total}] {plant_name} {name} {model} {loop} goal {g}: "
                             f"{result.initial_error_mm:.1f} -> {result.error_mm:.2f} mm ({result.status}, "
                             f"{len(result.errors_mm) - 1} steps), {wall:.1f} s" + (" (logged)" if logged else ""))
                    rows.append({**_row(plant_name, name, model, loop, results), "episodes_wall_s": sum(walls)})
    replanning = [replanning_rate(rate_solves, args.compile, dtype, sdf, int(workers), budget, update,
                                  costs == "compiled", kind, args.device, int(samples), int(chunks))
                  for samples in args.rate_samples
                  for costs in (args.rate_costs if args.compile else ["eager"]) for update in rate_updates
                  for budget in (budgets if args.compile else budgets[:1]) for kind in args.rate_worker_kinds
                  for workers in args.rate_workers for chunks in args.rate_chunks for sdf in rate_sdf
                  for dtype in args.rate_dtypes] if rate_solves > 0 else None
    pngs = [] if args.rate_only else [str(_plot(rows, name, args.out)) for name in args.tasks]
    settings = {**preset, "goals": goals, "goal_indices": indices, "quick": args.quick, "plant": args.plant,
                "plants": args.plants, "same_models": same_models,
                "threads": args.threads,
                "compile": args.compile, "sdf_solver_steps": args.sdf_solver_steps,
                "object_update": args.object_update,
                "noise": {"pose_mm": args.pose_noise_mm, "pose_deg": args.pose_noise_deg,
                          "deformation_mm": args.deformation_noise_mm},
                "steps": {name: make_task(name, args.steps).steps for name in args.tasks},
                "wall_s": time.perf_counter() - started, "pngs": pngs,
                "episodes": None if log is None else {
                    "file": str(args.episodes), "reused": reused, "ran": done - reused,
                    "other_settings": log.other_settings, "malformed": log.malformed,
                    "commits": log.commits([(p, t, m, loop, g) for p, m in runs for t in args.tasks
                                            for loop in args.loops for g in indices])}}
    if args.json:
        print(json.dumps({"rows": rows, "replanning": replanning, "settings": settings}))
    else:
        if not args.rate_only:
            print(_table(rows, args.models))
        for r in replanning or []:
            mode = "compiled" if r["compiled"] else "eager"
            compiling = ", compiling the step unless a planner of the same shapes did before" if r["compiled"] else ""
            sdf = "converged" if r["sdf_solver_steps"] is None else f"in {r['sdf_solver_steps']} solver steps"
            budget = "" if r["activation_budget"] is None else f"activation budget {r['activation_budget']:g}, "
            costs = "compiled costs, " if r["compiled_costs"] else ""
            print(f"\nreplanning rate on {r['device']}{_gpu_memory(r)}, closed-loop planar pushing, {r['dtype']}, "
                  f"B={r['samples']}, K={r['horizon']}, "
                  f"G={r['grad_steps']}, {r['surface_points']} surface points ({r['points']} active, {r['pairs']} "
                  f"point-body pairs), {r['substeps']} sub-steps, bubble SDF {sdf}, {r['threads']} thread(s), "
                  f"{'LD_PRELOAD ' + r['preloaded'] if r['preloaded'] else 'system malloc'}, "
                  f"{r['workers']} solver worker(s) ({r['worker_kind']}), the samples in {r['chunks']} chunk(s), "
                  f"{r['object_update']} object update, "
                  f"{budget}{costs}"
                  f"{mode}: {r['rate_hz']:.2f} Hz ({r['solve_ms']:.0f} ms per solve, mean of {r['solves']}: rollout "
                  f"{r['rollout_ms']:.0f}{_call_split(r)}, backward {r['backward_ms']:.0f}, cem {r['cem_ms']:.1f}, "
                  f"state estimate {r['estimate_ms']:.1f}, prediction {r['predict_ms']:.1f} ms; median "
                  f"{r['median_solve_ms']:.0f} ms, slowest {r['slowest_solve_ms']:.0f} ms; plan costs "
                  f"{', '.join(f'{c:.4g}' for c in r['plan_costs'])}; warm-up solves "
                  f"{', '.join(f'{t / 1e3:.1f}' for t in r['warmup_solves_ms'])} s{compiling})")
        print(f"\n{total} episodes in {settings['wall_s']:.0f} s"
              + (f" ({reused} of them reused from {args.episodes}; the episodes' own wall times add up to "
                 f"{sum(r['episodes_wall_s'] for r in rows):.0f} s)" if log is not None else "")
              + f"; figures: {', '.join(pngs)}")
    return 0
