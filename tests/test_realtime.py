from __future__ import annotations

import os

import pytest

from dobhil.runtime import realtime
from dobhil.runtime.realtime import apply_realtime


def test_no_priority_asks_for_nothing(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(*_a: object) -> None:
        raise AssertionError("must not be called")
    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    assert apply_realtime(0) == []


@pytest.mark.skipif(not hasattr(os, "sched_setscheduler"), reason="Linux only")
def test_refused_priority_gives_a_warning_not_an_error(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(*_a: object) -> None:
        raise PermissionError(1, "Operation not permitted")
    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    monkeypatch.setattr(realtime, "_lock_memory", lambda: "mlockall refused (test)")
    warnings = apply_realtime(50)
    assert any("SCHED_FIFO priority 50 refused" in w for w in warnings)
    assert "mlockall refused (test)" in warnings
