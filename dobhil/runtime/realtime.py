"""Optional real-time scheduling of the control thread (Linux): SCHED_FIFO and locked memory.

Both need privileges (root or CAP_SYS_NICE / CAP_IPC_LOCK, or rtprio/memlock limits in
/etc/security/limits.conf). When they are refused the run goes on with normal
scheduling and the caller gets a warning line to show -- before the loop starts,
never from inside it.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys

_MCL_CURRENT, _MCL_FUTURE = 1, 2


def apply_realtime(priority: int) -> list[str]:
    """Ask for SCHED_FIFO at ``priority`` (0: do nothing) and lock memory; return warnings."""
    if priority <= 0:
        return []
    if not sys.platform.startswith("linux"):
        return [f"loop.realtime_priority = {priority}: SCHED_FIFO is only available on Linux; "
                "running with normal scheduling"]
    return [w for w in (_set_fifo(priority), _lock_memory()) if w]


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
