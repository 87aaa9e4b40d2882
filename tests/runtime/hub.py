"""The python-can-remote hub the cross-process tests share (loopback only): the
``hub`` fixture (in ``conftest.py``) and the helpers to start children on it."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from .helpers import REPO

STARTUP_TIMEOUT = 30.0   # s, a bound for a loaded CI machine, not a measurement


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def accepts(port: int) -> bool:
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=0.5):
            return True
    except OSError:
        return False


def child_env() -> dict[str, str]:
    """Children import this checkout of dobhil, whatever is installed."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
    return env


def wait_for_emulator(proc: subprocess.Popen[bytes], out: Path, protocol: str = "odrive") -> None:
    """Until ``dobhil emulate`` (writing to ``out``) says it runs; fails if it died or is slow."""
    deadline = time.monotonic() + STARTUP_TIMEOUT
    while f"emulating {protocol}" not in out.read_text(errors="replace"):
        assert proc.poll() is None, out.read_text(errors="replace")
        assert time.monotonic() < deadline, "dobhil emulate did not start"
        time.sleep(0.05)


def stop_process(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=10)


@contextmanager
def hub_process(tmp_path: Path) -> Iterator[tuple[subprocess.Popen[bytes], int]]:
    """``python -m can_remote`` serving a virtual channel on 127.0.0.1: its process (a test
    may stop or freeze it mid-run) and its port."""
    port = free_port()
    log = (tmp_path / "hub.log").open("wb")
    proc = subprocess.Popen(
        [sys.executable, "-m", "can_remote", "-i", "virtual", "-c", f"dobhil-xp-{port}",
         "-H", "127.0.0.1", "-p", str(port)],
        stdout=log, stderr=subprocess.STDOUT, env=child_env(), cwd=REPO)
    try:
        deadline = time.monotonic() + STARTUP_TIMEOUT
        while not accepts(port):
            if proc.poll() is not None or time.monotonic() > deadline:
                pytest.skip(f"python-can-remote hub did not start on 127.0.0.1:{port}: "
                            f"{(tmp_path / 'hub.log').read_text(errors='replace')[-300:]!r}")
            time.sleep(0.05)
        yield proc, port
    finally:
        stop_process(proc)
        log.close()


def serve_hub(tmp_path: Path) -> Iterator[int]:
    """The hub of :func:`hub_process`; yields its port."""
    with hub_process(tmp_path) as (_proc, port):
        yield port


