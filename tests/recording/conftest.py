"""Recording tests also fail if they leave a child process behind (the writer process)."""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from dobhil import forkserver


def child_processes() -> set[int]:
    """Pids of the processes this one started (zombies included: a child not waited for):
    its own children and the children of its fork servers (dobhil.forkserver forks the
    writer and the emulated drives for it), the servers themselves left out -- they stay
    on purpose, for the next child."""
    servers = forkserver.server_pids()
    parents = {os.getpid(), *servers}
    out = set()
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2:].split()
        if int(fields[1]) in parents:
            out.add(int(entry.name))
    return out - servers


@pytest.fixture(autouse=True)
def no_leaked_child_processes() -> Iterator[None]:
    if not Path("/proc/self/stat").exists():  # pragma: no cover - not Linux
        yield
        return
    before = child_processes()
    yield
    deadline = time.monotonic() + 2.0  # a subprocess the test killed may still be reaped
    leaked = child_processes() - before
    while leaked and time.monotonic() < deadline:
        time.sleep(0.05)
        leaked = child_processes() - before
    if leaked:
        pytest.fail(f"test left child processes behind: {sorted(leaked)}")
