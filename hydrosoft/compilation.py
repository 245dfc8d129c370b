"""``torch.compile`` for the model library's pure functions, safe to call from the planner's worker threads.

``CompiledCopies`` keeps compiled copies of one function: a call checks out a copy no other call is using and
returns it after, so two threads never run one copy's guards at once; the first call from each new input signature
runs alone under a lock, since dynamo compiling in two threads at once fails; and if compiling fails, it warns once
and runs the eager function from then on (``fallback_reason`` says why). ``CompiledFunction`` is that for a plain
function of tensors (the planner's costs); ``dynamics.CompiledStep`` uses it for the sub-step inside its own
stability-checked loop.

Why copies. With one compiled copy used by two solver workers at once, dynamo's guards failed spuriously in the
middle of a run ("runtime guards failed even though they passed during recompilation-reason analysis"), twice in
two runs, each time a 23-26 s recompile that also spent one of the copy's graphs. So there are as many copies as
the solver has workers (more if more calls ever ran at once), each compiled for every signature as it first
appears, mostly from inductor's cache after the first; calls one after another, from any threads (a service's
executor), share one.

Why private code. Dynamo keeps compiled graphs, and counts recompilations against
``torch._dynamo.config.recompile_limit`` (8), per code object. Every copy compiles a private copy of the function's
code (``private_copy``), so any number of copies and instances stay compiled; past its limit a copy raises instead
of silently running eager (``raise_past_recompile_limit``), and the instance then falls back with a warning.

Why precompiled copies. From a warm compile cache, a process still traced every compiled function again with dynamo
before the cache answered with the graphs. With a precompiled directory set (``use_precompiled``, a variable of the
environment so that processes started from this one inherit it), each copy is a ``Precompiled``: every input
signature's function is loaded from one file there, guards and graphs, without tracing anything. Building the files
(``torch.compile(fullgraph=True).aot_compile``, backward graphs included) is a compile of its own, longer than
loading graphs from inductor's cache, so only a process that is asked to (``build``: ``hydrosoft-stack compile``,
or the planner's own process at a launch that finds its artefact missing or stale, ``building_precompiled``) builds
them; any other (the planner's solver worker processes) loads them, and compiles a signature without a file the
usual way.
"""
from __future__ import annotations

import contextlib
import hashlib
import os
import threading
import types
import warnings
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, NamedTuple, TypeVar

import torch
from torch import Tensor

T = TypeVar("T")

DEFAULT_OPTIONS = {"cpp_wrapper": True, "assert_indirect_indexing": False, "cpp.enable_loop_tail_vec": False}
"""Inductor's options on the CPU when a caller gives none (``dynamics.CompiledStep``'s docstring says why each is
set)."""

GPU_DEFAULT_OPTIONS = {"assert_indirect_indexing": False, "triton.cudagraphs": True}
"""Inductor's options on a GPU when a caller gives none: no bounds check on each indirect index (as on the CPU);
the Python wrapper (inductor's C++ wrapper for GPU kernels is a C++ build of its own per graph: the planner's first
compiled solve had not ended after 325 s with it); and CUDA graphs, each graph's kernels launched as one (the
planner's solve is bound by launching many small kernels: 0.19 of the time without them on an H200, 2026-11-28,
docs/benchmarks.md "On a GPU"). With CUDA graphs a call's outputs are copied out of the graphs' memory
(``out_of_graph_memory``)."""


PRECOMPILED_ENV = "HYDROSOFT_PRECOMPILED_DIR"
"""The environment variable that names the directory of precompiled functions (``use_precompiled``)."""

PRECOMPILED_BUILD_ENV = "HYDROSOFT_PRECOMPILED_BUILD"
"""The environment variable that, set to 1, has missing precompiled functions built (``use_precompiled``)."""

PRECOMPILED = Counter()
"""This process's precompiled functions so far: ``loaded`` from their files, ``built`` (compiled and saved), and
``jit``: copies that compile the usual way, since a signature of theirs has no file (and none is built here) or
cannot be precompiled."""

AOT_RESTARTS = 3
"""Tries of one ahead-of-time compile that dynamo asks to restart: its float specialisation (a tensorified Python
float) restarts the analysis, which the ahead-of-time path does not do by itself; each try keeps the floats the
last one specialised."""


class Precompiling(NamedTuple):
    """Where compiled functions keep their precompiled files, and whether missing ones are built."""

    directory: Path
    build: bool


