"""Peak memory of ``dobhil montecarlo``'s own process for a given ``--runs``, after the same
wall time of running: a campaign that streams its plan, rows and table holds about the same
whatever ``--runs`` says.

    python tools/campaign_memory.py --runs 1000 1000000 1000000000 --seconds 15

Starts ``python -m dobhil montecarlo demo --runs N --duration 0.05 --vary
plant.inertia=normal:0.25:0.02 --workers 2 --out TMP`` for each N, lets it run ``--seconds``,
reads the process' peak resident set (``VmHWM`` in ``/proc/PID/status``, Linux) and how many
runs its progress lines counted, then ends it (SIGINT, then SIGKILL of its process group).
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def peak_kib(pid: int) -> int:
    text = Path(f"/proc/{pid}/status").read_text()
    match = re.search(r"VmHWM:\s+(\d+) kB", text)
    return int(match[1]) if match else -1


def measure(runs: int, seconds: float) -> tuple[int, str]:
    with tempfile.TemporaryDirectory() as tmp:
        command = [sys.executable, "-m", "dobhil", "montecarlo", "demo", "--runs", str(runs), "--duration", "0.05",
                   "--vary", "plant.inertia=normal:0.25:0.02", "--workers", "2", "--out", str(Path(tmp) / "out")]
        proc = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                                start_new_session=True)
        time.sleep(seconds)
        peak = peak_kib(proc.pid) if proc.poll() is None else -1
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGINT)
        try:
            _, err = proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            _, err = proc.communicate()
        said = [line for line in err.splitlines() if line.startswith("montecarlo:")]
        return peak, said[-1] if said else "(no progress line)"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, nargs="+", default=[1000, 1_000_000, 1_000_000_000])
    parser.add_argument("--seconds", type=float, default=15.0)
    args = parser.parse_args()
    for runs in args.runs:
        peak, said = measure(runs, args.seconds)
        print(f"--runs {runs}: peak RSS {peak / 1024:.0f} MiB after {args.seconds:g} s; last progress: {said}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
