"""Settling Python's cyclic garbage collector once a process has built what it keeps for life (no torch import here,
so every service may use it)."""
from __future__ import annotations

import gc


def settle_garbage_collector() -> None:
    """Collect once, then move every object left out of the collector's generations for good (``gc.freeze``).

    Call it once a process holds what it keeps for life: a service when it is ready (``Service.ready``: its imports,
    sockets and model), a planner once its compiled calls are warm. Frozen objects are never walked again; garbage
    made later is collected as before. What it saves, measured on two busy cores: compiling leaves about half a
    million objects (dynamo's and inductor's graphs and caches), and a full collection over them took 20 ms or more,
    one per solve in some runs (a share's solve 52 instead of 34 ms, half of it ``gc_collect_main``); a service's
    start-up objects took 14-32 ms without torch and 140-220 ms with it, an event-loop pause no message could outrun
    (docs/benchmarks.md, the bus's tail). The first generation's threshold stays Python's: with the objects frozen
    its collections took 0.14 ms at most in ``bench bus --tail``."""
    gc.collect()
    gc.freeze()