def use_precompiled(directory: Path | None, build: bool = False) -> None:
    """Have compiled functions made from now on, in this process and in the processes it starts, load their graphs
    from precompiled files in ``directory`` (``Precompiled``), building missing ones when ``build``; None: compile
    them the usual way."""
    if directory is None:
        os.environ.pop(PRECOMPILED_ENV, None)
        os.environ.pop(PRECOMPILED_BUILD_ENV, None)
    else:
        os.environ[PRECOMPILED_ENV] = str(directory)
        os.environ[PRECOMPILED_BUILD_ENV] = "1" if build else "0"


@contextlib.contextmanager
def building_precompiled(directory: Path) -> Iterator[None]:
    """Have the compiled functions made inside the block build their missing precompiled files into ``directory``
    (``use_precompiled(directory, build=True)``); the setting from before is back after it, so functions made later
    (and processes started later) load from there or trace, as before."""
    before = precompiling()
    use_precompiled(directory, build=True)
    try:
        yield
    finally:
        use_precompiled(*before) if before is not None else use_precompiled(None)


def precompiling() -> Precompiling | None:
    """What ``use_precompiled`` set (here or in a parent process), or None."""
    directory = os.environ.get(PRECOMPILED_ENV)
    if not directory:
        return None
    return Precompiling(Path(directory), os.environ.get(PRECOMPILED_BUILD_ENV) == "1")


def compiled_copy(fn: Callable, options: dict, setting: Precompiling | None) -> Callable:
    """A compiled copy of ``fn`` with ``torch.compile``'s ``options``: a ``Precompiled`` one as ``setting`` says
    when ``options`` name inductor (whose graphs alone can be saved), else a ``torch.compile`` of private code."""
    if setting is None or options.get("backend", "inductor") != "inductor":
        return torch.compile(private_copy(fn), **options)
    return Precompiled(fn, options, setting)


class Precompiled:
    """``fn`` compiled whole per input signature by dynamo's ahead-of-time path, each signature's function saved in
    ``setting.directory`` and loaded from there by the next process (no tracing); one copy for ``CompiledCopies``.

    A call runs the function loaded for its ``signature`` (dtype, shape, strides, grad mode, constants). For a new
    signature it loads ``directory/NAME-DIGEST.pt2`` (``NAME`` the function's, ``DIGEST`` a hash of the signature)
    and checks the file's guards on the call's arguments; a missing file, or one whose guards refuse them, it
    compiles and saves when ``setting.build``, else it compiles that signature the usual way (``torch.compile`` of
    private code). (Later calls of a loaded signature skip the guards, which bind the arguments in Python.) The
    objects in ``fn``'s closure (a model's tensors) are not saved: the loaded function is given this ``fn``'s, so
    it computes with this process's values, never with those of the process that saved it. A signature that cannot
    be compiled whole (a graph break) warns once and runs through a ``torch.compile`` of private code
    (``jit_reason`` says why); an error there is ``CompiledCopies``' fallback to eager.
    """

    def __init__(self, fn: Callable, options: dict, setting: Precompiling) -> None:
        self.fn = fn
        self.options = options
        self.directory, self.build = setting
        self.jit_reason: str | None = None
        self._loaded: dict[tuple, Callable] = {}  # signature -> its function
        self._unbuilt: set[tuple] = set()  # signatures without a file, compiled the usual way
        self._jit: Callable | None = None
        self._closure = {f"cell{i}": cell.cell_contents for i, cell in enumerate(fn.__closure__ or ())}

    def __call__(self, *args: Any) -> Any:
        key = signature(*args)
        loaded = self._loaded.get(key)
        if loaded is not None:
            return loaded(*args)
        if self.jit_reason is None and key not in self._unbuilt:
            try:
                loaded = self._load_or_build(args)
            except Exception as err:  # noqa: BLE001 - not precompilable (a graph break): compiled the usual way
                self.jit_reason = f"{type(err).__name__}: {err}".splitlines()[0]
                warnings.warn(f"{self.fn.__qualname__} cannot be precompiled, compiled at each start: "
                              f"{self.jit_reason}", RuntimeWarning, stacklevel=2)
            else:
                if loaded is not None:
                    loaded.disable_guard_check()
                    self._loaded[key] = loaded
                    return loaded(*args)
                self._unbuilt.add(key)
        if self._jit is None:
            self._jit = torch.compile(private_copy(self.fn), **self.options)
            PRECOMPILED["jit"] += 1
        return self._jit(*args)

    def path(self, args: tuple) -> Path:
        """The file of the function for ``args``' signature (grad mode included)."""
        digest = hashlib.sha256(repr(signature(*args)).encode()).hexdigest()[:16]
        return self.directory / f"{self.fn.__module__}.{self.fn.__qualname__}-{digest}.pt2"

    def _load_or_build(self, args: tuple) -> Callable | None:
        """The function for ``args``: loaded from its file when that accepts them, else compiled and saved when
        building (None when not)."""
        path = self.path(args)
        if path.exists():
            try:
                with path.open("rb") as file:
                    loaded = torch.compiler.load_compiled_function(file, f_globals=self.fn.__globals__,
                                                                   external_data=self._closure)
            except Exception:  # noqa: BLE001 - an unreadable or incompatible file is built again
                loaded = None
            if loaded is not None and loaded.guard_check(*args):
                PRECOMPILED["loaded"] += 1
                return loaded
        if not self.build:
            return None
        compiled = torch.compile(private_copy(self.fn), fullgraph=True, **self.options)
        for attempt in range(AOT_RESTARTS):
            try:
                with warnings.catch_warnings():  # dynamo's guards read .grad of the inputs' non-leaf tensors: noise
                    warnings.filterwarnings("ignore", message="The .grad attribute of a Tensor that is not a leaf",
                                            category=UserWarning)
                    built = compiled.aot_compile((args, {}))
                break
            except torch._dynamo.exc.TensorifyScalarRestartAnalysis:
                if attempt == AOT_RESTARTS - 1:
                    raise
        path.parent.mkdir(parents=True, exist_ok=True)
        partial = path.with_name(f"{path.name}.{os.getpid()}.partial")  # whole or absent to another process
        built.save_compiled_function(str(partial), external_data=self._closure)
        os.replace(partial, path)
        PRECOMPILED["built"] += 1
        return built


