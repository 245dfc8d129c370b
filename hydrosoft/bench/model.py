"""``hydrosoft-stack bench model``: step speed, memory and force accuracy of the contact models.

Eight sections; ``--json`` prints them as one document ``{"config": {...}, "rows": [...], "accuracy": [...],
"wrench": [...], "object_update": [...], "pruning": [...], "point_sets": [...], "loop_tails": [...], "drift":
[...]}``, otherwise as tables. Progress goes to stderr. Every section but ``drift`` runs by default.

``rows``: one quasi-dynamic step (``dynamics.step``) of the planar pushing scene, a Soft Bubble (ellipsoid) pressed
5 mm into a cube resting on the table (half-space): ``M = 2`` bodies, the cube's surface discretised to about
``points`` points, all kept (``compile_scene(prune=False)``, so ``N`` is what was asked for), for each contact
model (nh, snh, pf, pff, nh_pressure_normal), dtype (float32, float64), batch ``B`` and point count ``N``. The step
is timed in steady state: from a state whose signed distances are cached (every step of a rollout after the first),
with the model's ``substeps = 1`` and a random sub-millimetre bubble motion per sample.

- ``substeps``: the sub-steps that step takes: the run-time stability check (``dynamics.substeps_needed``) raises
  ``substeps = 1`` to what the current contacts need (3 for the unpruned 600-point scene). ``check_ms``: one
  such check.
- ``step_ms``: the whole forward step under ``no_grad`` (its checks and all its sub-steps);
  ``step_backward_ms``: forward plus backward of ``sum(object_pose) + sum(forces)`` of the next state with respect
  to the controls. ``substep_ms`` / ``substep_backward_ms``: the same for one sub-step alone (one contact update,
  the compiled kernel in compiled rows, no check). All are the best, over several repeats, of the mean time of a
  loop of calls; the variants of one (model, B, N) are timed interleaved.
- ``point_updates_per_s``: ``B * M * N`` per ``substep_ms`` (one contact update of every point and body). Before
  the run-time check existed a step was one sub-step; timing whole steps against one update each is how the
  figure once fell from 45.6 M to 29 M/s with the kernel unchanged.
- ``peak_mem_mb`` / ``peak_mem_backward_mb``: peak of the live torch tensor storage allocated during one
  forward step / one forward plus backward, above what existed before (``config.memory_method``; on CPU
  ``null`` for compiled rows).
- ``speedup_vs_eager_f64``: the step time of the same model in eager float64 at the same B and N, timed in
  the same run, divided by this row's step time.
- ``mode``: ``eager``, or ``compiled`` with ``--compile`` (``dynamics.CompiledStep``; ``compile_s`` is the
  wall time of its first forward and first backward call, compilation included).

``accuracy``: the net force of the bubble on the object along a prescribed press-and-shear path replayed with
``dynamics.advance_forces`` (object held, bubble lowered from 1 mm above contact to 3 mm indentation, dragged
6 mm along x, lifted off again), for coarser settings against the reference (exact NH, float64, the finest
surface and the most path steps): coarser surface spacing, fewer path steps, float32, smoothed NH for each
beta, and the path-independent PF / PFF. ``force_rel_error = max_k |F_k - F_ref,k|_2 / max_k |F_ref,k|_2`` over
the path samples the setting shares with the reference (``F``: the 3-vector net force in N); ``step_ms`` is the
mean time of one ``advance_forces`` step (B = 1) along the path.

``wrench``: the pose-to-wrench query of one primitive pair at batch 1 (``dynamics.pressure_wrenches``: signed
distances, the pressure field's normal forces, the net wrench on the bubble), the wrench benchmark's cube and R25
cylinder (``bench.wrench_scenes``, 5 mm spacing) with the Soft Bubble pressed 6 mm into each, eager and (with
``--compile``) compiled, float64 and float32: ``query_ms`` (best of the loop means), ``points``, the normal force
``force_z_n`` (N, the same in every mode), and ``compile_s`` (first call) for compiled rows. Drake's hydroelastic
query takes 0.06-0.2 ms for such pairs (``config.drake_query_ms``).

``object-update``: the explicit object update (the scene's sub-steps) against the linearly implicit one
(``Model.object_update``; one sub-step per step, and four for its convergence) on ten-step rollouts of eight samples
(float64, eager) under random actions of up to half each task's bounds: pushing, pushing with a fifth of its damping
time (``epsilon / 5``, contacts five times stiffer for the explicit update), rolling and in-hand. Reference: the
explicit update at four times the scene's sub-steps (``--quick``: the two pushing scenes). Per row:
``substeps``, ``step_ms`` (one step of the batch, best of loop means), and the largest object position error
``position_error_mm`` and rotation error ``rotation_error_mrad`` over the rollout, against the reference, beside
its largest motion ``motion_mm``.

``pruning``: step time of the compiled task scenes (pushing, rotation, rolling, in-hand) with pruning (the
default) and without (``prune=False``), float32, and the largest difference of the net contact force after
the timed step.

``point-sets``: the pushing planner's model (the full planner's 216 surface points, pruned per body to 132;
linearly implicit object update, float32), eager or (with ``--compile``) compiled, at B = 32 and 64 (``--quick``:
B = 8): one step with each body's touchable points read as a slice (``Model.point_sets``, the default wherever
they are consecutive) against the same model reading them by index (``dynamics.with_gathered_points``), timed
interleaved: ``forward_ms`` (no grad) and ``forward_backward_ms`` (forward plus backward of ``sum(object_pose) +
sum(forces)`` to the controls) of each, their ratios (slices / gathers), ``compile_s`` of each compiled variant,
and the largest force difference between the two after the step (N).

``loop-tails``: the same model and batches, always compiled: the step with ``compilation.DEFAULT_OPTIONS`` (inductor's
loop tails as scalar loops) against the same options with inductor's masked tail vectorisation
(``cpp.enable_loop_tail_vec``, its default), timed and reported as ``point-sets`` is (``scalar`` / ``masked``).
Only with ``--compile`` (it compiles both variants: minutes); without it the section is skipped with a note.

``drift``: float32 against float64 over a back-and-forth rollout of ``--drift-steps`` steps (default 100) in the
rolling scene, for NH and ``nh_pressure_normal`` (``bench.drift``): how far the object ends from its start in each
dtype, and the largest float32-float64 gap. About 50 s of CPU per 1000 steps and rollout: ``--drift-steps 1000``
takes about 4 minutes on an idle core (38 minutes on the 2-core machine under heavy load). Run only when named in
``--sections``.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import sys
import time
import weakref
from collections.abc import Callable
from typing import Any

FULL_GRID = {"models": "nh,snh,pf,pff,nh_pressure_normal", "dtypes": "float32,float64", "batches": "1,16,64,256",
             "points": "100,500,2000"}
QUICK_GRID = {"models": "nh,snh,pf,pff", "dtypes": "float32,float64", "batches": "1,64", "points": "100,500"}

SECTIONS = ("rows", "accuracy", "wrench", "object-update", "pruning", "point-sets", "loop-tails", "drift")
DEFAULT_SECTIONS = SECTIONS[:-1]  # drift runs only when named: minutes at its long lengths

# Accuracy path (metres): gap above contact at the start and end, indentation, shear travel.
GAP, DEPTH, SHEAR = 0.001, 0.003, 0.006


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``hydrosoft-stack bench model``."""
    parser.add_argument("--json", action="store_true", help="print one JSON document instead of tables")
    parser.add_argument("--quick", action="store_true",
                        help="small grid (4 models x 2 dtypes x batch 1, 64 x 100, 500 points: 32 settings) and short "
                             "paths: over 9 min of one core, its timing rows alone (measured 2026-11-27)")
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"], help="device to run on (default cpu)")
    parser.add_argument("--threads", type=int, default=None,
                        help="torch CPU threads (default: torch's own choice); reported in config")
    parser.add_argument("--compile", action="store_true",
                        help="also time the torch.compile'd step (dynamics.CompiledStep); compiling takes minutes")
    parser.add_argument("--models", default=None,
                        help="comma list of contact models (default nh,snh,pf,pff,nh_pressure_normal)")
    parser.add_argument("--dtypes", default=None, help="comma list: float32,float64 (float64 is always timed)")
    parser.add_argument("--batches", default=None, help="comma list of batch sizes (default 1,16,64,256)")
    parser.add_argument("--points", default=None, help="comma list of surface point counts (default 100,500,2000)")
    parser.add_argument("--sections", default=",".join(DEFAULT_SECTIONS),
                        help="comma list of sections to run: rows, accuracy, wrench (pose-to-wrench query), "
                             "object-update (explicit against linearly implicit), pruning, point-sets (slices against "
                             "gathers), loop-tails (compiled step: scalar against masked loop tails; runs with "
                             "--compile only), drift (float32 against float64 over a back-and-forth rollout, NH and "
                             "nh_pressure_normal); default all but drift")
    parser.add_argument("--drift-steps", type=int, default=None,
                        help="steps of the drift section's rollout (default 100: under a minute; 1000: about 4 min "
                             "on an idle core, 38 min on the 2-core machine under heavy load)")


