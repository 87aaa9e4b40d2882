"""Fail any test that leaks a non-daemon thread or a python-can bus it did not shut down."""

from __future__ import annotations

import logging
import threading
import weakref
from collections.abc import Iterator
from typing import Any

import can
import pytest


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
