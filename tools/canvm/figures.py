#!/usr/bin/env python3
"""Figures measured inside the kernel guest (tools/canvm), for ``tools/bench.py`` and the tests.

Run in the guest (``python tools/canvm/canvm.py run -- python tools/canvm/figures.py NAME...``):
each NAME is one measurement in :data:`FIGURES`; the JSON object of the results is printed on
one line prefixed ``figures:``. Every figure is a guest figure: under software emulation (TCG)
it says what this machine's emulated kernel did, not what a real one does.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from tests.socketcan.guest import Dumped

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]


#: name -> a function of no arguments returning a JSON-able mapping
FIGURES: dict[str, Callable[[], dict[str, Any]]] = {}


def figure(name: str) -> Callable[[Callable[[], dict[str, Any]]], Callable[[], dict[str, Any]]]:
    """Register a measurement under ``name``."""
    def register(fn: Callable[[], dict[str, Any]]) -> Callable[[], dict[str, Any]]:
        FIGURES[name] = fn
        return fn
    return register


# ----------------------------------------------------------------------------------------------
# real time in the guest: a 1 kHz run with SCHED_FIFO next to a bare loop that waits the same way

#: the run and the bare loop: SCHED_FIFO priority, period, length
RT_PRIORITY = 50
RT_PERIOD = 1e-3
RT_SECONDS = 10.0


def _percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    if not ordered:
        return math.nan
    return ordered[min(len(ordered) - 1, int(math.ceil(q / 100 * len(ordered))) - 1)]


def bare_loop(seconds: float = RT_SECONDS, period: float = RT_PERIOD, spin: float = 2e-4) -> dict[str, Any]:
    """A loop that does nothing but wait, exactly as the runtime's host timing waits
    (its own code: dobhil/runtime/deadlines.py ``next_deadline``/``sleep_until``): ``time.sleep`` to ``spin`` s
    before each deadline, spin on the clock to it, and after an overrun skip to the next
    deadline not yet passed. Period error = wake-up minus deadline; overruns per 10,000
    deadlines, as the run counts them."""
    import threading

    from dobhil.realtime import apply_realtime
    from dobhil.runtime.deadlines import next_deadline, sleep_until
    warnings = apply_realtime(RT_PRIORITY)
    clock, never = time.perf_counter, threading.Event()
    t0 = clock()
    n = int(round(seconds / period))
    errors: list[float] = []
    k = overruns = 0
    while k < n:
        deadline = t0 + k * period
        sleep_until(deadline, spin=spin, clock=clock, stop=never)
        errors.append(clock() - deadline)
        nxt = next_deadline(k, clock(), t0, period)
        overruns += nxt > k + 1
        k = nxt
    return {"deadlines": n, "wakes": len(errors), "overruns": overruns,
            "overruns_per_10k": overruns / n * 1e4, "period_error_p99_us": _percentile(errors, 99) * 1e6,
            "period_error_max_us": max(errors) * 1e6, "sched": warnings[0] if warnings else f"SCHED_FIFO {RT_PRIORITY}"}


def _dobhil(*args: str) -> list[str]:
    script = Path(sys.executable).parent / "dobhil"
    return [str(script) if script.is_file() else sys.executable, *([] if script.is_file() else ["-m", "dobhil"]), *args]


def rt_run(seconds: float = RT_SECONDS) -> dict[str, Any]:
    """``dobhil run`` of the MIT demo (a Damiao, host timing: one command, one reply per period)
    at 1 kHz for ``seconds`` over a vcan, ``loop.realtime_priority`` set, against ``dobhil
    emulate`` in another process. The figures are the run's own (its summary), with its stop
    reason: a run that did not last its duration is reported as such, never as a figure."""
    iface = f"vcanrt{os.getpid() % 1000}"
    subprocess.run(["bash", str(ROOT / "tools" / "setup_vcan.sh"), iface], check=True, capture_output=True)
    settings = ["--set", "drive.profile=dm4310", "--set", f"loop.period={RT_PERIOD}",
                "--set", "loop.feedback_timeout=0.5"]
    config = str(ROOT / "configs" / "mit-demo.yaml")
    with tempfile.TemporaryDirectory() as tmp:
        log = open(Path(tmp) / "emulate.out", "wb")
        emulator = subprocess.Popen(_dobhil("emulate", config, "--bus", f"socketcan:{iface}", *settings),
                                    stdout=log, stderr=subprocess.STDOUT)
        try:
            deadline = time.monotonic() + 120
            while b"emulating" not in (Path(tmp) / "emulate.out").read_bytes():
                if emulator.poll() is not None or time.monotonic() > deadline:
                    return {"error": (Path(tmp) / "emulate.out").read_text(errors="replace")[-300:]}
                time.sleep(0.1)
            run = subprocess.run(_dobhil("run", config, "--bus", f"socketcan:{iface}", *settings,
                                         "--set", f"loop.realtime_priority={RT_PRIORITY}",
                                         "--duration", str(seconds), "--summary-json"),
                                 capture_output=True, text=True, timeout=600)
        finally:
            emulator.terminate()
            emulator.wait(30)
            log.close()
            subprocess.run(["ip", "link", "del", "dev", iface], capture_output=True)
    lines = [line for line in run.stdout.splitlines() if line.startswith("{")]
    if not lines:
        return {"error": (run.stdout + run.stderr)[-300:]}
    summary = json.loads(lines[-1])
    timing = summary["loop_timing"]
    deadlines = int(summary["cycles"]) + int(summary.get("skipped", 0))
    return {"stop_reason": summary["stop_reason"], "stop_detail": summary["stop_detail"],
            "lasted": summary["stop_reason"] == "done", "cycles": summary["cycles"], "deadlines": deadlines,
            "overruns": summary["overruns"],
            "overruns_per_10k": summary["overruns"] / deadlines * 1e4 if deadlines else math.nan,
            "period_error_p99_us": timing["period_error_p99"] * 1e6,
            "period_error_max_us": timing["period_error_max"] * 1e6,
            "exec_time_p50_us": timing["exec_time_p50"] * 1e6,
            "warnings": [line for line in run.stderr.splitlines() if "realtime" in line or "SCHED" in line]}


@figure("rt_guest")
def rt_guest() -> dict[str, Any]:
    """The bare loop, the run, the bare loop again: the machine's state before and after."""
    return {"bare_before": bare_loop(), "run": rt_run(), "bare_after": bare_loop()}