def run(args: argparse.Namespace) -> int:
    """Run the benchmark described by ``args`` (see ``add_arguments``); returns the exit status."""
    import torch

    if args.device == "cuda" and not torch.cuda.is_available():
        print("bench model: --device cuda but no CUDA device is available", file=sys.stderr)
        return 2
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    grid = dict(QUICK_GRID if args.quick else FULL_GRID)
    for key in grid:
        if getattr(args, key, None):
            grid[key] = getattr(args, key)
    sections = set(args.sections.split(","))
    bench = _Bench(torch.device(args.device), quick=args.quick)
    unknown = sections - set(SECTIONS)
    if unknown:
        print(f"bench model: unknown section {', '.join(sorted(unknown))}; the sections are {', '.join(SECTIONS)}",
              file=sys.stderr)
        return 2
    if args.drift_steps is not None and args.drift_steps < 1:
        print(f"bench model: --drift-steps must be at least 1, got {args.drift_steps}", file=sys.stderr)
        return 2
    doc: dict[str, Any] = {"config": bench.config(grid, args.compile), "rows": [], "accuracy": [], "wrench": [],
                           "object_update": [], "pruning": [], "point_sets": [],
                           "loop_tails": [], "drift": []}
    if "rows" in sections:
        doc["rows"] = bench.rows(
            models=grid["models"].split(","),
            dtypes=grid["dtypes"].split(","),
            batches=[int(b) for b in grid["batches"].split(",")],
            points=[int(n) for n in grid["points"].split(",")],
            compiled=args.compile,
        )
    if "accuracy" in sections:
        doc["accuracy"] = bench.accuracy()
    if "wrench" in sections:
        doc["wrench"] = bench.wrench_query(compiled=args.compile)
    if "object-update" in sections:
        doc["object_update"] = bench.object_update()
    if "pruning" in sections:
        doc["pruning"] = bench.pruning()
    if "point-sets" in sections:
        doc["point_sets"] = bench.point_sets(compiled=args.compile)
    if "loop-tails" in sections:
        if args.compile:
            doc["loop_tails"] = bench.loop_tails()
        else:
            _progress("loop-tails: skipped, it times the compiled step only (add --compile)")
    if "drift" in sections:
        from hydrosoft.bench.drift import DRIFT_STEPS, drift

        doc["drift"] = drift(steps=DRIFT_STEPS if args.drift_steps is None else args.drift_steps, progress=_progress)
    if args.json:
        print(json.dumps(doc, indent=1))
    else:
        _print_tables(doc)
    return 0


