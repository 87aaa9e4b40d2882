"""Scheduling of the control thread and of the work around it (Linux first).

- :func:`apply_realtime`: SCHED_FIFO and locked memory for the control thread, and its
  CPU affinity (``loop.cpu_affinity``). FIFO and locking need privileges (root or
  CAP_SYS_NICE / CAP_IPC_LOCK, or rtprio/memlock limits in /etc/security/limits.conf).
  When they are refused the run goes on with normal scheduling and the caller gets a
  warning line to show -- before the loop starts, never from inside it.
- :func:`lower_priority`: the other side -- the emulator thread (host timing), the
  ``dobhil emulate`` process and the recording writer process get a higher nice value,
  so the loop wins the CPU when it is short. Lowering the priority of one's own thread
  or process needs no privilege.
- :func:`run_in_background`: the writer process of a real-time run goes further, to
  SCHED_IDLE: it only gets CPU time nothing else wants, and a waking loop thread
  preempts it at once. A nice value alone is not enough: the scheduler (EEVDF, Linux
  6.6+) lets a running task finish its slice (about 3 ms here) before a waking one of
  higher priority gets the CPU. Measured on this 2-core machine, 8 interleaved rounds of
  6 s host-timed emulated runs: 1.0 overruns per 10,000 deadlines unlogged, 14.8 with
  the writer at nice +10, 1.5 with it at SCHED_IDLE. An unprivileged process cannot
  leave SCHED_IDLE again, so it is used only where the writer may lag (lossy, real time).

On Linux the nice value, the scheduling policy and the affinity are per *thread*; each
function here acts on the thread that calls it. Only the OS is below this module: the
runtime, the emulator and the command all use it, and none of them needs another to do so.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from dobhil.errors import ConfigError

_MCL_CURRENT, _MCL_FUTURE = 1, 2


#: nice increment of the recording writer process (lossy in real time: it may lag)
WRITER_PRIORITY_DROP = 10
#: nice increment of an emulator thread or process (it stands for the drive: a little only)
EMULATOR_PRIORITY_DROP = 3
#: nice decrement of an emulated drive's own process in feedback timing, where allowed: it
#: stands for a drive with a CPU of its own, which no other process on the host can delay
EMULATOR_PRIORITY_BOOST = 5


def apply_realtime(priority: int, cpu: int = -1) -> list[str]:
    """Pin the calling thread to ``cpu`` (-1: do not), ask for SCHED_FIFO at ``priority``
    (0: do not) and lock memory; return warnings. A CPU this process may not use is a
    ConfigError (bad input), not a warning."""
    warnings: list[str] = []
    if cpu >= 0:
        warnings.extend(w for w in (_pin(cpu),) if w)
    if priority <= 0:
        return warnings
    if not sys.platform.startswith("linux"):
        return [*warnings, f"loop.realtime_priority = {priority}: SCHED_FIFO is only available "
                "on Linux; running with normal scheduling"]
    return [*warnings, *(w for w in (_set_fifo(priority), _lock_memory()) if w)]


def lower_priority(increment: int = WRITER_PRIORITY_DROP, pid: int = 0) -> str:
    """Raise the nice value of the calling thread (``pid`` 0; Linux: this thread only,
    elsewhere the process) or of process ``pid`` (e.g. the writer process, from the
    process that started it: the writer itself imports nothing for it) by ``increment``.
    Returns a warning, or "" when done. Never raises."""
    return _renice(increment, pid, "lowered") if increment > 0 else ""


def raise_priority(boost: int = EMULATOR_PRIORITY_BOOST) -> str:
    """Lower the nice value of the calling process by ``boost`` where the OS allows it
    (root, CAP_SYS_NICE or RLIMIT_NICE: an ordinary user may not). Returns a warning, or ""
    when done. Never raises."""
    return _renice(-boost, 0, "raised") if boost > 0 else ""


def _renice(delta: int, pid: int, done: str) -> str:
    """Add ``delta`` to the nice value of ``pid`` (0: the calling thread), within -20..19."""
    if not hasattr(os, "setpriority"):
        return f"the priority cannot be {done} here"
    try:
        current = os.getpriority(os.PRIO_PROCESS, pid)
        os.setpriority(os.PRIO_PROCESS, pid, max(-20, min(current + delta, 19)))
    except OSError as exc:
        return f"priority not {done} ({exc.strerror or exc})"
    return ""


def run_in_background(pid: int) -> str:
    """Process ``pid`` to SCHED_IDLE (Linux), else nice +:data:`WRITER_PRIORITY_DROP`.
    Returns a warning, or "" when done. Never raises."""
    if hasattr(os, "SCHED_IDLE"):
        try:
            os.sched_setscheduler(pid, os.SCHED_IDLE, os.sched_param(0))
            return ""
        except OSError:
            pass
    return lower_priority(WRITER_PRIORITY_DROP, pid=pid)


def _pin(cpu: int) -> str:
    if not hasattr(os, "sched_setaffinity"):
        return f"loop.cpu_affinity = {cpu}: CPU affinity is not supported here; not pinned"
    allowed = sorted(os.sched_getaffinity(0))
    if cpu not in allowed:
        raise ConfigError(f"loop.cpu_affinity = {cpu}: not a CPU this process may use; "
                          f"allowed: {', '.join(map(str, allowed))} (or -1: no pinning)")
    try:
        os.sched_setaffinity(0, {cpu})
    except OSError as exc:
        return f"loop.cpu_affinity = {cpu} refused ({exc.strerror or exc}); not pinned"
    return ""


def _set_fifo(priority: int) -> str:
    try:
        top = os.sched_get_priority_max(os.SCHED_FIFO)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(min(priority, top)))
    except (PermissionError, OSError) as exc:
        return (f"SCHED_FIFO priority {priority} refused ({exc.strerror or exc}); running with "
                "normal scheduling (needs CAP_SYS_NICE or an rtprio limit)")
    return ""


def _lock_memory() -> str:
    name = ctypes.util.find_library("c")
    if not name:
        return "mlockall unavailable (no libc found); memory not locked"
    libc = ctypes.CDLL(name, use_errno=True)
    if libc.mlockall(_MCL_CURRENT | _MCL_FUTURE) != 0:
        err = ctypes.get_errno()
        return f"mlockall refused ({os.strerror(err)}); memory not locked (needs CAP_IPC_LOCK)"
    return ""


_BLAS_LOCK = threading.Lock()
_BLAS: dict[str, Any] = {"controller": None, "depth": 0, "limiter": None}


@contextmanager
def one_blas_thread() -> Iterator[None]:
    """BLAS (numpy's and scipy's OpenBLAS) on one thread while inside; nests, and the
    outermost exit restores what was there.

    Why: the identification's linear algebra is tiny -- 3x3 matrix exponentials (the ZOH
    of the Plant's 2x2 modes, dobhil.synthesis.controller.discretize), products with 2 or 3
    columns -- and a multithreaded OpenBLAS wakes its pool for each: ``scipy.linalg.expm``
    of a 3x3 measured 4-16 ms (min/median) on this busy 2-core machine with the default
    pool, 0.017 ms on one thread, and every fit evaluation builds the Plant's propagators
    afresh. threadpoolctl is the maintained public API to resize the pools at run time
    (``OPENBLAS_NUM_THREADS`` only acts before the library loads, and would be the whole
    process's business); its controller is made once (scanning the loaded libraries costs
    ms; scipy.linalg is imported first so its BLAS is among them) and ``limit`` then costs
    ~15 us, so this wraps every :func:`simulate_torque` and can wrap a whole fit. Callers
    running simulations in several threads hold it around the whole threaded region: the
    pools are process-wide, and one thread's outermost exit would restore them under the
    other's feet.
    """
    with _BLAS_LOCK:
        if _BLAS["depth"] == 0:
            if _BLAS["controller"] is None:
                import scipy.linalg  # noqa: F401 -- loaded first, so that its BLAS is among those found
                from threadpoolctl import ThreadpoolController
                _BLAS["controller"] = ThreadpoolController()
            _BLAS["limiter"] = _BLAS["controller"].limit(limits=1, user_api="blas")
        _BLAS["depth"] += 1
    try:
        yield
    finally:
        with _BLAS_LOCK:
            _BLAS["depth"] -= 1
            if _BLAS["depth"] == 0:
                _BLAS["limiter"].restore_original_limits()
                _BLAS["limiter"] = None