def uses_cuda_graphs(options: dict) -> bool:
    """Whether ``torch.compile``'s keyword arguments ``options`` have inductor run its graphs as CUDA graphs (its
    option ``triton.cudagraphs``, the mode ``reduce-overhead``, or the process's inductor setting, e.g.
    ``TORCHINDUCTOR_CUDAGRAPHS=1``)."""
    if options.get("backend", "inductor") != "inductor":
        return False
    if options.get("mode") in ("reduce-overhead", "max-autotune"):
        return True
    return bool(options.get("options", {}).get("triton.cudagraphs", torch._inductor.config.triton.cudagraphs))


def with_default_options(options: dict, device: torch.device | str = "cpu") -> dict:
    """``torch.compile`` keyword arguments ``options`` with inductor's default options for graphs on ``device``
    (``DEFAULT_OPTIONS`` on the CPU, ``GPU_DEFAULT_OPTIONS`` on any other) when the backend is inductor and neither
    ``mode`` nor ``options`` is given."""
    if options.get("backend", "inductor") == "inductor" and not {"mode", "options"} & options.keys():
        defaults = DEFAULT_OPTIONS if torch.device(device).type == "cpu" else GPU_DEFAULT_OPTIONS
        return {**options, "options": dict(defaults)}
    return dict(options)


def private_copy(fn: Callable) -> Callable:
    """``fn`` with a code object of its own, so that dynamo counts its graphs against a recompile limit of its own."""
    return types.FunctionType(fn.__code__.replace(), fn.__globals__, fn.__name__, fn.__defaults__, fn.__closure__)


def raise_past_recompile_limit() -> None:
    """Have dynamo raise past its recompile limit instead of silently running eager, in this whole process.

    Every ``CompiledCopies`` sets it when it is made, and it stays set: a process that compiles the model library
    wants every compiled call either compiled or failed loudly. (It was set around each compiled call and restored
    after, under a lock, since solver workers call at once; but each change of dynamo's config marks its cached
    settings stale, which the next compiled call rebuilds: that cost about 20 us of a 0.6-0.7 ms step.)"""
    torch._dynamo.config.fail_on_recompile_limit_hit = True


def signature(*args: Any) -> tuple:
    """What tells the compiled graphs of a call apart: grad mode, and ``args`` (tensors and hashable constants, in
    tuples, named tuples and lists) with each tensor's dtype, device, shape, strides and whether it requires grad in
    its place, each container's type with it. (Spelled out rather than through torch's pytrees: hashing a
    ``TreeSpec`` cost 20 us per call.)"""
    return torch.is_grad_enabled(), _key(args)


def _key(arg: Any) -> Any:
    """``signature``'s part for one argument."""
    if isinstance(arg, Tensor):
        return arg.dtype, arg.device, arg.shape, arg.stride(), arg.requires_grad
    if isinstance(arg, (tuple, list)):
        return type(arg), *map(_key, arg)
    return arg