def _progress(text: str) -> None:
    print(f"[bench model] {text}", file=sys.stderr, flush=True)


class _PeakLiveMemory:
    """Peak bytes of live torch tensor storage created inside the ``with`` block (any device).

    A ``TorchDispatchMode`` sees every tensor an operator returns; each storage is counted once while any tensor
    that uses it is alive (released by weakref finalizers). CPU tensors bypass ``tracemalloc``, hence this.
    """

    def __new__(cls):
        from torch.utils._python_dispatch import TorchDispatchMode
        from torch.utils._pytree import tree_flatten

        class Mode(TorchDispatchMode):
            def __init__(self):
                super().__init__()
                self.live: dict[int, list[int]] = {}
                self.current = 0
                self.peak = 0

            def _release(self, key: int) -> None:
                entry = self.live.get(key)
                if entry is not None:
                    entry[1] -= 1
                    if entry[1] == 0:
                        self.current -= entry[0]
                        del self.live[key]

            def __torch_dispatch__(self, func, types, args=(), kwargs=None):
                import torch

                out = func(*args, **(kwargs or {}))
                for t in tree_flatten(out)[0]:
                    if isinstance(t, torch.Tensor):
                        storage = t.untyped_storage()
                        key = storage.data_ptr()
                        if key == 0:
                            continue
                        if key in self.live:
                            self.live[key][1] += 1
                        else:
                            self.live[key] = [storage.nbytes(), 1]
                            self.current += storage.nbytes()
                            self.peak = max(self.peak, self.current)
                        weakref.finalize(t, self._release, key)
                return out

        return Mode()


