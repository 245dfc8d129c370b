"""The memory allocator of the command line's processes: a faster ``malloc`` than glibc's, preloaded when installed.

The compiled planner allocates and frees about 90 buffers of a few tens of kB per model step, and every tensor
op allocates its small C++ objects. Under glibc's ``malloc`` that took 12-14 % of a solve (``perf``: ``_int_malloc``,
``_int_free``, ``malloc_consolidate``), and the planner's two solver threads share its arenas. gperftools' tcmalloc,
preloaded, took a solve to 0.92 of glibc's time in a round-robin of processes (docs/decisions.md, 2026-11-27,
"the solver's shares may run in worker processes, and a faster `malloc` is preloaded").

A running process cannot swap its allocator, so ``hydrosoft-stack`` re-executes itself once, at start, with the
library in ``LD_PRELOAD`` (``reexec_with_allocator``); the processes it starts (the launcher's services, inductor's
compiler workers) inherit it. ``HYDROSOFT_MALLOC`` chooses: ``auto`` (default: the first installed of
``CANDIDATES``), ``system`` (glibc's), or the path of a library to preload. A user's own ``LD_PRELOAD`` is left as it
is. Linux only; elsewhere, and when nothing is installed, the process runs on the system's allocator.
"""
from __future__ import annotations

import os
import sys
import sysconfig
from collections.abc import Mapping, Sequence
from pathlib import Path

SETTING = "HYDROSOFT_MALLOC"
"""Environment variable: ``auto``, ``system`` or a library's path."""

APPLIED = "HYDROSOFT_MALLOC_APPLIED"
"""Set in the re-executed process, so that it never re-executes again (even where the preload did not take)."""

CANDIDATES = ("libtcmalloc_minimal.so.4", "libtcmalloc.so.4", "libmimalloc.so.2", "libjemalloc.so.2")
"""Libraries ``auto`` preloads, best first (tcmalloc 0.92 of glibc's solve time, mimalloc 0.94, jemalloc 1.02 in
one round-robin run; Debian packages libtcmalloc-minimal4, libgoogle-perftools4, libmimalloc2.0, libjemalloc2)."""


def library_dirs() -> list[Path]:
    """Where ``auto`` looks for ``CANDIDATES``: the platform's multiarch library folders, then the usual ones."""
    arch = sysconfig.get_config_var("MULTIARCH")
    dirs = [f"/usr/lib/{arch}", f"/lib/{arch}"] if arch else []
    return [Path(d) for d in [*dirs, "/usr/lib64", "/usr/lib", "/usr/local/lib"]]


def choose(environ: Mapping[str, str], dirs: Sequence[Path]) -> Path | None:
    """The library to preload for ``environ``'s ``HYDROSOFT_MALLOC``, or None for the system's allocator.

    Raises ValueError naming the setting when it is a path that is not a file."""
    setting = environ.get(SETTING, "auto").strip() or "auto"
    if setting == "system":
        return None
    if setting != "auto":
        path = Path(setting)
        if not path.is_file():
            raise ValueError(f"{SETTING}={setting!r}: no such library (use auto, system or a library's path)")
        return path
    for name in CANDIDATES:
        for folder in dirs:
            if (folder / name).is_file():
                return folder / name
    return None


def reexec_with_allocator(environ: Mapping[str, str] | None = None) -> None:
    """Re-execute this process (same pid, same command line) with the chosen allocator preloaded, and return only when
    there is nothing to do: not Linux, already re-executed, the user's own ``LD_PRELOAD``, or the system's allocator.
    A bad ``HYDROSOFT_MALLOC`` is reported on stderr and the process goes on with the system's allocator."""
    environ = os.environ if environ is None else environ
    if not sys.platform.startswith("linux") or environ.get(APPLIED) or environ.get("LD_PRELOAD"):
        return
    try:
        library = choose(environ, library_dirs())
    except ValueError as err:
        print(f"hydrosoft-stack: {err}; running on the system's allocator", file=sys.stderr)
        return
    if library is None:
        return
    sys.stdout.flush()
    sys.stderr.flush()
    os.execve(sys.executable, [sys.executable, *sys.orig_argv[1:]],
              {**environ, "LD_PRELOAD": str(library), APPLIED: "1"})
