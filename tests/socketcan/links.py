"""The kernel's side of the fault tests: ``ip`` and ``tc`` on the guest's CAN interfaces,
vxcan pairs, and candump as the record of what the kernel really delivered.

Why a vxcan pair where a qdisc must act on the drive's frames only: on a vcan, the CAN core
loops a sent frame back to every reader of the interface as soon as the queueing discipline
accepted it (``can_send`` in the kernel's net/can/af_can.c hands a clone to ``netif_rx`` for an
interface without IFF_ECHO), so a netem delay on a vcan delays nothing a reader sees; a vxcan
hands each frame to its peer in its transmit function, after the qdisc
(drivers/net/can/vxcan.c), so a qdisc on the emulator's end shapes exactly the frames the
emulator sends and none of the host's, which leave by the other end. Each end still loops its
own frames back to its own readers at once: candump on the emulator's end stamps a frame when
the emulator sent it, candump on the host's end when the host got it.

Why a prio qdisc with an ``em_canid`` filter on top: it puts the fault (netem, tbf) on the
drive's feedback frames only, by CAN id (tc-ematch(8), the kernel's net/sched/em_canid.c);
the drive's other frames -- heartbeats, SDO answers while the run sets the drive up -- pass
untouched, so a lost frame is a lost sample and never a start-up that fails by chance.
"""

from __future__ import annotations

import bisect
import itertools
import json
import os
import re
import subprocess
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import maximum_bipartite_matching

from .guest import CANDUMP_OPTIONS, START_TIMEOUT, Dumped, read_candump

_names = itertools.count()
#: the band of the prio qdisc the fault sits in (bands 1 and 2 carry everything else)
FAULT_BAND = "1:3"


