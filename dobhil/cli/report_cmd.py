"""``dobhil report FILE.mcap --out DIR [--json]``: figures and a summary of a recorded run.

Writes force.png, tracking_error.png, position.png, commands.png, loop_timing.png,
summary.json and summary.txt (:mod:`dobhil.analysis.run_report`). A progress bar goes
to stderr when it is a terminal.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("report", help="plots and a summary (step metrics, errors, timing, bus) of a recorded run")
    p.add_argument("file", metavar="FILE.mcap")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="output directory")
    p.add_argument("--json", action="store_true", help="print the summary as JSON instead of text")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from dobhil.analysis.run_report import summary_text, write_report
    from dobhil.recording.reader import open_log
    log = open_log(args.file)
    total = sum(c.message_count for c in log.channels()) if log.has_summary else None
    with tqdm(total=total, desc="report", unit="msg", file=sys.stderr, disable=not sys.stderr.isatty()) as bar:
        summary, files = write_report(args.file, args.out, progress=bar.update)
    if args.json:
        print(json.dumps(summary))
    else:
        sys.stdout.write(summary_text(summary))
        print(f"wrote {len(files)} files to {args.out}")
    return 0