class _Bench:
    """Builds the benchmark models and times them on one device."""

    def __init__(self, device, quick: bool) -> None:
        import torch

        self.torch = torch
        self.device = device
        self.quick = quick
        self.min_repeat_s = 0.01 if quick else 0.05
        self.repeats = 3 if quick else 5
        self._scenes: dict[tuple, tuple] = {}

    # ------------------------------------------------------------------------------------------------------
    # infrastructure

    def config(self, grid: dict[str, str], compiled: bool) -> dict[str, Any]:
        torch = self.torch
        return {
            "device": str(self.device),
            "threads": torch.get_num_threads(),
            "torch": torch.__version__,
            "quick": self.quick,
            "grid": grid,
            "compile": compiled,
            "scene": "pushing task scene: bubble ellipsoid (6 x 4.5 x 3 cm) 5 mm into a 5 cm cube on the table "
                     "half-space, M = 2 bodies, prune=False, substeps = 1",
            "drake_query_ms": [0.06, 0.2],
            "timing_method": f"best of {self.repeats} repeats of the mean over a loop of >= {self.min_repeat_s} s, "
                             "variants of one configuration interleaved",
            "memory_method": "torch.cuda.max_memory_allocated above the start" if self.device.type == "cuda"
            else "peak live torch tensor storage seen by a TorchDispatchMode (weakref-tracked), above the start; "
                 "null for compiled rows (under that mode dynamo would skip the compiled frame)",
        }

    def _sync(self) -> None:
        if self.device.type == "cuda":
            self.torch.cuda.synchronize(self.device)

    def _interleaved(self, fns: dict[str, Callable[[], Any]]) -> dict[str, float]:
        """Seconds per call of each function: best of ``repeats`` loops, the functions interleaved per repeat."""
        loops = {}
        for name, fn in fns.items():
            self._sync()
            tic = time.perf_counter()
            fn()
            self._sync()
            once = max(time.perf_counter() - tic, 1e-6)
            loops[name] = max(1, math.ceil(self.min_repeat_s / once))
        best = {name: math.inf for name in fns}
        for _ in range(self.repeats):
            for name, fn in fns.items():
                self._sync()
                tic = time.perf_counter()
                for _ in range(loops[name]):
                    fn()
                self._sync()
                best[name] = min(best[name], (time.perf_counter() - tic) / loops[name])
        return best

    def _peak_mb(self, fn: Callable[[], Any]) -> float:
        torch = self.torch
        if self.device.type == "cuda":
            self._sync()
            start = torch.cuda.memory_allocated(self.device)
            torch.cuda.reset_peak_memory_stats(self.device)
            fn()
            self._sync()
            return (torch.cuda.max_memory_allocated(self.device) - start) / 1e6
        mode = _PeakLiveMemory()
        with mode:
            fn()
        return mode.peak / 1e6

    def _scene(self, task: str, contact: str = "nh", points: int | None = None, prune: bool = True,
               params: dict | None = None):
        """``(model, state, report)`` of a task scene in float64 on the device, cached."""
        import msgspec

        from hydrosoft.scene import compile_scene
        from hydrosoft.tasks.scenes import task_scene

        key = (task, contact, points, prune, tuple(sorted((params or {}).items())))
        if key not in self._scenes:
            scene = task_scene(task)
            scene = msgspec.structs.replace(scene, contact=contact, contact_params=params or {})
            if points is not None:
                side = scene.object.params["side"]
                spacing = side * math.sqrt(6.0 / points)  # the cube's area over the point count
                scene = msgspec.structs.replace(scene, object=msgspec.structs.replace(scene.object, spacing=spacing))
            self._scenes[key] = compile_scene(scene, device=self.device, prune=prune)
        return self._scenes[key]

    @staticmethod
    def _cast(model, state, dtype):
        from hydrosoft.dynamics import State

        return model.to(dtype=dtype), State(*(t.to(dtype) for t in state[:3]))

    def _controls(self, model, batch: int, seed: int = 0):
        """Random controls ``(B, M, 6)``: sub-millimetre moves and a few mrad of yaw of the first actuated body."""
        torch = self.torch
        g = torch.Generator().manual_seed(seed)
        u = torch.zeros(batch, model.n_bodies, 6, dtype=torch.float64)
        moved = int(model.actuated.argmax())
        scale = torch.tensor([5e-4, 5e-4, 1e-4], dtype=torch.float64)
        u[:, moved, :3] = torch.randn(batch, 3, generator=g, dtype=torch.float64) * scale
        u[:, moved, 5] = 5e-3 * torch.randn(batch, generator=g, dtype=torch.float64)
        return u.to(dtype=model.dtype, device=self.device)

    def _batched(self, model, state, batch: int, u=None):
        """Steady-state batch: ``state`` (B = 1) repeated, stepped once under ``u`` (so phi is cached), and ``u``."""
        torch = self.torch
        from hydrosoft.dynamics import State, step

        state = State(
            state.object_pose.expand(batch, -1).contiguous(),
            state.body_poses.expand(batch, -1, -1).contiguous(),
            state.forces.expand(batch, -1, -1, -1).contiguous(),
        )
        u = self._controls(model, batch) if u is None else u
        with torch.no_grad():
            state = step(model, state, u)
        return state, u

    def _step_calls(self, stepper, state, u) -> tuple[Callable[[], Any], Callable[[], None]]:
        """``(forward, backward)`` to time: one step of ``stepper`` from ``state`` under ``u`` without gradients
        (returns the next state), and one forward plus backward of ``sum(object_pose) + sum(forces)`` of the next
        state with respect to the controls."""
        torch = self.torch

        def forward():
            with torch.no_grad():
                return stepper(state, u)

        def backward():
            leaf = u.detach().requires_grad_(True)
            nxt = stepper(state, leaf)
            (nxt.object_pose.sum() + nxt.forces.sum()).backward()

        return forward, backward

    # ------------------------------------------------------------------------------------------------------
    # sections

    def rows(self, models: list[str], dtypes: list[str], batches: list[int], points: list[int],
             compiled: bool) -> list[dict]:
        torch = self.torch
        from dataclasses import replace

        from hydrosoft.dynamics import CompiledStep, _substep, step

        if compiled:  # one CompiledStep per model and dtype compiles every batch size and grad mode: > 8 graphs
            torch._dynamo.config.recompile_limit = max(torch._dynamo.config.recompile_limit, 64)
        dtype_of = {"float32": torch.float32, "float64": torch.float64}
        timed_dtypes = list(dict.fromkeys([*dtypes, "float64"]))
        out = []
        for contact in models:
            for n_points in points:
                model64 = replace(self._scene("pushing", contact, n_points, prune=False)[0], substeps=1)
                variants = {}
                for name in timed_dtypes:
                    model = model64.to(dtype=dtype_of[name])
                    variants[(name, "eager")] = (model, functools.partial(step, model),
                                                 functools.partial(_substep, model))
                    if compiled:
                        stepper = CompiledStep(model)
                        variants[(name, "compiled")] = (model, stepper, stepper.compiled_substep)
                for batch in batches:
                    out.extend(self._time_config(contact, n_points, batch, variants, dtypes))
        return out

    def _time_config(self, contact: str, n_points: int, batch: int, variants: dict, dtypes: list[str]) -> list[dict]:
        torch = self.torch
        from hydrosoft.dynamics import substeps_needed

        fns, prepared, compile_s = {}, {}, {}
        for key, (model, stepper, substep) in variants.items():
            state, u = self._batched(model, self._state_for(model, contact, n_points), batch)
            prepared[key] = (model, stepper, state, u)
            dt = torch.tensor(model.dt, dtype=model.dtype, device=self.device)
            forward, backward = self._step_calls(stepper, state, u)

            def sub_forward(substep=substep, state=state, u=u, dt=dt):
                with torch.no_grad():
                    return substep(state, u, dt)

            def sub_backward(substep=substep, state=state, u=u, dt=dt):
                leaf = u.detach().requires_grad_(True)
                nxt = substep(state, leaf, dt)
                (nxt.object_pose.sum() + nxt.forces.sum()).backward()

            if key[1] == "compiled":
                tic = time.perf_counter()
                forward()
                backward()
                self._sync()
                compile_s[key] = time.perf_counter() - tic
            fns[key + ("forward",)] = forward
            fns[key + ("backward",)] = backward
            fns[key + ("sub_forward",)] = sub_forward
            fns[key + ("sub_backward",)] = sub_backward
            if key[1] == "eager":
                fns[key + ("check",)] = functools.partial(substeps_needed, model, state)
        n_real = next(iter(prepared.values()))[0].n_points
        _progress(f"rows: {contact} B={batch} N={n_real} ({', '.join('/'.join(k) for k in variants)})")
        times = self._interleaved(fns)
        reference = times[("float64", "eager", "forward")]
        rows = []
        for key, (model, stepper, state, u) in prepared.items():
            if key[0] not in dtypes:
                continue
            forward, backward = fns[key + ("forward",)], fns[key + ("backward",)]
            # Under the CPU tracking mode dynamo would give up on the compiled frame and run it eagerly for good.
            untracked = key[1] == "compiled" and self.device.type != "cuda"
            seconds = times[key + ("forward",)]
            sub_seconds = times[key + ("sub_forward",)]
            row = {
                "model": contact,
                "dtype": key[0],
                "mode": key[1],
                "batch": batch,
                "points": model.n_points,
                "bodies": model.n_bodies,
                "substeps": substeps_needed(model, state),
                "check_ms": 1e3 * times[(key[0], "eager", "check")],
                "step_ms": 1e3 * seconds,
                "step_backward_ms": 1e3 * times[key + ("backward",)],
                "substep_ms": 1e3 * sub_seconds,
                "substep_backward_ms": 1e3 * times[key + ("sub_backward",)],
                "point_updates_per_s": batch * model.n_bodies * model.n_points / sub_seconds,
                "peak_mem_mb": None if untracked else self._peak_mb(forward),
                "peak_mem_backward_mb": None if untracked else self._peak_mb(backward),
                "speedup_vs_eager_f64": reference / seconds,
            }
            if key in compile_s:
                row["compile_s"] = compile_s[key]
                row["compiled_ok"] = stepper.compiled
            rows.append(row)
        return rows

    def _state_for(self, model, contact: str, n_points: int):
        """The compiled scene's initial state (B = 1) cast to ``model``'s dtype."""
        state = self._scene("pushing", contact, n_points, prune=False)[1]
        return self._cast(model, state, model.dtype)[1]

    def _path(self, model, path_steps: int):
        """Net bubble force ``(path_steps + 1, 3)`` (N, float64) along the press-shear-release path."""
        torch = self.torch
        from hydrosoft.dynamics import State, advance_forces

        _, scene_state, _ = self._scene("pushing")
        bubble = model.body_names.index("bubble")
        rest = scene_state.body_poses.to(model.dtype)  # bubble pressed 5 mm into the cube's top face
        quarter = path_steps // 4
        s = torch.arange(path_steps + 1, dtype=model.dtype, device=self.device)
        press = (s / quarter).clamp(max=1.0) - ((s - 3 * quarter) / quarter).clamp(min=0.0)
        shear = ((s - quarter) / (2 * quarter)).clamp(0.0, 1.0)
        lift = 0.005 + GAP - (GAP + DEPTH) * press  # bubble height above its scene pose, m
        body_poses = rest.expand(path_steps + 1, -1, -1).clone()
        body_poses[:, bubble, 0] += SHEAR * shear
        body_poses[:, bubble, 2] += lift
        object_pose = scene_state.object_pose.to(model.dtype)
        state = State(object_pose, body_poses[:1], torch.zeros(1, model.n_bodies, model.n_points, 3,
                                                                dtype=model.dtype, device=self.device))
        forces = [state.forces[0, bubble].sum(0)]
        self._sync()
        tic = time.perf_counter()
        with torch.no_grad():
            for k in range(1, path_steps + 1):
                state = advance_forces(model, state, object_pose, body_poses[k:k + 1])
                forces.append(state.forces[0, bubble].sum(0))
        self._sync()
        seconds = (time.perf_counter() - tic) / path_steps
        return torch.stack(forces).double().cpu(), seconds

    def accuracy(self) -> list[dict]:
        torch = self.torch

        ref_points, ref_steps = (500, 60) if self.quick else (4000, 240)
        coarser_points = (100,) if self.quick else (2000, 500, 100)
        fewer_steps = (20, 12) if self.quick else (120, 60, 24)
        betas = (1e2, 1e4, 1e6) if self.quick else (1e2, 1e3, 1e4, 1e5, 1e6)
        settings = [("reference: nh float64", "nh", {}, ref_points, ref_steps, torch.float64)]
        settings += [(f"spacing: {n} points", "nh", {}, n, ref_steps, torch.float64) for n in coarser_points]
        settings += [(f"time step: {k} path steps", "nh", {}, ref_points, k, torch.float64) for k in fewer_steps]
        settings += [("float32", "nh", {}, ref_points, ref_steps, torch.float32)]
        settings += [(f"smoothed nh: beta {b:.0e}/m", "snh", {"beta": b}, ref_points, ref_steps, torch.float64)
                     for b in betas]
        settings += [(f"model: {m}", m, {}, ref_points, ref_steps, torch.float64)
                     for m in ("pf", "pff", "nh_pressure_normal")]
        reference = None
        out = []
        for label, contact, params, n_points, path_steps, dtype in settings:
            _progress(f"accuracy: {label}")
            model64, _, _ = self._scene("pushing", contact, n_points, prune=True, params=params)
            model = model64.to(dtype=dtype)
            forces, seconds = self._path(model, path_steps)
            if reference is None:
                reference = forces
            stride = ref_steps // path_steps
            ref = reference[::stride]
            error = float((forces - ref).norm(dim=-1).max() / ref.norm(dim=-1).max())
            out.append({
                "setting": label,
                "model": contact,
                "beta": params.get("beta"),
                "dtype": str(dtype).removeprefix("torch."),
                "points": model.n_points,
                "path_steps": path_steps,
                "force_rel_error": error,
                "peak_force_n": float(forces.norm(dim=-1).max()),
                "step_ms": 1e3 * seconds,
            })
        return out

    def wrench_query(self, compiled: bool, objects: tuple[str, ...] = ("cube", "cylinder_r25"),
                     press_m: float = 0.006) -> list[dict]:
        """Pose-to-wrench query times at batch 1 (``dynamics.pressure_wrenches``), per object, dtype and mode."""
        torch = self.torch
        from hydrosoft.bench.wrench_scenes import BUBBLE_RADII_M, SPACING_M, bench_object, start_pose, wrench_scene
        from hydrosoft.compilation import DEFAULT_OPTIONS
        from hydrosoft.dynamics import pressure_wrenches
        from hydrosoft.scene import compile_scene

        out = []
        for name in objects:
            obj = bench_object(name)
            bubble = start_pose(obj)
            bubble[2] = obj.top_z() + BUBBLE_RADII_M[2] - press_m  # its lowest point press_m deep
            scene = wrench_scene(name, "pff", SPACING_M, object_pose=obj.pose(), bubble_pose=bubble)
            model64, state, _ = compile_scene(scene, device=self.device)
            for dtype in ("float64", "float32"):
                model = model64.to(dtype=getattr(torch, dtype))
                object_pose = state.object_pose.to(model.dtype)
                body_poses = state.body_poses.to(model.dtype)
                queries = {"eager": functools.partial(pressure_wrenches, model)}
                if compiled:
                    queries["compiled"] = torch.compile(functools.partial(pressure_wrenches, model), dynamic=False,
                                                        options=dict(DEFAULT_OPTIONS))
                for mode, query in queries.items():
                    _progress(f"wrench: {name} {dtype} {mode}")
                    with torch.no_grad():
                        tic = time.perf_counter()
                        first = query(object_pose, body_poses)
                        compile_s = time.perf_counter() - tic
                        seconds = self._interleaved({mode: lambda: query(object_pose, body_poses)})[mode]
                    row = {"object": name, "points": model.n_points, "dtype": dtype, "mode": mode, "batch": 1,
                           "press_mm": 1e3 * press_m, "query_ms": 1e3 * seconds, "force_z_n": float(first[0, 0, 2])}
                    if mode == "compiled":
                        row["compile_s"] = compile_s
                    out.append(row)
        return out

    def object_update(self) -> list[dict]:
        torch = self.torch
        from dataclasses import replace

        import msgspec

        from hydrosoft.dynamics import State, step, with_object_update
        from hydrosoft.geometry import se3
        from hydrosoft.scene import compile_scene
        from hydrosoft.tasks import make_task

        batch, steps = 8, 10
        out = []
        scenes = (("pushing", 1.0), ("pushing", 0.2)) + ((("rolling", 1.0), ("in_hand", 1.0)) if not self.quick else ())
        for name, damping in scenes:
            _progress(f"object update: {name}, epsilon x {damping:g}")
            task = make_task(name)
            scene = msgspec.structs.replace(task.scene, epsilon=task.scene.epsilon * damping, max_substeps=1024)
            model, state, _ = compile_scene(scene, device=self.device)
            low, high = task.bounds(model.body_names)
            g = torch.Generator().manual_seed(0)
            u = 0.5 * (low + (high - low) * torch.rand(batch, *low.shape, generator=g, dtype=torch.float64))
            u = u.to(self.device)
            start = State(*(t.expand(batch, *t.shape[1:]).contiguous() for t in state[:3]))

            def rollout(variant, u=u, start=start):
                poses, x = [], start
                with torch.no_grad():
                    for _ in range(steps):
                        x = step(variant, x, u)
                        poses.append(x.object_pose)
                return torch.stack(poses)

            reference = rollout(replace(model, substeps=4 * model.substeps))
            implicit = with_object_update(model, "linearly_implicit")
            variants = {"explicit": model, "linearly_implicit": implicit,
                        "linearly_implicit x4": replace(implicit, substeps=4)}
            times = self._interleaved({label: functools.partial(step, variant, start, u)
                                       for label, variant in variants.items()})
            motion = (reference[..., :3] - start.object_pose[:, :3]).norm(dim=-1).max()
            for label, variant in variants.items():
                poses = rollout(variant)
                turn = se3.quat_to_matrix(reference[..., 3:]).mT @ se3.quat_to_matrix(poses[..., 3:])
                cos = ((turn.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1.0, 1.0)
                out.append({
                    "task": name, "epsilon_factor": damping, "update": label, "batch": batch,
                    "substeps": variant.substeps, "step_ms": 1e3 * times[label],
                    "position_error_mm": 1e3 * float((poses[..., :3] - reference[..., :3]).norm(dim=-1).max()),
                    "rotation_error_mrad": 1e3 * float(torch.arccos(cos).max()),
                    "motion_mm": 1e3 * float(motion),
                })
        return out

    def pruning(self) -> list[dict]:
        torch = self.torch
        from hydrosoft.dynamics import step
        from hydrosoft.tasks.scenes import TASK_SCENES

        batch = 8 if self.quick else 64
        out = []
        for task in TASK_SCENES:
            _progress(f"pruning: {task}")
            pruned, s_pruned, _ = self._scene(task, prune=True)
            full, s_full, _ = self._scene(task, prune=False)
            pruned, s_pruned = self._cast(pruned, s_pruned, torch.float32)
            full, s_full = self._cast(full, s_full, torch.float32)
            u_pruned = self._controls(pruned, batch)
            u_full = torch.zeros(batch, full.n_bodies, 6, dtype=full.dtype, device=self.device)
            for m, name in enumerate(pruned.body_names):
                u_full[:, full.body_names.index(name)] = u_pruned[:, m]
            s_pruned, _ = self._batched(pruned, s_pruned, batch, u_pruned)
            s_full, _ = self._batched(full, s_full, batch, u_full)

            def run_pruned(model=pruned, state=s_pruned, u=u_pruned):
                with torch.no_grad():
                    return step(model, state, u)

            def run_full(model=full, state=s_full, u=u_full):
                with torch.no_grad():
                    return step(model, state, u)

            times = self._interleaved({"pruned": run_pruned, "full": run_full})
            diff = (run_pruned().forces.sum((1, 2)) - run_full().forces.sum((1, 2))).abs().max()
            out.append({
                "task": task,
                "dtype": "float32",
                "batch": batch,
                "points_full": full.n_points,
                "points_pruned": pruned.n_points,
                "bodies_full": full.n_bodies,
                "bodies_pruned": pruned.n_bodies,
                "substeps": pruned.substeps,
                "step_ms_full": 1e3 * times["full"],
                "step_ms_pruned": 1e3 * times["pruned"],
                "speedup": times["full"] / times["pruned"],
                "net_force_max_diff_n": float(diff),
            })
        return out

    def _planner_model(self):
        """The pushing planner's model (the full planner's 216 surface points pruned per body to 132, linearly
        implicit object update) and its start state, float32."""
        torch = self.torch
        import msgspec

        from hydrosoft.bench.control import FULL
        from hydrosoft.dynamics import with_object_update
        from hydrosoft.scene import compile_scene
        from hydrosoft.tasks.scenes import task_scene

        scene = task_scene("pushing")
        scene = msgspec.structs.replace(scene, object=msgspec.structs.replace(scene.object, spacing=FULL["spacing"]))
        model, state, _ = compile_scene(scene, device=self.device)
        return self._cast(with_object_update(model, "linearly_implicit"), state, torch.float32)

    def _step_pair(self, section: str, variants: dict[str, tuple[Any, Callable[[], Any]]], state,
                   compiled: bool) -> list[dict]:
        """Two ways of stepping the same model timed interleaved from ``state`` at B = 32 and 64 (quick: 8).
        ``variants``: name -> (model, a function making its stepper); the first is the one under test, the ratios
        are its times over the second's."""
        from hydrosoft.dynamics import pair_counts

        (first, (model, _)), (second, _) = variants.items()
        out = []
        for batch in (8,) if self.quick else (32, 64):
            _progress(f"{section}: B={batch}{' (compiling both variants)' if compiled else ''}")
            fns, compile_s, ends = {}, {}, {}
            for name, (variant, make) in variants.items():
                forward, backward = self._step_calls(make(), *self._batched(variant, state, batch))
                tic = time.perf_counter()
                ends[name] = forward()
                backward()
                self._sync()
                compile_s[name] = time.perf_counter() - tic
                fns[(name, "forward")], fns[(name, "backward")] = forward, backward
            times = self._interleaved(fns)
            row = {"batch": batch, "dtype": "float32", "mode": "compiled" if compiled else "eager",
                   "points": model.n_points, "pairs": sum(pair_counts(model))}
            for name in variants:
                row[f"forward_ms_{name}"] = 1e3 * times[(name, "forward")]
                row[f"forward_backward_ms_{name}"] = 1e3 * times[(name, "backward")]
                if compiled:
                    row[f"compile_s_{name}"] = compile_s[name]
            row["forward_ratio"] = times[(first, "forward")] / times[(second, "forward")]
            row["forward_backward_ratio"] = times[(first, "backward")] / times[(second, "backward")]
            row["max_force_diff_n"] = float((ends[first].forces - ends[second].forces).abs().max())
            out.append(row)
        return out

    def point_sets(self, compiled: bool) -> list[dict]:
        from hydrosoft.dynamics import CompiledStep, step, with_gathered_points

        model, state = self._planner_model()

        def stepper(variant):
            return lambda: CompiledStep(variant, dynamic=False) if compiled else functools.partial(step, variant)

        gathered = with_gathered_points(model)
        variants = {"slices": (model, stepper(model)), "gathers": (gathered, stepper(gathered))}
        return self._step_pair("point-sets", variants, state, compiled)

    def loop_tails(self) -> list[dict]:
        from hydrosoft.compilation import DEFAULT_OPTIONS
        from hydrosoft.dynamics import CompiledStep

        model, state = self._planner_model()
        masked = {**DEFAULT_OPTIONS, "cpp.enable_loop_tail_vec": True}
        return self._step_pair("loop-tails", {
            "scalar": (model, lambda: CompiledStep(model, dynamic=False)),
            "masked": (model, lambda: CompiledStep(model, dynamic=False, options=dict(masked))),
        }, state, compiled=True)


def _print_tables(doc: dict) -> None:
    cfg = doc["config"]
    print(f"device {cfg['device']}, {cfg['threads']} threads, torch {cfg['torch']}; {cfg['scene']}")
    print(f"timing: {cfg['timing_method']}; memory: {cfg['memory_method']}")
    if doc["rows"]:
        print("\nstep speed and memory")
        print(f"{'model':>5} {'dtype':>7} {'mode':>8} {'B':>4} {'N':>5} {'subs':>4} {'step ms':>9} {'fwd+bwd ms':>10} "
              f"{'sub ms':>8} {'sub f+b':>8} {'check':>7} {'M upd/s':>8} {'mem MB':>7} {'bwd MB':>7} {'vs f64':>6}")
        for r in doc["rows"]:
            print(f"{r['model']:>5} {r['dtype']:>7} {r['mode']:>8} {r['batch']:>4} {r['points']:>5} {r['substeps']:>4} "
                  f"{r['step_ms']:>9.3f} {r['step_backward_ms']:>10.3f} {r['substep_ms']:>8.3f} "
                  f"{r['substep_backward_ms']:>8.3f} {r['check_ms']:>7.3f} {r['point_updates_per_s'] / 1e6:>8.2f} "
                  f"{_mb(r['peak_mem_mb']):>7} {_mb(r['peak_mem_backward_mb']):>7} {r['speedup_vs_eager_f64']:>6.2f}")
    if doc["accuracy"]:
        print("\nforce accuracy on press 3 mm, shear 6 mm, release (max |F - F_ref| / max |F_ref|)")
        print(f"{'setting':>32} {'N':>5} {'steps':>5} {'rel error':>10} {'peak N':>8} {'step ms':>8}")
        for r in doc["accuracy"]:
            print(f"{r['setting']:>32} {r['points']:>5} {r['path_steps']:>5} {r['force_rel_error']:>10.2e} "
                  f"{r['peak_force_n']:>8.3f} {r['step_ms']:>8.3f}")
    if doc["wrench"]:
        low, high = cfg["drake_query_ms"]
        print(f"\npose-to-wrench query, batch 1 (Drake's hydroelastic query: {low}-{high} ms)")
        print(f"{'object':>13} {'N':>5} {'dtype':>7} {'mode':>8} {'query ms':>9} {'F_z N':>7}")
        for r in doc["wrench"]:
            print(f"{r['object']:>13} {r['points']:>5} {r['dtype']:>7} {r['mode']:>8} {r['query_ms']:>9.4f} "
                  f"{r['force_z_n']:>7.3f}")
    if doc["object_update"]:
        print("\nobject update against the explicit one at 4x the sub-steps (float64 eager, 10 steps, largest errors)")
        print(f"{'task':>9} {'eps x':>5} {'update':>21} {'subs':>4} {'step ms':>8} {'pos mm':>8} {'rot mrad':>8} "
              f"{'motion mm':>9}")
        for r in doc["object_update"]:
            print(f"{r['task']:>9} {r['epsilon_factor']:>5g} {r['update']:>21} {r['substeps']:>4} {r['step_ms']:>8.2f} "
                  f"{r['position_error_mm']:>8.3f} {r['rotation_error_mrad']:>8.2f} {r['motion_mm']:>9.2f}")
    if doc["pruning"]:
        print("\npruning (float32 eager step)")
        print(f"{'task':>9} {'B':>3} {'N full':>6} {'N kept':>6} {'bodies':>6} {'full ms':>8} {'pruned ms':>9} "
              f"{'speedup':>7} {'max dF N':>9}")
        for r in doc["pruning"]:
            print(f"{r['task']:>9} {r['batch']:>3} {r['points_full']:>6} {r['points_pruned']:>6} "
                  f"{r['bodies_pruned']}/{r['bodies_full']:<4} {r['step_ms_full']:>8.3f} {r['step_ms_pruned']:>9.3f} "
                  f"{r['speedup']:>7.2f} {r['net_force_max_diff_n']:>9.2e}")
    if doc["drift"]:
        r0 = doc["drift"][0]
        print(f"\nfloat32 against float64: rolling scene, {r0['spacing_m'] * 1e3:g} mm spacing, bubble +-1 mm per step "
              f"back and forth, {r0['steps']} steps")
        print(f"{'model':>18} {'dtype':>7} {'drift mm':>9} {'drift rad':>9} {'f32 gap um':>10} {'f32 gap rad':>11} "
              f"{'wall s':>7}")
        for r in doc["drift"]:
            print(f"{r['model']:>18} {r['dtype']:>7} {r['drift_mm']:>9.3f} {r['drift_rad']:>9.4f} "
                  f"{r['f32_gap_um']:>10.3g} {r['f32_gap_rad']:>11.3g} {r['wall_s']:>7.0f}")
    for key, title, (first, second) in (
            ("point_sets", "point sets: the pushing planner's step (float32, linearly implicit), slices against "
             "gathers", ("slices", "gathers")),
            ("loop_tails", "loop tails: the pushing planner's compiled step (float32, linearly implicit), scalar loop "
             "tails (DEFAULT_OPTIONS) against masked vectors", ("scalar", "masked"))):
        if doc[key]:
            print(f"\n{title}")
            print(f"{'mode':>8} {'B':>3} {'pairs':>5} {'fwd ' + first:>12} {'fwd ' + second:>12} {'ratio':>5} "
                  f"{'f+b ' + first:>12} {'f+b ' + second:>12} {'ratio':>5} {'max dF N':>9}")
            for r in doc[key]:
                print(f"{r['mode']:>8} {r['batch']:>3} {r['pairs']:>5} {r['forward_ms_' + first]:>12.3f} "
                      f"{r['forward_ms_' + second]:>12.3f} {r['forward_ratio']:>5.2f} "
                      f"{r['forward_backward_ms_' + first]:>12.3f} {r['forward_backward_ms_' + second]:>12.3f} "
                      f"{r['forward_backward_ratio']:>5.2f} {r['max_force_diff_n']:>9.2e}")


def _mb(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"
