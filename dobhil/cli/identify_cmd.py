"""``dobhil identify LOG.mcap [--segment T0:T1[:free|contact]]... [--drive PROFILE] [--period S]
[--out F.yaml] [--json] [--plot DIR]`` and ``dobhil compare A.mcap B.mcap``.

identify fits the emulator's exact sampled plant to a recorded run (:mod:`dobhil.identify`):
the free-motion and contact segments are found from the data unless given; the overlay
(``--out``) is what ``dobhil analyze``/``run`` take with ``--set-file``. compare reports the
RMS of the difference of two runs' force (the estimated interaction torque), cycle by cycle.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("identify", help="fit the servo, environment and delay to a recorded run")
    p.add_argument("log", metavar="LOG.mcap")
    p.add_argument("--segment", action="append", default=[], metavar="T0:T1[:KIND]",
                   help="fit only this time span [s from the first cycle] (repeatable); KIND free or "
                   "contact, found from the data when not given")
    p.add_argument("--drive", metavar="PROFILE",
                   help="the drive profile (name or path): decodes a CAN log imported with dobhil log import; "
                   "a dobhil log must have been recorded with its protocol")
    p.add_argument("--period", type=float, metavar="SECONDS",
                   help="a CAN log's control period (default: the median spacing of its motion frames)")
    p.add_argument("--out", type=Path, metavar="F.yaml", help="write the config overlay (for --set-file)")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.add_argument("--plot", type=Path, metavar="DIR", help="measured vs model figures, one per segment")
    p.set_defaults(func=run)
    c = sub.add_parser("compare", help="RMS of the force difference of two recorded runs")
    c.add_argument("first", metavar="A.mcap")
    c.add_argument("second", metavar="B.mcap")
    c.add_argument("--json", action="store_true", help="print the result as JSON")
    c.set_defaults(func=compare)


def run(args: argparse.Namespace) -> int:
    from dobhil.drives.profile import load_profile
    from dobhil.files import check_output, check_output_dir
    from dobhil.identify.data import find_segments, parse_segment, read_log
    if args.out:
        check_output(args.out, inputs=[args.log], suffix=(".yaml", ".yml"), what="--out")
    if args.plot:
        check_output_dir(args.plot, ["identify_segment_0.png"], inputs=[args.log], what="--plot")
    profile = None if args.drive is None else load_profile(args.drive)
    data = read_log(args.log, profile=profile, period=args.period)
    segments = tuple(parse_segment(s, data) for s in args.segment) or find_segments(data)
    from dobhil.identify.fit import identify
    result = identify(data, segments)
    info = summary(result, data)
    if args.out:
        _write_overlay(result.overlay(), args.out)
    if args.plot:
        for path in _figures(result, data, args.plot):
            sys.stderr.write(f"wrote {path}\n")
    if args.json:
        print(json.dumps(info))
    else:
        _print(info)
    return 0


def _figures(result: Any, data: Any, out: Path) -> list[Path]:
    """One measured-vs-model PNG per segment, the model simulated with the identifiable values."""
    from dobhil.identify.fit import simulate
    from dobhil.plotting.identify_figures import measured_vs_model
    values = {n: e.value for n, e in result.estimates.items() if e.identifiable}
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for i, seg in enumerate(result.segments):
        s = slice(seg.start, seg.stop)
        t = data.t[s]
        title = f"{data.source}: {seg.kind} segment {t[0]:.3f}-{t[-1]:.3f} s"
        written.append(measured_vs_model(t, (data.position[s], data.velocity[s]), simulate(values, data, seg),
                                         title, out / f"identify_segment_{i}.png"))
    return written


def summary(result: Any, data: Any) -> dict[str, Any]:
    """The JSON of an identification: estimates, correlations, residual, segments (times)."""
    def number(x: float) -> float | None:
        return None if x != x else float(x)  # NaN (not identifiable) -> null
    return {"file": data.source, "protocol": data.protocol, "period": data.period, "samples": data.samples,
            "segments": [{"kind": s.kind, "t0": s.start * data.period, "t1": s.stop * data.period}
                         for s in result.segments],
            "estimates": {n: {"value": number(e.value), "stderr": number(e.stderr), "low": number(e.low),
                              "high": number(e.high), "identifiable": e.identifiable, "why": e.why}
                          for n, e in result.estimates.items()},
            "correlations": [{"a": a, "b": b, "r": number(r)} for (a, b), r in result.correlations.items()],
            "residual": {"rms": number(result.residual.rms), "whiteness_p": number(result.residual.whiteness_p),
                         "misfit": result.residual.misfit, "warning": result.residual.warning}}


def _print(info: dict[str, Any]) -> None:
    spans = ", ".join(f"{s['kind']} {s['t0']:.3f}-{s['t1']:.3f} s" for s in info["segments"])
    print(f"identified {info['file']} ({info['protocol']}, {info['samples']} samples at T = "
          f"{info['period']:g} s): {spans}")
    for name, e in info["estimates"].items():
        if e["identifiable"]:
            print(f"  {name:<18} {e['value']:.6g}  95 % [{e['low']:.6g}, {e['high']:.6g}]  stderr {e['stderr']:.3g}")
        else:
            print(f"  {name:<18} not identifiable: {e['why']}")
    r = info["residual"]
    print(f"residual RMS {_num(r['rms'], '.4g')}, whiteness p = {_num(r['whiteness_p'], '.3g')}")
    if r["warning"]:
        print(f"warning: {r['warning']}")


def _num(value: float | None, spec: str) -> str:
    return "n/a" if value is None else format(value, spec)


def _write_overlay(overlay: dict[str, Any], path: Path) -> None:
    import yaml

    from dobhil.files import atomic_path
    text = ("# written by dobhil identify; use with --set-file\n"
            + yaml.safe_dump({k: float(v) if isinstance(v, float) else v for k, v in overlay.items()},
                             sort_keys=True))
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    sys.stderr.write(f"wrote {path}\n")


def compare(args: argparse.Namespace) -> int:
    from dobhil.identify.compare import compare_logs
    info = compare_logs(args.first, args.second)
    if args.json:
        print(json.dumps(info))
    else:
        print(f"compared {info['cycles']} cycles: force (tau_int_hat) RMS difference {info['rms']:.6g} N m, "
              f"max |difference| {info['max_abs']:.6g} N m")
    return 0
