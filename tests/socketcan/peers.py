"""Helpers of the tests that put other programs on a run's vcan: can-utils (``candump -l``,
``cansend``), a python-can bus of the test's own, a second dobhil run; and what they leave
behind read back (candump's log, a run's MCAP, ``dobhil emulate``'s last line).

Nothing here asserts a wall-clock figure: every wait is a bound (:data:`guest.START_TIMEOUT`).
"""

from __future__ import annotations

import contextlib
import io
import json
import re
import subprocess
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import pytest

from .guest import CANDUMP_OPTIONS, START_TIMEOUT, Dobhil, Proc, read_candump


@pytest.fixture(autouse=True)
def crashes_say_where(monkeypatch: pytest.MonkeyPatch) -> None:
    """A process a test starts that crashes (a SIGSEGV under software emulation) prints its
    Python stack: faulthandler, switched on through the environment the processes inherit.
    Autouse: importing it into a test module applies it there."""
    monkeypatch.setenv("PYTHONFAULTHANDLER", "1")


def start_candump(dobhil: Dobhil, iface: str) -> Proc:
    """``candump -l IFACE`` in the test's folder, once it has opened its log file (can-utils
    2020.11 names it ``candump-DATE_TIME.log`` and prints that it did)."""
    proc = dobhil.start(f"candump-{iface}", [*CANDUMP_OPTIONS, "-l", iface], program=["candump"])
    proc.wait_for("Enabling Logfile")
    return proc


def candump_log(dobhil: Dobhil) -> Path:
    """The one log file ``candump -l`` wrote in the test's folder."""
    logs = sorted(dobhil.tmp_path.glob("candump-*.log"))
    assert len(logs) == 1, logs
    return logs[0]


def cansend(iface: str, frame: str) -> None:
    """``cansend IFACE FRAME`` (can-utils' syntax: ``123#DEADBEEF``, FD ``123##1<data>``)."""
    out = subprocess.run(["cansend", iface, frame], capture_output=True, text=True, timeout=START_TIMEOUT)
    assert out.returncode == 0, f"cansend {iface} {frame}: {out.stdout}{out.stderr}"


def cansend_text(msg: can.Message) -> str:
    """A python-can message in cansend's syntax (classic frames)."""
    ident = f"{msg.arbitration_id:08X}" if msg.is_extended_id else f"{msg.arbitration_id:03X}"
    return f"{ident}#{bytes(msg.data).hex().upper()}"


def watch(bus: can.BusABC, match: Callable[[can.Message], bool], count: int = 1,
          timeout: float = START_TIMEOUT) -> list[can.Message]:
    """Read ``bus`` until ``count`` frames ``match``; those frames. Fails at ``timeout`` s."""
    deadline = time.monotonic() + timeout
    seen: list[can.Message] = []
    while len(seen) < count:
        left = deadline - time.monotonic()
        assert left > 0, f"{len(seen)} of {count} awaited frames on {bus.channel_info} within {timeout:.0f} s"
        msg = bus.recv(min(left, 1.0))
        if msg is not None and match(msg):
            seen.append(msg)
    return seen


def heartbeat_state(msg: can.Message, node: int) -> int | None:
    """The axis state of an ODrive (firmware 0.6) heartbeat from ``node``, else None."""
    from dobhil.drives.odrive import codec
    if msg.arbitration_id != codec.arbitration_id(node, codec.CmdId.HEARTBEAT) or msg.is_remote_frame \
            or len(msg.data) < 5:
        return None
    return int(codec.decode_message(msg, codec.Firmware.V0_6).axis_state)


def cli_json(args: list[str]) -> dict[str, Any]:
    """``dobhil ARGS --json`` run in this process (``dobhil.cli.main``, the console script's
    code; a guest process costs seconds to start): its JSON."""
    from dobhil.cli.main import main
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main([*args, "--json"]) == 0
    return dict(json.loads(out.getvalue()))


def cli(args: list[str]) -> str:
    """``dobhil ARGS`` run in this process; what it printed. Fails on a nonzero exit."""
    from dobhil.cli.main import main
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        status = main(args)
    assert status == 0, out.getvalue()
    return out.getvalue()


@dataclass(frozen=True)
class Recorded:
    """A run's MCAP, read once: every record of the topics asked for as (topic, log time
    [ns], payload), in log-time order."""

    records: list[tuple[str, int, dict[str, Any]]]
    metadata: dict[str, dict[str, str]]

    def topic(self, name: str) -> list[dict[str, Any]]:
        return [p for t, _, p in self.records if t == name]

    def timed(self, name: str) -> list[tuple[int, dict[str, Any]]]:
        return [(ns, p) for t, ns, p in self.records if t == name]

    def frames(self, name: str = "/can/rx") -> list[can.Message]:
        """The frames of ``/can/rx`` or ``/can/tx`` as python-can messages (bus stamps)."""
        from dobhil.recording.schemas import can_frame_message
        return [can_frame_message(p, ns) for ns, p in self.timed(name)]


def read_run(path: Path, topics: tuple[str, ...]) -> Recorded:
    from dobhil.recording.reader import open_log
    with open_log(path) as log:
        # the reader's decoding: the same dicts for protobuf and JSON logs
        records = [(t, ns, dict(p)) for t, ns, p in log.iter_messages(topics)]
        return Recorded(records, {k: dict(v) for k, v in log.metadata.items()})


#: ``dobhil emulate``'s last line (dobhil/cli/run_cmd.py)
EMULATOR_COUNTS = re.compile(r"emulator stopped: (\d+) frames received \((\d+) not addressed to node (\d+)\), "
                             r"(\d+) sent")


@dataclass(frozen=True)
class EmulatorCounts:
    received: int
    not_addressed: int
    node: int
    sent: int


def emulator_counts(proc: Proc) -> EmulatorCounts:
    """The counts a stopped ``dobhil emulate`` printed."""
    found = EMULATOR_COUNTS.search(proc.text())
    assert found, proc.text()
    return EmulatorCounts(*(int(g) for g in found.groups()))


@contextlib.contextmanager
def own_bus(iface: str, fd: bool = False) -> Iterator[can.BusABC]:
    """A python-can SocketCAN bus of the test's own (``fd``: CAN FD frames allowed)."""
    bus = can.Bus(interface="socketcan", channel=iface, fd=fd)
    try:
        yield bus
    finally:
        bus.shutdown()


__all__ = ["EmulatorCounts", "Recorded", "candump_log", "cansend", "cansend_text", "cli", "cli_json",
           "crashes_say_where", "emulator_counts", "heartbeat_state", "own_bus", "read_candump", "read_run",
           "start_candump", "watch"]
