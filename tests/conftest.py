"""Test-wide settings.

- torch runs single-threaded: on two shared cores OpenMP worker threads stall each other (a B = 64 step measured
  ~10x slower with 2 threads than with 1 while another process was busy), and the suite's figures stay stable.
- hypothesis runs derandomized under CI so a red build is reproducible.
- inductor compiles in the compiling process itself (``TORCHINDUCTOR_COMPILE_THREADS=1``, inherited by the stacks'
  processes; set before torch is imported, unless the environment names it): the same kernels, without a pool of
  compile worker processes started in each compiling process. A cold plant compile (``hydrosoft-stack compile``) took
  35.4 and 44.9 CPU-s with it against 39.5 and 50.6 without on the loaded 2-core machine, 33.7 against 35.2 idle;
  a cold launch of ``test_stack.py`` 70.0 and 69.9 CPU-s against 87.6 and 74.2, idle; the compiled-step check in a
  pytest worker gained nothing (docs/benchmarks.md, "The test suite").
- the suite runs on two pytest-xdist workers (``-n 2 --dist loadgroup --no-loadscope-reorder``, the README's
  command), which take the units of work in the order this file sorts them (``pytest_collection_modifyitems``):
  1. the ``stacks`` group, the modules that launch a whole stack or the real launcher on the split-stack hosts
     (``STACK_MODULES``), one test after another on one worker: two stacks never share two cores;
  2. the modules with a test marked ``slow``: a long test handed out last would leave the other worker idle while it
     runs (the PF rolling finding, 167 s, was among the last once);
  3. the rest.
  Each test is a unit of its own, except the tests that share a fixture of ours wider than a test (module or
  session scope: one stack launch, one simulated controller, one recorded run): those are one group, so the fixture
  is set up once, not once on each worker (both workers launched test_stack_requests.py's module stack). The
  groups are xdist's ``xdist_group`` marks, set before xdist reads them (``tryfirst``: set after, as they once
  were, xdist never saw them and every test went its own way). ``--no-loadscope-reorder`` keeps this order
  (xdist's own puts the units with the most tests first).
"""

import os
import shutil
import tempfile
from pathlib import Path

os.environ.setdefault("TORCHINDUCTOR_COMPILE_THREADS", "1")  # before torch (module docstring)

import pytest  # noqa: E402
import torch  # noqa: E402
from hypothesis import settings  # noqa: E402

TESTS = Path(__file__).resolve().parent
PROCESS_DIRS = ("services", "drivers")

settings.register_profile("ci", derandomize=True, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")


STACK_MODULES = ("test_*stack*.py", "test_two_hosts.py")
"""The modules under ``tests/services`` of the ``stacks`` group: each launches a whole stack, or the real launcher on
the loopback hosts and ports of the split-stack tests (``test_two_hosts.py`` shares them with
``test_two_hosts_stack.py``)."""


def shared_fixtures(item: pytest.Item) -> list[str]:
    """The fixtures of ours (defined under ``tests/``) wider than a test that ``item`` uses, each as the key of its
    one instance: ``NAME`` for a session fixture, ``MODULE::NAME`` for a module (or class, package) one."""
    keys = []
    info = getattr(item, "_fixtureinfo", None)  # a test function's; pytest keeps no public handle on it
    for name in getattr(item, "fixturenames", ()) if info is not None else ():
        definitions = info.name2fixturedefs.get(name)  # the definitions visible here, the used one last
        if not definitions or definitions[-1].scope == "function" or not definitions[-1].baseid:
            continue  # a test's own, a parameter, or a plugin's (their baseid is empty)
        keys.append(name if definitions[-1].scope == "session" else f"{item.nodeid.split('::')[0]}::{name}")
    return keys


def xdist_groups(items: list[pytest.Item]) -> dict[str, str]:
    """Each grouped item's xdist group by node id: ``stacks`` for ``STACK_MODULES``, else the first shared fixture
    (``shared_fixtures``) of the tests joined by sharing one, directly or through others; ungrouped items are left
    out."""
    parent: dict[str, str] = {}

    def root(key: str) -> str:
        while parent.setdefault(key, key) != key:
            key = parent[key]
        return key

    keys_of = {}
    for item in items:
        keys = shared_fixtures(item)
        path = item.path.resolve()
        if path.relative_to(TESTS).parts[0] == "services" and any(path.match(p) for p in STACK_MODULES):
            keys.insert(0, "stacks")
        for key in keys[1:]:
            first, other = root(keys[0]), root(key)
            if first != other:
                first, other = (other, first) if other == "stacks" else (first, other)
                parent[other] = first  # "stacks", or the first key seen, names the union
        keys_of[item.nodeid] = keys
    return {nodeid: root(keys[0]) for nodeid, keys in keys_of.items() if keys}


@pytest.hookimpl(tryfirst=True)  # before xdist's worker reads the xdist_group marks into the node ids
def pytest_collection_modifyitems(config, items):
    """Mark the xdist groups (``xdist_groups``) and sort the items in the order their units are handed out: the
    ``stacks`` group, the other modules with a ``slow`` test, the rest; each part in collection order, each group
    together where its first test is (module docstring)."""
    groups = xdist_groups(items)
    for item in items:
        if item.nodeid in groups:
            item.add_marker(pytest.mark.xdist_group(groups[item.nodeid]))
    slow_modules = {item.path for item in items if item.get_closest_marker("slow")}
    first_rank: dict[str, int] = {}
    for item in items:
        rank = 0 if groups.get(item.nodeid) == "stacks" else 1 if item.path in slow_modules else 2
        first_rank.setdefault(groups.get(item.nodeid, item.nodeid), rank)
    order = {unit: index for index, unit in enumerate(first_rank)}
    items.sort(key=lambda item: (first_rank[unit := groups.get(item.nodeid, item.nodeid)], order[unit]))


@pytest.fixture
def tmp_path():
    """A fresh directory with a short path, /tmp/hst-XXXXXXXX, removed after the test, in place of pytest's own.

    The stack's ipc:// endpoints are Unix sockets in a config's run_dir, whose paths may have at most 107 bytes;
    under pytest-xdist pytest's paths (/tmp/pytest-of-USER/pytest-N/popen-gwK/TEST_NAME0) leave too few of them.
    """
    root = Path(tempfile.mkdtemp(prefix="hst-", dir="/tmp"))
    yield root
    shutil.rmtree(root, ignore_errors=True)


@pytest.fixture(autouse=True)
def one_thread():
    """Run each test with one torch thread and restore the setting after."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture
def fresh_dynamo():
    """Start and end the test with empty dynamo caches and counters (the test counts graphs, or adds many)."""
    torch._dynamo.reset()
    yield
    torch._dynamo.reset()
