#!/usr/bin/env python3
"""Figures measured inside the kernel guest (tools/canvm), for ``tools/bench.py`` and the tests.

Run in the guest (``python tools/canvm/canvm.py run -- python tools/canvm/figures.py NAME...``):
each NAME is one measurement in :data:`FIGURES`; the JSON object of the results is printed on
one line prefixed ``figures:``. Every figure is a guest figure: under software emulation (TCG)
it says what this machine's emulated kernel did, not what a real one does.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]

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
    (dobhil/runtime/loop.py ``_next_deadline``/``_sleep_until``): ``time.sleep`` to ``spin`` s
    before each deadline, spin on the clock to it, and after an overrun skip to the next
    deadline not yet passed. Period error = wake-up minus deadline; overruns per 10,000
    deadlines, as the run counts them."""
    from dobhil.realtime import apply_realtime
    warnings = apply_realtime(RT_PRIORITY)
    clock = time.perf_counter
    t0 = clock()
    n = int(round(seconds / period))
    errors: list[float] = []
    k = overruns = 0
    while k < n:
        deadline = t0 + k * period
        remaining = deadline - clock() - spin
        if remaining > 0:
            time.sleep(remaining)
        while clock() < deadline:
            pass
        errors.append(clock() - deadline)
        nxt = k + 1
        now = clock()
        if now > t0 + nxt * period:
            overruns += 1
            nxt = int((now - t0) / period) + 1
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