# CiA 402 SYNC: the kernel's broadcast manager against the loop


def _guest() -> Any:
    """tests/socketcan/guest.py (the guest tests' configs, processes and candump reader), also
    when this file runs as a script (its folder, not the checkout, is then on sys.path)."""
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    import tests.socketcan.guest as guest
    return guest


@dataclass(frozen=True)
class Cia402Ids:
    """The frames of one CiA 402 node the SYNC figures read (CiA 301 pre-defined connection
    set, :class:`dobhil.drives.cia402.codec.Cob`; the numbers of drivers/cia402-emulated.yaml)."""

    sync: int
    rpdo: int
    status: int
    motion: int
    heartbeat: int
    emcy: int

    @classmethod
    def of(cls, profile: str = "cia402-emulated") -> Cia402Ids:
        from dobhil.drives.cia402.codec import Cob
        from dobhil.drives.load import load_profile
        loaded = load_profile(profile)
        node, rpdo, tpdo = loaded.node_id, int(loaded.options["rpdo"]), int(loaded.options["tpdo"])
        return cls(int(Cob.SYNC), Cob.rpdo(rpdo, node), Cob.tpdo(tpdo, node), Cob.tpdo(tpdo + 1, node),
                   int(Cob.HEARTBEAT) + node, Cob.emcy(node))


def rpdo_command(data: bytes) -> tuple[int, int]:
    """(controlword, target torque per mille) of a CST RPDO (dobhil.drives.cia402.codec.RPDO_CST)."""
    from dobhil.drives.cia402.codec import RPDO_CST_STRUCT
    controlword, torque = RPDO_CST_STRUCT.unpack_from(data)
    return int(controlword), int(torque)