def sh(*args: str) -> str:
    """Run ``ip``/``tc`` (or any tool); its stdout. Fails the test with the tool's words."""
    done = subprocess.run(list(args), capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, f"{' '.join(args)}: exit {done.returncode}: {done.stderr.strip()}"
    return done.stdout


@contextmanager
def vxcan_pair() -> Iterator[tuple[str, str]]:
    """A fresh vxcan pair, both ends up: (the drive's end, the host's end); deleted after."""
    n = f"{next(_names)}x{os.getpid() % 1000}"
    drive_end, host_end = f"vxd{n}", f"vxh{n}"
    sh("ip", "link", "add", "dev", drive_end, "type", "vxcan", "peer", "name", host_end)
    try:
        sh("ip", "link", "set", drive_end, "up")
        sh("ip", "link", "set", host_end, "up")
        yield drive_end, host_end
    finally:
        subprocess.run(["ip", "link", "del", "dev", drive_end], capture_output=True)


def fault_on_ids(iface: str, ids: Sequence[int], *qdisc: str) -> None:
    """Put the queueing discipline ``qdisc`` (e.g. ``netem delay 3ms``) on the frames of
    ``ids`` leaving ``iface``: a prio root whose every priority maps to its first band, the
    fault in its third band, and an em_canid filter sending those ids there."""
    sh("tc", "qdisc", "add", "dev", iface, "root", "handle", "1:", "prio", "bands", "3",
       "priomap", *["0"] * 16)
    sh("tc", "qdisc", "add", "dev", iface, "parent", FAULT_BAND, "handle", "30:", *qdisc)
    match = " ".join(f"sff 0x{i:03x}:0x7ff" for i in ids)
    sh("tc", "filter", "add", "dev", iface, "parent", "1:", "prio", "1", "protocol", "can",
       "basic", "match", f"canid({match})", "classid", FAULT_BAND)


def change_fault(iface: str, *qdisc: str) -> None:
    """Change the fault of :func:`fault_on_ids` in place (``tc qdisc change``)."""
    sh("tc", "qdisc", "change", "dev", iface, "parent", FAULT_BAND, "handle", "30:", *qdisc)


def qdisc_stats(iface: str, handle: str = "30:") -> dict[str, Any]:
    """The kernel's counters of one qdisc (``tc -s -j qdisc show``): packets, drops, ..."""
    for entry in json.loads(sh("tc", "-s", "-j", "qdisc", "show", "dev", iface)):
        if entry.get("handle") == handle:
            return dict(entry)
    raise AssertionError(f"no qdisc {handle} on {iface}")


def wait_frames(iface: str, ident: int, count: int, timeout: float = START_TIMEOUT) -> None:
    """Until ``count`` frames of id ``ident`` went over ``iface`` (candump -n counts them)."""
    proc = subprocess.Popen(["candump", "-n", str(count), f"{iface},{ident:03x}:7ff"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        proc.wait(timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        raise AssertionError(f"fewer than {count} frames 0x{ident:03x} on {iface} within {timeout:.0f} s") from None
    assert proc.returncode == 0, proc.stderr.read() if proc.stderr else proc.returncode


@dataclass
class Capture:
    """candump -L of some interfaces into a file, for the whole of a ``with`` block."""

    path: Path
    ifaces: tuple[str, ...]
    proc: subprocess.Popen[bytes] | None = None

    def __enter__(self) -> Capture:
        with self.path.open("wb") as out:
            self.proc = subprocess.Popen(["candump", *CANDUMP_OPTIONS, "-L", *self.ifaces], stdout=out,
                                         stderr=subprocess.STDOUT)
        time.sleep(0.5)  # candump opened its sockets (it prints nothing until a frame)
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            time.sleep(0.5)  # the last frames are read
            self.proc.terminate()
            self.proc.wait(15)

    def frames(self, iface: str, ident: int | None = None) -> list[Dumped]:
        return [f for f in read_candump(self.path)
                if f.iface == iface and (ident is None or f.arbitration_id == ident)]


def one_line(text: str, pattern: str) -> str:
    """The only line of ``text`` matching ``pattern`` (fails on none or several)."""
    lines = [line for line in text.splitlines() if re.search(pattern, line)]
    assert len(lines) == 1, f"expected one line matching {pattern!r}, got {len(lines)}:\n{text}"
    return lines[0]


def pause(stamps: Sequence[float]) -> float:
    """The middle of the longest silence in ``stamps``: where one run ended and the next began."""
    gaps = [(b - a, (a + b) / 2) for a, b in zip(stamps, stamps[1:])]
    return max(gaps)[1]


def sample_latencies(syncs: Sequence[Dumped], samples: Sequence[Dumped]) -> list[tuple[float, ...]]:
    """Per sample frame, the latencies a CiA 402 host may measure for it (``Feedback.
    sample_latency``, dobhil/drives/cia402/drive.py ``_sampled_at``), from the kernel's stamps
    on one interface: since the newest SYNC stamped before it, or -- when the host's socket
    got the frame before that SYNC (on two processors frames reach sockets out of their
    stamps' order) -- since the SYNC before."""
    stamps = [f.stamp for f in syncs]
    out = []
    for frame in samples:
        i = bisect.bisect_right(stamps, frame.stamp) - 1
        if i >= 0:
            out.append(tuple(frame.stamp - stamps[j] for j in (i, i - 1) if j >= 0))
    return out


def transit_delays(sent: Sequence[Dumped], received: Sequence[Dumped], least: float) -> list[float]:
    """For each frame received at the far end, the time since the same frame (id and data)
    was sent at the near end: the newest such frame sent at least ``least`` s before (netem
    never delivers sooner than its delay minus its jitter)."""
    stamps = [f.stamp for f in sent]
    out = []
    for frame in received:
        i = bisect.bisect_right(stamps, frame.stamp - least) - 1
        while i >= 0 and (sent[i].arbitration_id, sent[i].data) != (frame.arbitration_id, frame.data):
            i -= 1
        assert i >= 0, f"frame {frame} received but never sent at least {least} s before"
        out.append(frame.stamp - sent[i].stamp)
    return out


def unmatched(measured: Sequence[float], truth: Sequence[tuple[float, ...]], within: float) -> list[float]:
    """The values of ``measured`` left over when each is paired with a distinct entry of
    ``truth`` one of whose values it equals, give or take ``within``, as many as can be (a
    maximum bipartite matching: scipy's ``maximum_bipartite_matching``). Empty: every
    measured value is one of the truth's, each entry used once.

    Why a matching and not the first free entry in increasing order: an entry has two
    values (a sample from its SYNC, or from the one before), and at microsecond tolerance
    a short latency can take the entry whose longer value another measurement needs while
    a twin entry with the same short value stays free; a matching finds the pairing
    whenever one exists."""
    flat = sorted((value, i) for i, values in enumerate(truth) for value in values)
    values = [value for value, _ in flat]
    rows: list[int] = []
    cols: list[int] = []
    for row, value in enumerate(measured):
        for _, entry in flat[bisect.bisect_left(values, value - within):bisect.bisect_right(values, value + within)]:
            rows.append(row)
            cols.append(entry)
    graph = csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(len(measured), len(truth)))
    pair = maximum_bipartite_matching(graph, perm_type="column")
    return [value for value, entry in zip(measured, pair) if entry < 0]