class _Copy(NamedTuple):
    """One compiled copy and the input signatures (``signature``) it has run from, whose graphs are compiled."""

    compiled: Callable
    warm: set


class CompiledCopies:
    """Compiled copies of one function, made by ``build() -> compiled callable`` (a fresh ``torch.compile`` of private
    code), checked out one per running call (module docstring).

    ``run(args, body, eager)`` returns ``body(compiled, *args)`` for a copy compiled for the input signature
    ``signature(*args)``, or ``body(eager, *args)`` once compiling has failed. Errors of the types in
    ``passthrough`` are the body's own and are raised; any other error of a compiled call is taken for a compiler
    failure: it warns once and falls back (a genuine error recurs in the eager call).

    The first call from a signature a copy has not run from compiles, under a lock, with its backward graph
    (``force_non_lazy_backward_lowering``): lazily, at the first backward, it compiled outside the lock while another
    worker ran or compiled, and dynamo failed ("FX to symbolically trace a dynamo-optimized function"), leaving the
    process unable to compile. ``activation_memory_budget`` is AOT autograd's, set while a graph compiles
    (``dynamics.CompiledStep`` says what it does).

    All copies compile every signature when it first appears, so that none compiles later in the middle of a run:
    the arguments of each signature's first call are kept (detached) as its example, and that call then compiles
    every idle copy on it (``warm(compiled, *example)``, a side-effect-free ``body``), making new copies up to
    ``workers`` (the calls that may run at once: the solver's workers); a copy busy at that moment compiles what it
    missed before it is returned. Before, a copy was made the first time two calls ran at once and compiled each
    signature the first time it met it: the two solver workers' short cost calls first overlapped in the third solve,
    after two warm-up solves, and that solve stalled while a copy compiled (0.5 s for a cost, 19 s for the step).

    ``copy_outputs`` (set when the copies run CUDA graphs, ``uses_cuda_graphs``): each compiled call's tensors are
    returned as copies (``out_of_graph_memory``).
    """

    def __init__(self, build: Callable[[], Callable], warm: Callable[..., Any], activation_memory_budget: float = 0.0,
                 passthrough: tuple[type[BaseException], ...] = (), workers: int = 1,
                 copy_outputs: bool = False) -> None:
        self.activation_memory_budget = activation_memory_budget
        self._copy_outputs = copy_outputs
        self.fallback_reason: str | None = None
        self._build = build
        self._warm = warm
        self._passthrough = passthrough
        self._workers = workers
        self.copies: list[_Copy] = []  # all made so far
        self._idle: list[_Copy] = []  # those no call is using
        self._examples: dict[tuple, tuple] = {}  # signature -> the (detached) arguments of its first call
        self._copies_lock = threading.Lock()
        self._first_calls = threading.Lock()  # a copy compiles under it
        raise_past_recompile_limit()

    def run(self, args: tuple, body: Callable[..., T], eager: Callable) -> T:
        """``body(compiled, *args)`` through a copy compiled for ``args``' signature, or ``body(eager, *args)`` after a
        fallback."""
        if self.fallback_reason is None:
            key = signature(*args)
            copy = self._check_out(key)
            try:
                if key in copy.warm:
                    out = body(copy.compiled, *args)
                else:
                    with self._compiling():
                        self._catch_up(copy)  # the signatures other copies ran, this call's among them if it was
                        out = body(copy.compiled, *args)
                        copy.warm.add(key)
                        if key not in self._examples:
                            self._examples[key] = _detached(args)
                            self._catch_up_idle()
                if len(copy.warm) < len(self._examples):  # a signature appeared while this copy ran
                    with self._compiling():
                        self._catch_up(copy)
                return out_of_graph_memory(out) if self._copy_outputs else out
            except self._passthrough:
                raise
            except Exception as err:  # noqa: BLE001 - a compiler failure; a genuine error recurs in the eager call
                self.fallback_reason = f"{type(err).__name__}: {err}"
                warnings.warn(f"torch.compile failed, running eager: {self.fallback_reason}", RuntimeWarning,
                              stacklevel=3)
            finally:
                with self._copies_lock:
                    self._idle.append(copy)
        return body(eager, *args)

    @contextlib.contextmanager
    def _compiling(self) -> Iterator[None]:
        """The context a copy compiles in: the lock, and AOT autograd's settings."""
        settings = torch._functorch.config.patch(activation_memory_budget=self.activation_memory_budget,
                                                 force_non_lazy_backward_lowering=True)
        with self._first_calls, settings:
            yield

    def _catch_up_idle(self) -> None:
        """Compile every idle copy, and new ones up to ``workers``, for every kept example (under the lock). Calls
        that want a copy meanwhile wait for it here instead of making one more."""
        with self._copies_lock:
            for copy in self._idle:
                self._catch_up(copy)
            while len(self.copies) < self._workers:
                copy = _Copy(self._build(), set())
                self._catch_up(copy)
                self.copies.append(copy)
                self._idle.append(copy)

    def any_copy(self) -> Callable:
        """A compiled copy, for timing it alone from one thread (no lock, no signature bookkeeping)."""
        copy = self._check_out()
        with self._copies_lock:
            self._idle.append(copy)
        return copy.compiled

    def _catch_up(self, copy: _Copy) -> None:
        """Compile ``copy`` for every signature another copy has run from, on its example (under the lock)."""
        for key, example in list(self._examples.items()):
            if key not in copy.warm:
                with torch.set_grad_enabled(key[0]):
                    self._warm(copy.compiled, *example)
                copy.warm.add(key)

    def _check_out(self, key: tuple | None = None) -> _Copy:
        """A copy no call is using, one compiled for ``key`` if there is one (a new copy when all are in use); the
        caller returns it to ``_idle``."""
        with self._copies_lock:
            if self._idle:
                warm = [i for i, copy in enumerate(self._idle) if key in copy.warm]
                return self._idle.pop(warm[-1] if warm else -1)
            copy = _Copy(self._build(), set())
            self.copies.append(copy)
            return copy


