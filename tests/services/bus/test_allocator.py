"""The faster allocator: which library is chosen, and the re-executed process that preloads it (real processes)."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from hydrosoft.services.bus.allocator import APPLIED, CANDIDATES, SETTING, choose, library_dirs

TCMALLOC, _, MIMALLOC, JEMALLOC = CANDIDATES
GLIBC_DEBUG = "libc_malloc_debug.so.0"

# Prints its pid, re-executes on the allocator, prints its pid again and whether the library is mapped.
CHILD = """
import os, sys
from hydrosoft.services.bus.allocator import reexec_with_allocator
print("pid", os.getpid(), flush=True)
reexec_with_allocator()
preload = os.environ.get("LD_PRELOAD", "")
print("mapped", bool(preload) and preload in open("/proc/self/maps").read(), flush=True)
"""


def _libraries(tmp_path: Path, layout: dict[str, list[str]]) -> list[Path]:
    """Folders under ``tmp_path`` holding empty files named like libraries: ``{folder: [names]}``."""
    dirs = []
    for folder, names in layout.items():
        (tmp_path / folder).mkdir()
        for name in names:
            (tmp_path / folder / name).write_bytes(b"")
        dirs.append(tmp_path / folder)
    return dirs


def test_auto_takes_the_best_installed_library_over_any_folder_order(tmp_path):
    dirs = _libraries(tmp_path, {"a": [JEMALLOC, MIMALLOC], "b": [TCMALLOC]})
    assert choose({}, dirs) == tmp_path / "b" / TCMALLOC
    assert choose({SETTING: "auto"}, dirs[:1]) == tmp_path / "a" / MIMALLOC
    assert choose({SETTING: ""}, dirs[:1]) == tmp_path / "a" / MIMALLOC


def test_system_and_nothing_installed_mean_glibc_and_a_path_is_taken_as_given(tmp_path):
    dirs = _libraries(tmp_path, {"a": [TCMALLOC], "empty": []})
    assert choose({SETTING: "system"}, dirs) is None
    assert choose({}, dirs[1:]) is None
    own = tmp_path / "libown.so"
    own.write_bytes(b"")
    assert choose({SETTING: str(own)}, dirs) == own
    with pytest.raises(ValueError, match="HYDROSOFT_MALLOC='/no/such/lib.so'"):
        choose({SETTING: "/no/such/lib.so"}, dirs)


def _run_child(**env: str) -> subprocess.CompletedProcess:
    clean = {k: v for k, v in os.environ.items() if k not in ("LD_PRELOAD", SETTING, APPLIED)}
    return subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True, timeout=60,
                          env={**clean, **env})


def _installed() -> Path:
    """A library to preload: the faster allocator ``auto`` chooses, or else glibc's own ``libc_malloc_debug.so.0``
    (in every glibc since 2.34), so that the re-execution is tested on a machine without a faster allocator too."""
    library = choose({}, library_dirs())
    if library is None:
        library = next((d / GLIBC_DEBUG for d in library_dirs() if (d / GLIBC_DEBUG).is_file()), None)
    if library is None:
        pytest.skip(f"none of {CANDIDATES} nor {GLIBC_DEBUG} is installed here")
    return library


def test_the_process_reexecutes_once_in_place_with_the_library_mapped():
    library = _installed()
    done = _run_child(**{SETTING: str(library)})
    assert done.returncode == 0, done.stderr
    lines = done.stdout.split("\n")
    pids = [line for line in lines if line.startswith("pid")]
    assert len(pids) == 2 and pids[0] == pids[1]  # exec'd once, same process
    assert "mapped True" in lines


def test_a_users_preload_a_bad_setting_and_system_run_without_reexecuting():
    library = _installed()
    for env, mapped in (({"LD_PRELOAD": str(library)}, "True"), ({SETTING: "system"}, "False"),
                        ({SETTING: "/no/such/lib.so"}, "False")):
        done = _run_child(**env)
        assert done.returncode == 0, done.stderr
        assert done.stdout.count("pid") == 1, env
        assert f"mapped {mapped}" in done.stdout, env
    assert "no such library" in done.stderr and "system's allocator" in done.stderr
