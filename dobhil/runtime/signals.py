"""SIGINT, SIGTERM, SIGHUP and SIGQUIT turn into a stop request the loop sees within one
cycle: each would otherwise end the process where it stands, the drive left with its last
torque command (SIGHUP: the terminal or the ssh session that started the run closed;
SIGQUIT: Ctrl-\\). Only SIGKILL and SIGSTOP cannot be caught: the drive's own watchdog is
the last line there (docs/hardware.md, "Stop reasons")."""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType

from dobhil.forkserver import STOP_SIGNALS
from dobhil.runtime.loop import StopRequest


@contextmanager
def stop_on_signals(request: StopRequest) -> Iterator[StopRequest]:
    """Route :data:`dobhil.forkserver.STOP_SIGNALS` to ``request`` while inside (main thread only)."""
    if threading.current_thread() is not threading.main_thread():
        yield request
        return

    def handler(signum: int, _frame: FrameType | None) -> None:
        request.set(f"received {signal.Signals(signum).name}")

    previous = {s: signal.signal(s, handler) for s in STOP_SIGNALS}
    try:
        yield request
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
