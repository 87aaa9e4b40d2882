from __future__ import annotations

import os
import sys
import threading
from collections.abc import Callable
from typing import Any

import pytest

from dobhil.errors import ConfigError
from dobhil import realtime
from dobhil.realtime import apply_realtime, lower_priority, run_in_background


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


def _in_thread(fn: Callable[[], dict[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    thread = threading.Thread(target=lambda: out.update(fn()))
    thread.start()
    thread.join()
    return out


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="per-thread nice: Linux")
def test_lower_priority_lowers_the_calling_thread_only() -> None:
    main_before = os.getpriority(os.PRIO_PROCESS, 0)

    def worker() -> dict[str, Any]:
        before = os.getpriority(os.PRIO_PROCESS, 0)
        warning = lower_priority(2)
        return {"before": before, "after": os.getpriority(os.PRIO_PROCESS, 0), "warning": warning}

    seen = _in_thread(worker)
    assert seen["warning"] == ""
    assert seen["after"] == min(seen["before"] + 2, 19)
    assert os.getpriority(os.PRIO_PROCESS, 0) == main_before
    assert lower_priority(0) == ""


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="Linux only")
def test_cpu_affinity_pins_the_calling_thread() -> None:
    cpu = max(os.sched_getaffinity(0))
    before = os.sched_getaffinity(0)
    seen = _in_thread(lambda: {"warnings": apply_realtime(0, cpu),
                               "cpus": os.sched_getaffinity(0)})
    assert seen["warnings"] == [] and seen["cpus"] == {cpu}
    assert os.sched_getaffinity(0) == before


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="Linux only")
def test_a_cpu_we_may_not_use_is_bad_input() -> None:
    missing = max(os.sched_getaffinity(0)) + 1
    with pytest.raises(ConfigError, match=f"loop.cpu_affinity = {missing}: not a CPU"):
        apply_realtime(0, missing)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="Linux")
def test_lower_priority_of_another_process() -> None:
    """The writer process is lowered from the process that started it."""
    import subprocess
    child = subprocess.Popen([sys.executable, "-c", "import sys; sys.stdin.read()"],
                             stdin=subprocess.PIPE)
    try:
        before = os.getpriority(os.PRIO_PROCESS, child.pid)
        assert lower_priority(4, pid=child.pid) == ""
        assert os.getpriority(os.PRIO_PROCESS, child.pid) == min(before + 4, 19)
    finally:
        child.communicate(b"")


@pytest.mark.skipif(not hasattr(os, "SCHED_IDLE"), reason="Linux scheduling policies")
def test_run_in_background_gives_another_process_idle_time_only() -> None:
    import subprocess
    child = subprocess.Popen([sys.executable, "-c", "import sys; sys.stdin.read()"], stdin=subprocess.PIPE)
    try:
        assert os.sched_getscheduler(child.pid) == os.SCHED_OTHER
        assert run_in_background(child.pid) == ""
        assert os.sched_getscheduler(child.pid) == os.SCHED_IDLE
    finally:
        child.communicate(b"")


@pytest.mark.skipif(not hasattr(os, "setpriority"), reason="no nice values here")
def test_raise_priority_where_allowed_else_one_warning() -> None:
    """In a child (pytest keeps its own priority): the nice value drops by the boost where
    the OS allows it (root, CAP_SYS_NICE), else it stays and one warning says why."""
    import subprocess
    code = ("import os; from dobhil.realtime import raise_priority; before = os.getpriority(os.PRIO_PROCESS, 0);"
            " warning = raise_priority(5); print(before, os.getpriority(os.PRIO_PROCESS, 0), repr(warning))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split(" ", 2)
    before, after, warning = int(out[0]), int(out[1]), out[2].strip()
    if warning == "''":
        assert after == max(before - 5, -20)
    else:
        assert after == before and "priority not raised" in warning
    assert realtime.raise_priority(0) == ""   # no boost asked: nothing done
