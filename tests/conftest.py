"""Fail any test that leaks a non-daemon thread or a python-can bus it did not shut down; a
module's in-process Dask cluster (``dask_client``) for the tests that run work on Dask; no
wall-clock deadline on hypothesis' examples; the tests of ``tests/socketcan`` run in the kernel
guest (tools/canvm/pytest_canvm.py); the tests listed in ``tests/slow-tests.txt`` marked ``slow``
(``pytest -m "not slow"``: the edit loop's run); ``python -m dobhil`` forked from one server
(``dobhil_forks``)."""

from __future__ import annotations

import importlib.util
import logging
import os
import signal
import sys
import tempfile
import threading
import weakref
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
import pytest
from dobhil_forks import DobhilForks
from hypothesis import settings
from slow_list import SLOW_LIST, heaviest_first, is_listed, slow_entries, slow_seconds
from threadpoolctl import threadpool_limits

# Hypothesis fails an example that takes over 200 ms by default: a wall-clock assertion, which a
# busy CI machine breaks (seen: the first example of a CiA 402 codec test took 465 ms under load,
# 22 ms when repeated). The suite must pass on a busy machine, so no deadline anywhere.
settings.register_profile("dobhil", deadline=None)
settings.load_profile("dobhil")

# PYTHONDONTWRITEBYTECODE (set on this machine and by .ci/run, to keep __pycache__ out of the
# tree) makes every process compile from source: each xdist worker rewrote and compiled all
# test modules (collection 19-23 s of CPU per worker, 7 s with their bytecode cached), and every
# `python -m dobhil` the tests start compiled dobhil again. The tests keep the tree as clean:
# bytecode goes to a cache of this user's in the temporary directory (sys.pycache_prefix,
# which pytest's assertion rewriting honours too), for this process and the ones it starts.
if sys.dont_write_bytecode and not sys.pycache_prefix:
    _BYTECODE = str(Path(tempfile.gettempdir()) / f"dobhil-test-bytecode-{os.getuid()}")
    sys.dont_write_bytecode = False
    sys.pycache_prefix = _BYTECODE
    os.environ.pop("PYTHONDONTWRITEBYTECODE", None)
    os.environ["PYTHONPYCACHEPREFIX"] = _BYTECODE

# BLAS on one thread, in this process and the ones it starts: the suite runs on two xdist
# workers on two cores, and each numpy call on a small matrix woke a second OpenBLAS thread that
# spun on the other worker's core (measured: tests/analysis, tests/test_quantisation.py and
# tests/campaign/test_figures.py with -n 2 took 49.6 s of CPU and 33.0 s wall, 36.6 s and
# 26.3 s with OPENBLAS_NUM_THREADS=1; the same results). A test about BLAS threads sets its own
# limit (tests/identify/test_model.py).
for _name in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OMP_NUM_THREADS"):
    os.environ.setdefault(_name, "1")
threadpool_limits(limits=1, user_api="blas")

# A shell without job control starts a background command with SIGINT ignored, and an ignored
# signal stays ignored across exec: every process the tests start would then ignore the Ctrl-C
# (SIGINT) that many tests send to stop it (`python -m can.logger`, `dobhil log serve`, ...),
# and hang. Seen: `.ci/run &` from a script, four such tests timed out. A handler here is
# reset to the default on exec, so the children get Python's own KeyboardInterrupt again.
if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


#: the kernel guest's tests (tools/canvm/pytest_canvm.py puts them first: they wait for the guest)
GUEST_TESTS = "tests/socketcan/"


def pytest_configure(config: pytest.Config) -> None:
    """The kernel guest's plugin, loaded by path: tools/ is not a package."""
    path = Path(__file__).resolve().parents[1] / "tools" / "canvm" / "pytest_canvm.py"
    spec = importlib.util.spec_from_file_location("dobhil_pytest_canvm", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    config.pluginmanager.register(module.CanvmPlugin(config), "canvm")


_SLOW_ENTRIES = slow_entries(SLOW_LIST.read_text(encoding="utf-8"))


def pytest_itemcollected(item: pytest.Item) -> None:
    """Mark a listed test ``slow`` as it is collected: ``-m`` deselects in pytest's own
    ``pytest_collection_modifyitems``, which sees only the marks already there."""
    if is_listed(item.nodeid, _SLOW_ENTRIES):
        item.add_marker(pytest.mark.slow)


@pytest.hookimpl(trylast=True)   # after the guest's plugin has put its tests first
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Run the files with the most listed seconds first (:func:`slow_list.heaviest_first`),
    the kernel guest's tests still ahead of all."""
    guest = [item for item in items if item.nodeid.startswith(GUEST_TESTS)]
    host = [item for item in items if not item.nodeid.startswith(GUEST_TESTS)]
    order = heaviest_first([item.nodeid for item in host], slow_seconds(SLOW_LIST.read_text(encoding="utf-8")))
    items[:] = guest + [host[i] for i in order]


class _ShutdownWarnings(logging.Handler):
    """python-can logs this when a bus is garbage-collected without shutdown()."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.names: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        if "was not properly shut down" in record.getMessage():
            self.names.append(record.getMessage())


@pytest.fixture(autouse=True)
def no_leaked_threads_or_buses(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    threads_before = set(threading.enumerate())
    created: list[weakref.ref[can.BusABC]] = []
    original_init = can.BusABC.__init__

    def tracking_init(self: can.BusABC, *args: Any, **kwargs: Any) -> None:
        created.append(weakref.ref(self))
        original_init(self, *args, **kwargs)

    monkeypatch.setattr(can.BusABC, "__init__", tracking_init)
    handler = _ShutdownWarnings()
    can_log = logging.getLogger("can")
    can_log.addHandler(handler)
    try:
        yield
    finally:
        can_log.removeHandler(handler)
    threads = [
        t.name for t in threading.enumerate()
        if t not in threads_before and t.is_alive() and not t.daemon
    ]
    buses = [b for b in (ref() for ref in created) if b is not None and not b._is_shutdown]
    for bus in buses:
        bus.shutdown()
    leaks = threads + [f"open {type(b).__name__} {b.channel_info}" for b in buses] + handler.names
    if leaks:
        pytest.fail(f"test leaked: {', '.join(leaks)}")


@pytest.fixture(scope="module")
def dask_client() -> Iterator[Any]:
    """A client of an in-process Dask cluster, 2 workers of one thread (the 2-core CI), made
    once per module that asks for it and closed at its end. Not once per session: while an
    in-process cluster lives, its event loops share the interpreter lock with every test that
    runs after it in that process (measured: lockstep runs 5,200-5,400 cycles/s with one
    alive, 7,300-8,100 without). Through :func:`dobhil.cluster.open_client`, so the tests run
    the code the commands run."""
    from dobhil.cluster import open_client
    with open_client(workers=2, processes=False) as client:
        yield client


@pytest.fixture(scope="session")
def dobhil_forks() -> Iterator[DobhilForks]:
    """``python -m dobhil`` as a process of its own, forked from a server that imported dobhil
    once per test process (tests/dobhil_forks.py: a new process' imports are most of a bad
    input's CPU). For the tests of what a command prints and exits with; a test of start-up
    itself (a first import's warnings, a signal during start-up) starts a new interpreter."""
    with DobhilForks() as forks:
        yield forks
