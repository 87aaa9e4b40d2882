"""Whether a bus sends periodic frames natively: outside this process's Python threads.

A drive whose cycle is triggered by a frame the host sends every period (CiA 402's SYNC)
wants that frame on time whatever the host's interpreter is doing. python-can's
``send_periodic`` gives it on every bus, but on most interfaces by a Python thread of
this very process (``ThreadBasedCyclicSendTask``): it needs the interpreter lock the
control loop holds, and is late by as much as the loop is busy -- then the drive is
better off with the SYNC sent by the loop itself right after each command, where its
timing is at least known. :func:`native_periodic` says which case a bus is:

- SocketCAN: the kernel's broadcast manager (BCM) sends it, found by ``isinstance``
  (the interface class is python-can's; it only exists where python-can can import it);
- our own buses that do it themselves say so with a class attribute
  ``native_periodic = True``: :class:`~dobhil.drives.emulated.LockstepBus` (simulated
  time) and the emulator process's :class:`~dobhil.emulator.pipe.PipeBus` (the child
  sends it, like a kernel would);
- anything else, wrappers included, is False unless the wrapper forwards the attribute
  itself (a wrapper's ``send_periodic`` is python-can's thread unless it says otherwise).
"""

from __future__ import annotations

from typing import Any

import can

__all__ = ["native_periodic"]


def _socketcan_class() -> type | None:
    """python-can's SocketCAN bus class, or None where it cannot be imported (not Linux)."""
    try:
        from can.interfaces.socketcan import SocketcanBus
    except Exception:   # ImportError, or an OSError of the socket module elsewhere
        return None
    return SocketcanBus


def native_periodic(bus: can.BusABC | Any) -> bool:
    """True when ``bus.send_periodic`` runs outside this process's Python threads."""
    if getattr(bus, "native_periodic", False) is True:
        return True
    socketcan = _socketcan_class()
    return socketcan is not None and isinstance(bus, socketcan)
