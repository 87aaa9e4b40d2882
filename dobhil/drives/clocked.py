"""A python-can bus whose ``recv`` timeout runs on the bus's own clock.

python-can's :meth:`can.BusABC.recv` (``can/bus.py``) calls the hook ``_recv_internal``
and, while a frame does not pass :meth:`~can.BusABC.set_filters`, calls it again with
``timeout - (time.time() - start)``: its remaining time is wall-clock time. On a bus whose
time is simulated (:class:`~dobhil.drives.emulated.LockstepBus`, and any wrapper of one)
that is wrong both ways: after a filtered frame the wait would start again in simulated
time (it ends late), and after the simulated deadline ``recv`` would call the hook again
for the wall-clock seconds still left, each call advancing the simulation further.

So on a :class:`ClockedBus` the hook does the whole wait: ``_recv_internal(timeout)``
waits ``timeout`` seconds of :meth:`ClockedBus.clock`, drops the frames the filters
reject (python-can's software filter, the very one ``BusABC.recv`` applies, which
python-can's subclasses call too) and says so (``already_filtered`` True); ``recv`` returns what the
hook returns, without python-can's wall-clock retry loop (and without its debug log of
every frame, which on the control path costs as much as the frame). Everything else of
the python-can contract holds: ``set_filters`` (and ``can_filters=``), ``send_periodic``,
iteration, ``shutdown``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import can
from can.typechecking import CanFilters

__all__ = ["ClockedBus", "bus_clock"]


def bus_clock(bus: can.BusABC | Any) -> Callable[[], float]:
    """The clock ``bus``'s timeouts run on: its ``clock()`` if it has one (a lockstep bus:
    simulated seconds, a :class:`ClockedBus` wrapper: its inner bus's), else ``time.monotonic``."""
    clock = getattr(bus, "clock", None)
    return clock if callable(clock) else time.monotonic


class ClockedBus(can.BusABC):
    """Base of dobhil's buses that wait on a clock of their own (see the module's text).

    A subclass implements :meth:`clock` and ``_recv_internal`` as said there: the whole
    ``timeout`` on :meth:`clock`, filters applied with :meth:`passes`."""

    #: whether :meth:`~can.BusABC.set_filters` set any filter (the hot path skips the check)
    filtering = False

    def clock(self) -> float:
        """Now, in the seconds this bus's ``recv`` timeouts are counted in."""
        raise NotImplementedError

    def _apply_filters(self, filters: CanFilters | None) -> None:
        # python-can's hook for a bus that filters itself (set_filters calls it)
        self.filtering = bool(filters)

    def passes(self, msg: can.Message) -> bool:
        """Whether ``msg`` passes the filters of :meth:`~can.BusABC.set_filters`."""
        return not self.filtering or self._matches_filters(msg)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        """The next frame that passes the filters within ``timeout`` seconds of
        :meth:`clock` (None: wait for ever), or None."""
        return self._recv_internal(timeout)[0]
