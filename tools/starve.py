#!/usr/bin/env python3
"""Real-time emulated runs on a busy machine: how many complete, and who gets the blame.

``python tools/starve.py`` runs ``dobhil run demo --emulate --duration 2`` 50 times, one
after the other, while two other real-time emulated runs (restarted as they end; the
measured config, or ``--background CONFIG``) and one CPU-bound process run alongside --
what parallel jobs on a 2-core CI box do (pure CPU hogs alone do not starve a run: the
scheduler favours processes that sleep). It prints how many runs completed their
duration, the stop reasons of the others, and how many stops blamed the drive
(``feedback_timeout``, ``drive_fault``) although the host was the one too slow; ``--json``
prints one JSON object. ``--duration 0`` runs the config's own duration; ``--log``
records each measured run (to a temporary file), as ``dobhil run identify-free --emulate
--log free.mcap`` does::

    python tools/starve.py --config identify-free --duration 0 --background demo --log

The target: at least 48 of 50 complete, and no stop blames the drive for a starved
emulator (``host_too_slow`` says so instead).

Everything started here is stopped here, by its own process group.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: stop reasons that put the blame on the drive
DRIVE_BLAMED = ("feedback_timeout", "drive_fault")


#: ``--set`` items for every run (``--set loop.spin=0`` ...)
SETTINGS: list[str] = []


def run_command(config: str, duration: float, json_out: bool = True, log: str = "") -> list[str]:
    return [sys.executable, "-m", "dobhil", "run", config, "--emulate",
            *(["--duration", str(duration)] if duration > 0 else []),
            *(x for item in SETTINGS for x in ("--set", item)),
            *(["--log", log] if log else []),
            *(["--summary-json"] if json_out else [])]


def start_background(config: str, duration: float, parallel: int, hogs: int) -> list[subprocess.Popen[bytes]]:
    """``parallel`` restarting real-time runs and ``hogs`` busy loops, each in its own group."""
    loop = (f"import subprocess, sys\nwhile True:\n"
            f"    subprocess.run({run_command(config, duration, False)!r}, stdout=subprocess.DEVNULL,"
            f" stderr=subprocess.DEVNULL)\n")
    started = []
    for _ in range(parallel):
        started.append(subprocess.Popen([sys.executable, "-c", loop], cwd=ROOT, start_new_session=True))
    for _ in range(hogs):
        started.append(subprocess.Popen([sys.executable, "-c", "while True: pass"], start_new_session=True))
    return started


def stop_background(started: list[subprocess.Popen[bytes]]) -> None:
    for proc in started:
        try:
            os.killpg(proc.pid, signal.SIGTERM)   # the group this tool made for it
        except ProcessLookupError:
            pass
    for proc in started:
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def one_run(config: str, duration: float, log: str = "") -> dict[str, object]:
    done = subprocess.run(run_command(config, duration, log=log), cwd=ROOT, capture_output=True, text=True)
    try:
        info = json.loads(done.stdout.strip().splitlines()[-1])
    except (json.JSONDecodeError, IndexError):
        return {"stop_reason": "no_summary", "stop_detail": done.stderr.strip()[-300:]}
    return info  # type: ignore[no-any-return]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=50)
    parser.add_argument("--duration", type=float, default=2.0)
    parser.add_argument("--parallel", type=int, default=2, help="real-time runs alongside")
    parser.add_argument("--hogs", type=int, default=1, help="CPU-bound processes alongside")
    parser.add_argument("--config", default="demo")
    parser.add_argument("--background", default="", metavar="CONFIG",
                        help="config of the real-time runs alongside (default: --config)")
    parser.add_argument("--log", action="store_true", help="record each measured run (--log)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a config override for every run (repeatable)")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    SETTINGS.extend(args.set)
    load_before = os.getloadavg()
    background = start_background(args.background or args.config, 2.0 if args.background else args.duration,
                                  args.parallel, args.hogs)
    folder = tempfile.TemporaryDirectory() if args.log else None
    log = str(Path(folder.name) / "run.mcap") if folder is not None else ""
    reasons: Counter[str] = Counter()
    details: list[str] = []
    try:
        time.sleep(1.0)   # the background is running before the first measured run
        for i in range(args.runs):
            if log and os.path.exists(log):
                os.unlink(log)   # a run refuses to overwrite a recording
            info = one_run(args.config, args.duration, log)
            reason = str(info["stop_reason"])
            reasons[reason] += 1
            if reason != "done":
                details.append(f"run {i + 1}: {reason}: {info.get('stop_detail', '')}")
            if not args.json:
                print(f"run {i + 1}/{args.runs}: {reason}", flush=True)
    finally:
        stop_background(background)
        if folder is not None:
            folder.cleanup()
    result = {"runs": args.runs, "completed": reasons["done"], "stop_reasons": dict(reasons),
              "drive_blamed": sum(reasons[r] for r in DRIVE_BLAMED),
              "host_too_slow": reasons["host_too_slow"],
              "load_before": load_before, "load_after": os.getloadavg(), "stops": details}
    if args.json:
        print(json.dumps(result))
    else:
        for line in details:
            print(line)
        print(f"{result['completed']} of {args.runs} runs completed their "
              f"{f'{args.duration:g} s' if args.duration > 0 else 'duration'}; "
              f"stops blaming the drive: {result['drive_blamed']}, host too slow: "
              f"{result['host_too_slow']} (load average before {load_before[0]:.2f}, "
              f"after {result['load_after'][0]:.2f})")  # type: ignore[index]
    return 0


if __name__ == "__main__":
    sys.exit(main())
