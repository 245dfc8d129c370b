"""Compiled artefacts: whether a compiled part of the stack (the planner's step, sim_world's plant) was built for
this config and this torch, so that a launch loads it (seconds) or says it compiles it cold (minutes), never runs
it eager without saying so.

What torch compiles (inductor's C++ kernels, AOT autograd's forward and backward graphs) it keeps in its compile
cache directory (``cache_dir``), found again by the graphs themselves; dynamo's tracing it would repeat in every
process. So the compiled functions are also precompiled (``compilation.Precompiled``): saved whole, guards and
graphs, in ``CACHE/hydrosoft-artefacts/PART-KEY/`` (``precompiled_dir``), and loaded from there at a launch without
tracing (``use_precompiled``, set before the part's model is built). The plant's are built by ``hydrosoft-stack
compile``; a launch that finds none traces them the usual way. The planner's are built by one process, ``compile``
or the planner itself at a launch that finds its artefact missing or stale, and loaded by its solver worker
processes (``services/planner.py``, ``build_precompiled``). An artefact is the
record ``CACHE/hydrosoft-artefacts/PART-KEY.json`` written once PART compiled completely into that cache, under its
key (``ArtefactKey``): a hash of the config keys that shape PART's graphs, torch's version, and the model library's
source. A launch whose key has a record loads
the part from the cache; one without any record of PART (``missing``) or with records of other keys only
(``stale``: a config, torch or code change) compiles it, saying so in its log and status, and records its key
when it is done. Records of several keys lie side by side, so several configs stay warm in one cache.
``hydrosoft-stack compile CONFIG`` builds every compiled part of a config ahead of the launch.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path

import msgspec

from hydrosoft.services.bus.config import StackConfig
from hydrosoft.services.bus.service_cli import CACHE_ENV

RECORDS = "hydrosoft-artefacts"  # the folder of the records, in the compile cache
PROGRESS_PERIOD_S = 15.0  # a compiling part reports its progress this often
#: planner keys that do not shape the compiled graphs (timing, priority and safety settings of the running service)
PLANNER_RUNTIME_KEYS = ("max_age_s", "heartbeat_period_s", "target_lead_s", "max_reapproaches", "stall_s", "seed",
                        "nice")
#: sim keys that do not shape the plant's graphs (the rendered images' noise, the simulated devices)
SIM_RUNTIME_KEYS = ("ur_tick_hz", "image_noise", "image_blur_px", "depth_noise_m", "ft_bias", "ft_noise",
                    "compile")


def cache_dir(config: StackConfig) -> Path:
    """torch's compile cache for ``config``'s processes, as ``service_cli.use_compile_cache`` sets it:
    ``$TORCHINDUCTOR_CACHE_DIR`` when set, else the config's ``compile_cache_dir``, else torch's default
    (``/tmp/torchinductor_USER``, which a reboot empties: its records then go with it)."""
    if CACHE_ENV in os.environ:
        return Path(os.environ[CACHE_ENV])
    if config.compile_cache_dir is not None:
        return Path(config.compile_cache_dir).expanduser()
    from torch._inductor.runtime.cache_dir_utils import default_cache_dir
    return Path(default_cache_dir())


@dataclass(frozen=True)
class ArtefactKey:
    """What a compiled part was built for. part: ``planner`` or ``plant``. config: hash of the config keys that
    shape its graphs. torch: torch's version. source: hash of the model library's source. key: the three in 12
    hex digits."""

    part: str
    config: str
    torch: str
    source: str

    @property
    def key(self) -> str:
        return _digest(f"{self.part} {self.config} {self.torch} {self.source}".encode())

    def differences(self, other: ArtefactKey) -> list[str]:
        """What changed from ``other`` to this key, in words (empty when nothing did)."""
        changed = []
        if other.config != self.config:
            changed.append("config changed")
        if other.torch != self.torch:
            changed.append(f"torch {other.torch} -> {self.torch}")
        if other.source != self.source:
            changed.append("model code changed")
        return changed


def planner_key(config: StackConfig, torch_version: str | None = None) -> ArtefactKey:
    """The planner step's key: the task, the arms and the ``[planner]`` keys but its runtime ones."""
    planner = {k: v for k, v in msgspec.to_builtins(config.planner).items() if k not in PLANNER_RUNTIME_KEYS}
    shape = {"task": config.scene.task, "arms": [arm.name for arm in config.arms], "planner": planner}
    return _key("planner", shape, torch_version)