def loop_window(frames: Sequence[Dumped], iface: str, ids: Cia402Ids,
                within: tuple[float, float] = (-math.inf, math.inf)) -> tuple[float, float] | None:
    """(start, end) of the cycles of a run on ``iface`` (candump's stamps, frames ``within``
    only): from its first RPDO with a torque (the enable's are zero) to its first later RPDO
    that is no longer Enable operation (the safe stop's quick stop). None: no such run."""
    from dobhil.drives.cia402.codec import Controlword
    start = None
    for f in frames:
        if f.iface != iface or f.arbitration_id != ids.rpdo or not within[0] <= f.stamp <= within[1]:
            continue
        controlword, torque = rpdo_command(f.data)
        if start is None and torque and controlword == Controlword.ENABLE_OPERATION:
            start = f.stamp
        elif start is not None and controlword != Controlword.ENABLE_OPERATION:
            return start, f.stamp
    return None


def stamps(frames: Sequence[Dumped], iface: str, arbitration_id: int, window: tuple[float, float]) -> list[float]:
    """candump's stamps of ``arbitration_id`` on ``iface`` within ``window`` (both ends inside)."""
    return [f.stamp for f in frames if f.iface == iface and f.arbitration_id == arbitration_id
            and window[0] <= f.stamp <= window[1]]


def deviations_us(times: Sequence[float], period: float) -> list[float]:
    """``|interval - period|`` [us] between consecutive ``times``."""
    return [abs(b - a - period) * 1e6 for a, b in zip(times, times[1:])]


def jitter(deviations: Sequence[float]) -> dict[str, Any]:
    """p50, p99 and max of ``deviations`` [us] (numpy's linear percentiles), and how many."""
    import numpy as np
    dev = np.asarray(deviations, dtype=float)
    if dev.size == 0:
        return {"intervals": 0, "p50_us": None, "p99_us": None, "max_us": None}
    return {"intervals": int(dev.size), "p50_us": float(np.percentile(dev, 50)),
            "p99_us": float(np.percentile(dev, 99)), "max_us": float(dev.max())}


@contextlib.contextmanager
def vcan_interfaces(names: Sequence[str]) -> Iterator[list[str]]:
    """Fresh vcan interfaces made by the README's tools/setup_vcan.sh, deleted afterwards."""
    made: list[str] = []
    try:
        for name in names:
            out = subprocess.run(["bash", str(ROOT / "tools" / "setup_vcan.sh"), name], capture_output=True,
                                 text=True)
            if out.returncode != 0:
                raise RuntimeError(f"tools/setup_vcan.sh {name} failed: {' '.join((out.stderr or out.stdout).split())}")
            made.append(name)
        yield made
    finally:
        for name in made:
            subprocess.run(["ip", "link", "del", "dev", name], capture_output=True)


@contextlib.contextmanager
def candump(path: Path, ifaces: Sequence[str]) -> Iterator[subprocess.Popen[bytes]]:
    """``candump -L IFACE...`` into ``path`` (its log format: the kernel's receive stamps,
    SO_TIMESTAMP, as ``candump -t a`` prints them) until the block ends."""
    with path.open("wb") as out:
        proc = subprocess.Popen(["candump", *_guest().CANDUMP_OPTIONS, "-L", *ifaces], stdout=out,
                                stderr=subprocess.DEVNULL)
    try:
        yield proc
    finally:
        proc.send_signal(signal.SIGINT)   # candump flushes and ends on SIGINT
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _last_json(text: str) -> dict[str, Any]:
    """The last line of ``text`` that is a JSON object ({} if none)."""
    for line in reversed(text.splitlines()):
        line = line.strip()
        if line.startswith("{"):
            with contextlib.suppress(ValueError):
                return dict(json.loads(line))
    return {}


def _run_facts(summary: dict[str, Any]) -> dict[str, Any]:
    keys = ("stop_reason", "stop_detail", "timing", "cycles", "overruns", "skipped", "sample_clock")
    return {k: summary[k] for k in keys if k in summary}


#: seconds each run of the SYNC figure lasts, and how many runs of each kind alternate
SYNC_RUN_S, SYNC_ROUNDS = 3.0, 2
#: the two ways a CiA 402 SYNC is sent, in the order the SYNC figure alternates them
SYNC_KINDS = ("bcm", "loop_sent")


