"""``dobhil report FILE.mcap --out DIR [--json]``: figures and a summary of a recorded run.

The analysis (:mod:`dobhil.run_report`) returns data; this command draws
force.png, tracking_error.png, position.png, commands.png, loop_timing.png
(:mod:`dobhil.plotting.report_figures`) and writes summary.json and summary.txt, each
under a temporary name renamed when complete. A several-axis log gets each axis' figures in
``DIR/<axis>/`` and one summary of all axes, their shared timing and each bus' load. Progress goes to stderr
(:mod:`dobhil.cli.progress`), none with --json.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any
from dobhil.cli.common import output_path

_FIGURES = ("force", "tracking_error", "position", "commands", "loop_timing")


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("report", help="plots and a summary (step metrics, errors, timing, bus) of a recorded run")
    p.add_argument("file", metavar="FILE.mcap")
    p.add_argument("--out", type=output_path, required=True, metavar="DIR", help="output directory")
    p.add_argument("--json", action="store_true", help="print the summary as JSON instead of text")
    p.set_defaults(func=run)


def _check_out_dir(out: Path, source: str, axes: tuple[str, ...] = ()) -> None:
    from dobhil.files import OutputError, check_output
    if out.exists() and not out.is_dir():
        raise OutputError(f"--out {out}: not a directory")
    for axis in axes:
        if (out / axis).exists() and not (out / axis).is_dir():
            raise OutputError(f"--out {out / axis}: not a directory")
    figures = [f"{n}.png" for n in _FIGURES]
    for name in ([f"{a}/{f}" for a in axes for f in figures] if axes else figures) + ["summary.json", "summary.txt"]:
        check_output(out / name, inputs=[source], what="--out")


def _earlier_figures(out: Path) -> list[Path]:
    """The figures of the report ``out`` already holds (its summary.json says its layout:
    ``axes`` names each axis' directory), so that those this report does not write over --
    an axis the new log does not have, the top-level figures of a one-axis report under a
    report of several -- are removed: left there, they would read as the new log's. Nothing
    but those figure names is touched; without a readable summary.json, nothing."""
    try:
        earlier = json.loads((out / "summary.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return []
    axes = earlier.get("axes") if isinstance(earlier, dict) else None
    if isinstance(axes, dict):   # only plain names: a summary.json is a file anyone may edit
        dirs = [out / a for a in axes if isinstance(a, str) and a not in ("", ".", "..") and "/" not in a]
    else:
        dirs = [out]
    return [d / f"{n}.png" for d in dirs for n in _FIGURES if (d / f"{n}.png").is_file()]


def _remove_stale(out: Path, earlier: list[Path], written: list[Path]) -> int:
    """Removes the ``earlier`` figures not among ``written`` (and an axis' directory left
    empty); how many."""
    kept = {p.resolve() for p in written}
    removed = 0
    for path in earlier:
        if path.resolve() in kept:
            continue
        path.unlink(missing_ok=True)
        removed += 1
        if path.parent != out:
            try:
                path.parent.rmdir()   # only when empty: other files there are not the report's
            except OSError:
                pass
    return removed


def run(args: argparse.Namespace) -> int:
    from dobhil.cli.progress import progress
    from dobhil.run_report import report, report_messages, summary_text
    from dobhil.plotting.report_figures import report_figures
    from dobhil.recording.axes import is_axes_log, layout
    from dobhil.recording.reader import open_log
    with open_log(args.file) as log:
        total = report_messages(log)
        axes = layout(log).names if is_axes_log(log) else ()
    _check_out_dir(args.out, args.file, axes)
    earlier = [p for p in _earlier_figures(args.out) if not p.samefile(args.file)]   # never the input
    if axes:
        return _run_axes(args, total, earlier)
    with progress("report", total=total, unit="message", quiet=args.json) as bar:
        data, summary, predicted = report(args.file, progress=bar.update)
    args.out.mkdir(parents=True, exist_ok=True)
    files = report_figures(data, predicted, summary, args.out)
    return _write_summary(args, summary, summary_text(summary), files, earlier)


def _run_axes(args: argparse.Namespace, total: int, earlier: list[Path]) -> int:
    """A several-axis log: each axis' figures in ``DIR/<axis>/``, one summary of all."""
    from dobhil.cli.progress import progress
    from dobhil.plotting.report_figures import report_figures
    from dobhil.run_report import axes_summary_text, report_axes
    with progress("report", total=total, unit="message", quiet=args.json) as bar:
        per, summary = report_axes(args.file, progress=bar.update)
    files: list[Path] = []
    for name, (data, axis_summary, predicted) in per.items():
        (args.out / name).mkdir(parents=True, exist_ok=True)
        files += report_figures(data, predicted, axis_summary, args.out / name)
    return _write_summary(args, summary, axes_summary_text(summary), files, earlier)


def _write_summary(args: argparse.Namespace, summary: dict[str, Any], text: str, files: list[Path],
                   earlier: list[Path]) -> int:
    """summary.json and summary.txt in ``--out`` (each renamed when complete), the ``earlier``
    report's figures not written over removed, then the summary on stdout (its JSON with
    --json) and the count of ``files`` written (and of those removed)."""
    from dobhil.files import atomic_path, shown
    text = shown(text)  # a file name that is not UTF-8 is shown escaped (\xff)
    for name, body in (("summary.json", json.dumps(summary, indent=2) + "\n"), ("summary.txt", text)):
        with atomic_path(args.out / name) as tmp:
            tmp.write_text(body, encoding="utf-8")
        files.append(args.out / name)
    removed = _remove_stale(args.out, earlier, files)
    if args.json:
        print(json.dumps(summary))
    else:
        sys.stdout.write(text)
        stale = f" (removed {removed} figures of the report it held before)" if removed else ""
        print(shown(f"wrote {len(files)} files to {args.out}{stale}"))
    return 0
