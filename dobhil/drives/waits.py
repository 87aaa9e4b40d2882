"""What every wait on a drive shares (the enable, an SDO answer, the preflight's
listening, the safe stop's confirmation): it reads the bus in slices of at most
:data:`WAIT_SLICE` s and asks its ``cancel`` between them, so a stop request (SIGINT,
SIGTERM) ends it within one slice, however long the wait itself (a profile's
``enable_timeout``, a preflight window). One blocking read of the whole wait would
hear the stop request only when the wait ends: seconds in which the operator's Ctrl-C
seems ignored while the drive may hold torque.

The times are the caller's ``clock`` (the drive's: simulated time in lockstep, where
the bus read itself moves time on), never the wall clock.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator

import can

from dobhil.errors import WaitCancelled

__all__ = ["WAIT_SLICE", "Cancel", "Read", "sliced_frames"]

#: longest single blocking read of a wait that can be cancelled
WAIT_SLICE = 0.02
#: ``cancel`` of the waits: the reason to stop waiting (e.g. "received SIGINT"), "" to go on
Cancel = Callable[[], str]
#: a bus read with a timeout in seconds (``can.BusABC.recv``): a frame or None
Read = Callable[[float], "can.Message | None"]


def sliced_frames(read: Read, clock: Callable[[], float], until: float, *,
                  cancel: Cancel | None = None, what: str = "",
                  between: Callable[[], object] | None = None, every: float = 0.0,
                  drain: bool = False) -> Iterator[can.Message]:
    """Every frame ``read`` gives until ``until`` on ``clock``, each read blocking at most
    :data:`WAIT_SLICE` s (and never past ``until``). The caller stops early by leaving
    the loop (the frame it waited for came).

    ``cancel`` is asked before every read: a reason raises :class:`WaitCancelled`
    ("<reason> while <what>", the reason alone without ``what``). ``between()``, when
    given, runs before the first read and again every ``every`` s (a keepalive the
    drive's watchdog needs while it is waited for); reads then end in time for it.
    ``drain``: once ``until`` passed, the frames already queued are still given (without
    blocking and without asking ``cancel``): a wait whose last read returned late (this
    process not scheduled) must not take for silence what the bus holds. What ``read``
    raises goes to the caller."""
    if between is not None and not every > 0:
        raise ValueError(f"sliced_frames: every must be > 0 s with between, got {every!r}")
    due = clock()
    while (now := clock()) < until:
        why = cancel() if cancel is not None else ""
        if why:
            raise WaitCancelled(f"{why} while {what}" if what else why)
        if between is not None and now >= due:
            between()
            due = now + every
        end = until if between is None else min(until, due)
        msg = read(max(0.0, min(end - now, WAIT_SLICE)))
        if msg is not None:
            yield msg
    while drain and (msg := read(0.0)) is not None:
        yield msg