@figure("bcm_sync_jitter")
def bcm_sync_jitter(work: Path | None = None, seconds: float = SYNC_RUN_S, rounds: int = SYNC_ROUNDS) -> dict[str, Any]:
    """CiA 402 SYNC interval jitter, ``|interval - loop.period|`` from candump's kernel receive
    stamps: the SYNC of SocketCAN's broadcast manager (``dobhil run``: its ``send_periodic``,
    dobhil.drives.periodic.native_periodic) against the SYNC the loop sends after each torque
    frame (the same session behind a wrapper without native periodic send, tools/canvm/loop_sync.py,
    loop.timing host). One vcan interface of one kernel, one emulated node (``dobhil emulate``;
    configs/cia402-demo.yaml at the guest's period of tests/socketcan/guest.py), ``rounds`` runs of
    each kind alternating, ``seconds`` each; intervals counted while each loop ran. (At once on two
    interfaces, each with its node, a guest under software emulation cannot keep both nodes
    answering every SYNC.) The top-level keys are the broadcast manager's; ``loop_sent`` has the
    loop's; ``runs`` what each run said of itself and when it ran. With ``work``, the files stay
    there (``candump``: the log)."""
    guest = _guest()
    with contextlib.ExitStack() as stack:
        kept = work is not None
        if work is None:
            work = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="bcm-sync-")))
        (iface,) = stack.enter_context(vcan_interfaces([f"sync{os.getpid() % 100000}"]))
        dump = work / "sync.candump"
        runs = _alternate_runs(guest, work, dump, iface, seconds, rounds)
        figures = sync_figures(guest.read_candump(dump), iface, runs, guest.PERIOD)
    figures.update(accel=guest.ACCEL, interface=iface, **({"candump": str(dump)} if kept else {}))
    return figures


def _alternate_runs(guest: Any, work: Path, dump: Path, iface: str, seconds: float,
                    rounds: int) -> list[dict[str, Any]]:
    """``rounds`` times a broadcast-manager run then a loop-sent one, one emulated node, under
    candump: what each said of itself (``kind``, wall-clock ``started`` and ``ended``)."""
    runner = guest.Dobhil(work)
    runs: list[dict[str, Any]] = []
    with candump(dump, [iface]):
        try:
            overlay = guest.guest_overlay(work, "cia402")
            config = str(guest.CONFIGS / guest.DEMOS["cia402"])
            runner.emulate(config, iface, overlay, protocol="cia402")
            common = [config, "--bus", f"socketcan:{iface}", "--set-file", str(overlay), "--duration", str(seconds)]
            commands = {"bcm": (["run", *common, "--summary-json"], None),
                        "loop_sent": ([str(HERE / "loop_sync.py"), *common], [sys.executable])}
            for n in range(rounds):
                for kind in SYNC_KINDS:
                    args, program = commands[kind]
                    started = time.time()
                    proc = runner.run(f"{kind}-{n}", args, guest.START_TIMEOUT + seconds, program)
                    runs.append({"kind": kind, "started": started, "ended": time.time(),
                                 **_run_facts(_last_json(proc.text()))})
        finally:
            runner.stop_all()
    return runs


def sync_figures(frames: Sequence[Dumped], iface: str, runs: list[dict[str, Any]], period: float) -> dict[str, Any]:
    """The jitter of each kind of SYNC over the cycles of its runs (each run's ``intervals``
    and ``window_s`` added to it); see :func:`bcm_sync_jitter`."""
    ids = Cia402Ids.of()
    found: dict[str, list[float]] = {kind: [] for kind in SYNC_KINDS}
    for run in runs:
        window = loop_window(frames, iface, ids, within=(run["started"], run["ended"]))
        dev = [] if window is None else deviations_us(stamps(frames, iface, ids.sync, window), period)
        run.update(intervals=len(dev), window_s=0.0 if window is None else window[1] - window[0])
        found[run["kind"]].extend(dev)
    return {"period_us": period * 1e6, "method": "candump -L kernel receive stamps, |SYNC interval - loop.period| "
            "while each loop ran", **jitter(found["bcm"]), "loop_sent": jitter(found["loop_sent"]), "runs": runs}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("names", nargs="*", help=f"figures to measure (default: all of {sorted(FIGURES)})")
    args = parser.parse_args(argv)
    unknown = [n for n in args.names if n not in FIGURES]
    if unknown:
        print(f"figures.py: unknown figure(s) {', '.join(unknown)}; known: {', '.join(sorted(FIGURES))}",
              file=sys.stderr)
        return 2
    out = {name: FIGURES[name]() for name in (args.names or sorted(FIGURES))}
    print("figures: " + json.dumps(out), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
