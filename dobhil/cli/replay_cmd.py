"""``dobhil replay FILE.mcap [--verify] [--axis NAME] [--set k=v]... [--plot F.png] [--out F.csv] [--json]``.

Re-runs the recorded run's controller on its recorded feedback frames
(:mod:`dobhil.replay`). ``--verify`` demands bit-identical outputs and exits 1
with one line naming the first differing cycle otherwise. A several-axis log replays
every axis (or the one ``--axis`` names), one line each; ``--verify`` then names the axes
that differ; ``--out``/``--plot`` write one file per axis (``F.<axis>.csv``).
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path
from typing import Any
from dobhil.cli.common import output_path

#: exit code of a verification that found a difference
EXIT_MISMATCH = 1


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("replay", help="re-run the controller offline on a recorded run's feedback")
    p.add_argument("file", metavar="FILE.mcap")
    p.add_argument("--verify", action="store_true",
                   help="require bit-identical commands and estimates (exit 1 if not)")
    p.add_argument("--axis", metavar="NAME", help="replay only this axis of a several-axis log")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="replay with this config key changed (repeatable)")
    p.add_argument("--plot", type=output_path, metavar="FILE.png", help="recorded vs replayed commands/estimates")
    p.add_argument("--out", type=output_path, metavar="FILE.csv", help="per-cycle recorded and replayed values")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from dobhil.recording.axes import axis_log, axis_logs
    from dobhil.recording.reader import open_log
    log = open_log(args.file)
    axes = axis_logs(log) if args.axis is None else (axis_log(log, args.axis),)
    if len(axes) > 1 or axes[0].listed:
        return _run_axes(args, axes)
    return _run_one(args, axes[0])


def _run_one(args: argparse.Namespace, axis: Any) -> int:
    from dobhil.files import check_output
    from dobhil.replay import replay_axis
    inputs = [args.file]
    if args.out:
        check_output(args.out, inputs=inputs, suffix=".csv", what="--out")
    if args.plot:
        check_output(args.plot, inputs=inputs, suffix=".png", what="--plot")
    result = replay_axis(axis, args.overrides)
    info = result.summary()
    if args.out:
        _write_csv(result, args.out)
    if args.plot:
        from dobhil.plotting.report_figures import replay_figure
        sys.stderr.write(f"wrote {replay_figure(result, args.plot)}\n")
    if args.json:
        print(json.dumps(info))
    else:
        _print(info)
    if args.verify and not info["identical"]:
        sys.stderr.write(f"dobhil replay: verification failed: {info['first_mismatch']}\n")
        return EXIT_MISMATCH
    if args.verify and info["missing"]:   # what is there matched; what is not was not verified
        sys.stderr.write(f"dobhil replay: verification incomplete: {info['missing']}\n")
        return EXIT_MISMATCH
    return 0


def _per_axis(path: Path, axis: str) -> Path:
    """``F.csv`` -> ``F.<axis>.csv``."""
    return path.with_name(f"{path.stem}.{axis}{path.suffix}")


def _run_axes(args: argparse.Namespace, axes: Any) -> int:
    """Every axis of a several-axis log (or the one ``--axis`` names): one line each."""
    from dobhil.files import check_output
    from dobhil.replay import replay_axis
    for axis in axes:
        if args.out:
            check_output(_per_axis(args.out, axis.name), inputs=[args.file],
                         suffix=".csv", what="--out")
        if args.plot:
            check_output(_per_axis(args.plot, axis.name), inputs=[args.file], suffix=".png", what="--plot")
    results = [replay_axis(axis, args.overrides) for axis in axes]
    infos = {r.recording.axis: r.summary() for r in results}
    for result in results:
        if args.out:
            _write_csv(result, _per_axis(args.out, result.recording.axis))
        if args.plot:
            from dobhil.plotting.report_figures import replay_figure
            sys.stderr.write(f"wrote {replay_figure(result, _per_axis(args.plot, result.recording.axis))}\n")
    differ = [name for name, info in infos.items() if not info["identical"]]
    if args.json:
        print(json.dumps({"file": args.file, "overrides": list(args.overrides), "identical": not differ,
                          "axes": infos}))
    else:
        over = ", ".join(args.overrides) or "recorded config"
        print(f"replayed {len(infos)} axes of {args.file} with {over}")
        for name, info in infos.items():
            what = ("identical: every command and estimate reproduced bit for bit" if info["identical"]
                    else info["first_mismatch"])
            print(f"  axis {name}: {info['cycles']} cycles, {what}" + (f"; {info['missing']}" if info["missing"]
                                                                      else ""))
    if args.verify and differ:
        first = infos[differ[0]]["first_mismatch"]
        which = f"axis {differ[0]}" if len(differ) == 1 else f"axes {', '.join(differ)} (first: {differ[0]})"
        sys.stderr.write(f"dobhil replay: verification failed on {which}: {first}\n")
        return EXIT_MISMATCH
    gaps = [name for name, info in infos.items() if info["missing"]]
    if args.verify and gaps:   # what is there matched; what is not was not verified
        sys.stderr.write(f"dobhil replay: verification incomplete on axis {gaps[0]}: {infos[gaps[0]]['missing']}\n")
        return EXIT_MISMATCH
    return 0


def _print(info: dict[str, Any]) -> None:
    over = ", ".join(info["overrides"]) or "recorded config"
    print(f"replayed {info['cycles']} cycles of {info['file']} with {over}")
    if info["identical"]:
        print("identical: every command and estimate " + ("of the cycles re-run " if info["missing"] else "")
              + "reproduced bit for bit")
    else:
        print(info["first_mismatch"])
    if info["missing"]:
        print(info["missing"])
    for name, d in info["difference"].items():
        print(f"  {name:<12} replayed - recorded: max |.| {d['max_abs']:.6g} N m, RMS {d['rms']:.6g} N m")


def _write_csv(result: Any, path: Path) -> None:
    from dobhil.files import atomic_path
    with atomic_path(path) as tmp, open(tmp, "w", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle)
        writer.writerow(result.header())
        writer.writerows(result.rows())
    sys.stderr.write(f"wrote {path}\n")