def out_of_graph_memory(out: Any) -> Any:
    """``out`` (tensors in tuples, named tuples and lists) with each tensor copied (``clone``, gradients flow), for
    inductor's CUDA graphs (``TORCHINDUCTOR_CUDAGRAPHS=1``): a graph's outputs live in its memory pool, which its next
    replay overwrites, and callers keep outputs across calls (a start state's signed distances, a rollout's states).
    Within one call (a step's sub-steps) outputs feed the next replay directly."""
    return _map_tensors(Tensor.clone, out)


def _detached(arg: Any) -> Any:
    """``arg`` (as ``signature`` takes it) with each tensor detached from autograd's graph, its ``requires_grad``
    kept: the same signature, without holding a rollout's graph alive."""
    return _map_tensors(lambda tensor: tensor.detach().requires_grad_(tensor.requires_grad), arg)


def _map_tensors(fn: Callable[[Tensor], Tensor], arg: Any) -> Any:
    """``arg`` (tensors and constants in tuples, named tuples and lists) with each tensor replaced by ``fn(tensor)``,
    its containers rebuilt with their types."""
    if isinstance(arg, Tensor):
        return fn(arg)
    if isinstance(arg, tuple) and hasattr(arg, "_fields"):
        return type(arg)(*(_map_tensors(fn, item) for item in arg))
    if isinstance(arg, (tuple, list)):
        return type(arg)(_map_tensors(fn, item) for item in arg)
    return arg


def _call(fn: Callable, *args: Any) -> Any:
    return fn(*args)


class FallsBack:
    """A callable compiled through ``CompiledCopies`` (in ``_copies``) that says whether it still runs compiled."""

    _copies: CompiledCopies

    @property
    def compiled(self) -> bool:
        """True while the compiled path is in use (False after a fallback to eager)."""
        return self._copies.fallback_reason is None

    @property
    def fallback_reason(self) -> str | None:
        """Why compiling failed (None while compiled)."""
        return self._copies.fallback_reason


class CompiledFunction(FallsBack):
    """``fn(*args)`` compiled by ``torch.compile``, callable from several threads at once, with an eager fallback.

    ``fn`` is a pure function of tensors and hashable constants, in tuples, named tuples and lists; each new
    ``signature`` of its arguments compiles once (constants are baked into the graph). ``options`` go to
    ``torch.compile``, with inductor's default options for ``device`` (where the tensors are) when none are given
    (``with_default_options``);
    ``activation_memory_budget`` is AOT autograd's; ``workers`` the calls that may run at once (``CompiledCopies``).
    Its copies are ``Precompiled`` when a precompiled directory was set when it was made (``use_precompiled``).
    """

    def __init__(self, fn: Callable, activation_memory_budget: float = 0.0, workers: int = 1,
                 device: torch.device | str = "cpu", **options) -> None:
        self.fn = fn
        options = with_default_options(options, device)
        setting = precompiling()
        self._copies = CompiledCopies(lambda: compiled_copy(fn, options, setting), _call, activation_memory_budget,
                                      copy_outputs=uses_cuda_graphs(options),
                                      workers=workers)

    def __call__(self, *args: Any) -> Any:
        return self._copies.run(args, _call, self.fn)