def plant_key(config: StackConfig, torch_version: str | None = None) -> ArtefactKey:
    """The plant's key: the task, the arms, the planner's spacing (the plant's is a factor of it) and the
    ``[sim]`` keys but its device ones."""
    sim = {k: v for k, v in msgspec.to_builtins(config.sim).items() if k not in SIM_RUNTIME_KEYS}
    shape = {"task": config.scene.task, "arms": [arm.name for arm in config.arms],
             "spacing": config.planner.spacing, "sim": sim}
    return _key("plant", shape, torch_version)


def _key(part: str, shape: dict, torch_version: str | None) -> ArtefactKey:
    if torch_version is None:
        import torch
        torch_version = torch.__version__
    return ArtefactKey(part, _digest(msgspec.json.encode(shape, order="sorted")), torch_version, source_digest())


@functools.cache
def source_digest() -> str:
    """Hash of the model library's Python source (``hydrosoft/``, what the compiled graphs are traced from)."""
    import hydrosoft
    root = Path(hydrosoft.__file__).parent
    digest = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        digest.update(path.relative_to(root).as_posix().encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()[:12]


def _digest(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()[:12]


# --- records ----------------------------------------------------------------------------------------------------


def record_path(cache: Path, key: ArtefactKey) -> Path:
    """Where ``key``'s record lies in the compile cache ``cache``: one file per part and key, so the artefacts of
    several configs (a lab's and the tests', the sim and the lab stack) stay warm side by side."""
    return cache / RECORDS / f"{key.part}-{key.key}.json"


def _built_for(path: Path) -> ArtefactKey | None:
    """The key a record was built for, or None when it cannot be read."""
    try:
        return ArtefactKey(**json.loads(path.read_text())["built_for"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def check(cache: Path, key: ArtefactKey) -> str:
    """``ready`` when ``cache`` holds ``key``'s part, built; else why it must be compiled: ``missing artefact``
    (no readable record of that part) or ``stale artefact (WHAT CHANGED)`` against the part's newest record."""
    if _built_for(record_path(cache, key)) == key:
        return "ready"
    others = sorted((cache / RECORDS).glob(f"{key.part}-*.json"), key=lambda path: path.stat().st_mtime,
                    reverse=True)
    for path in others:
        built = _built_for(path)
        if built is not None:
            return f"stale artefact ({', '.join(key.differences(built))})"
    return "missing artefact"


def precompiled_dir(cache: Path, key: ArtefactKey) -> Path:
    """Where ``key``'s part keeps its precompiled functions in the compile cache ``cache``."""
    return cache / RECORDS / f"{key.part}-{key.key}"


def use_precompiled(config: StackConfig, key: ArtefactKey, build: bool = False) -> Path:
    """Have the compiled functions this process (and the processes it starts) makes from now on load ``key``'s
    precompiled functions, and build missing ones when ``build`` (``compilation.use_precompiled``); their
    directory."""
    from hydrosoft.compilation import use_precompiled as use
    directory = precompiled_dir(cache_dir(config), key)
    use(directory, build)
    return directory


def record(cache: Path, key: ArtefactKey, seconds: float) -> Path:
    """Record that ``key``'s part compiled completely into ``cache`` in ``seconds``; the record's path. Written to a
    temporary file and renamed, so a reader never sees half a record."""
    path = record_path(cache, key)
    path.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps({"key": key.key, "built_for": asdict(key), "compile_s": round(seconds, 1),
                       "built_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}, indent=1)
    partial = path.with_suffix(f".{os.getpid()}.tmp")
    partial.write_text(text + "\n")
    os.replace(partial, path)
    return path


# --- building a part --------------------------------------------------------------------------------------------


class PartBuild:
    """One compiled part's start in one process: whether its artefact is ready, the status line to show
    (``status``), and its compilation with progress lines (``run``).

    ``status`` before ``run``: ``compiling: loading artefact KEY`` (ready) or ``compiling: missing artefact, building
    KEY`` / ``compiling: stale artefact (WHAT CHANGED), building KEY``; after it: ``compiled (artefact KEY,
    precompiled)`` when its functions were loaded (or built) whole, ``compiled (artefact KEY)`` when dynamo traced
    them, or ``eager: WHY`` when the part fell back to eager."""

    def __init__(self, key: ArtefactKey, cache: Path) -> None:
        self.key = key
        self.cache = cache
        self.state = check(cache, key)
        self.seconds: float | None = None
        self.fallback: str | None = None
        self.precompiled = False  # its functions were loaded or built whole, none traced

    @property
    def ready(self) -> bool:
        """True when the cache holds the part for this key (the start loads it)."""
        return self.state == "ready"

    @property
    def status(self) -> str:
        if self.fallback is not None:
            return f"eager: {self.fallback}"
        if self.seconds is not None:
            return f"compiled (artefact {self.key.key}{', precompiled' if self.precompiled else ''})"
        if self.ready:
            return f"compiling: loading artefact {self.key.key}"
        return f"compiling: {self.state}, building {self.key.key}"

    def run(self, compile: Callable[[], str | None], say: Callable[[str], None],
            period_s: float = PROGRESS_PERIOD_S, elsewhere: Callable[[], Mapping[str, int]] | None = None) -> bool:
        """Compile the part by ``compile()`` (None once compiled, or why it fell back to eager), saying what happens
        through ``say`` (a line at the start, one every ``period_s`` while it compiles, one at the end); record the
        artefact when it was built here. ``elsewhere()``: the precompiled functions of the part's other processes
        (the planner's worker processes: ``WorkerProcesses.precompiled``), counted with this process's. True when
        the part runs compiled."""
        part = self.key.part
        what = "loading its artefact" if self.ready else "building its artefact (minutes on a small machine)"
        say(f"{part}: {self.status}: {what}; compile cache {self.cache}")
        counts = functools.partial(_graph_counts, elsewhere)
        started, before = time.monotonic(), counts()
        with _progress(lambda: say(f"{part}: still compiling, {time.monotonic() - started:.0f} s, "
                                   f"{_graphs(before, counts())}"), period_s):
            fallback = compile()
        seconds = time.monotonic() - started
        if fallback is not None:
            self.fallback = fallback
            say(f"{part}: fell back to eager after {seconds:.1f} s: {fallback}")
            return False
        if not self.ready:
            record(self.cache, self.key, seconds)
        after = counts()
        _, _, built, loaded, traced = (now - then for now, then in zip(after, before))
        self.precompiled = bool(built + loaded) and not traced
        self.seconds = seconds
        say(f"{part}: {self.status} in {seconds:.1f} s ({_graphs(before, after)})")
        return True


@contextmanager
def _progress(tick: Callable[[], None], period_s: float) -> Iterator[None]:
    """Call ``tick()`` every ``period_s`` from a thread of its own while the block runs."""
    done = threading.Event()

    def ticking() -> None:
        while not done.wait(period_s):
            tick()

    thread = threading.Thread(target=ticking, name="compile-progress", daemon=True)
    thread.start()
    try:
        yield
    finally:
        done.set()
        thread.join()


def _graph_counts(elsewhere: Callable[[], Mapping[str, int]] | None = None) -> tuple[int, int, int, int, int]:
    """The graphs so far: this process's inductor graphs (compiled, loaded from the compile cache) and precompiled
    functions (built, loaded, and copies that traced instead: ``compilation.PRECOMPILED``), with ``elsewhere()``'s
    precompiled functions added (counted the same way in other processes)."""
    from torch._dynamo.utils import counters

    from hydrosoft.compilation import PRECOMPILED
    inductor = counters["inductor"]
    other = {} if elsewhere is None else elsewhere()
    return (inductor["fxgraph_cache_miss"] + inductor["fxgraph_cache_bypass"], inductor["fxgraph_cache_hit"],
            *(PRECOMPILED[name] + other.get(name, 0) for name in ("built", "loaded", "jit")))


def _graphs(before: tuple[int, int, int, int, int], now: tuple[int, int, int, int, int]) -> str:
    """The graphs from ``before`` to ``now`` (``_graph_counts``), in words."""
    compiled, loaded, built, precompiled, traced = (after - then for after, then in zip(now, before))
    return (f"{compiled} graphs compiled, {loaded} loaded from the cache; {built} precompiled functions built, "
            f"{precompiled} loaded, {traced} traced instead")
