"""``dobhil identify LOG.mcap... [--axis NAME] [--segment T0:T1[:free|contact]]... [--drive PROFILE]
[--period S] [--out F.yaml] [--json] [--plot DIR]`` and ``dobhil compare A.mcap B.mcap [--axis NAME]``.

identify fits the emulator's exact sampled plant to recorded runs (:mod:`dobhil.identify`):
several logs of one drive are fitted together (one plant: a free run's friction, a contact
run's environment); the free-motion and contact segments are found from the data unless
given (``--segment``: one log only); the overlay
(``--out``) is what ``dobhil analyze``/``run`` take with ``--set-file``. compare reports the
RMS of the difference of two runs' force (the estimated interaction torque), cycle by cycle; of
a log of several axes, the one ``--axis`` names (:mod:`dobhil.identify.compare`).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from dobhil.cli.common import output_path
from dobhil.config import key_fields
from dobhil.files import same_file

if TYPE_CHECKING:
    from dobhil.identify.fit import IdentResult

#: the longest --period: loop.period's own ceiling, read from its key (dobhil/config/schema.py)
MAX_PERIOD: float = key_fields()["loop.period"].metadata["maximum"]


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("identify", help="fit the servo, environment and delay to a recorded run")
    p.add_argument("log", metavar="LOG.mcap", nargs="+",
                   help="one or more logs of the same drive, fitted together (e.g. a free run and a contact run)")
    p.add_argument("--segment", action="append", default=[], metavar="T0:T1[:KIND]",
                   help="fit only this time span [s from the first cycle] (repeatable, one LOG only); KIND free "
                   "or contact, found from the data when not given")
    p.add_argument("--drive", metavar="PROFILE",
                   help="the drive profile (name or path): decodes a CAN log imported with dobhil log import; "
                   "a dobhil log must have been recorded with its protocol")
    p.add_argument("--period", type=float, metavar="SECONDS",
                   help="a CAN log's control period (default: the period its motion frames' stamps scatter around, "
                   "late ones left out: their least-squares slope, snapped to a whole microsecond when near); "
                   "one the stamps contradict (beyond 2e-4 of it and their scatter) is refused")
    p.add_argument("--axis", metavar="NAME",
                   help="the axis of a log of several axes to identify (its records and its bus' frames; "
                   "a coupled axis' environment is its coupling plus its own)")
    p.add_argument("--method", choices=("auto", "closed-loop", "open-loop"), default="auto",
                   help="auto (default): a force run of one dobhil log in closed loop (its recorded controller "
                   "simulated from the reference), anything else open loop (output error on the torque sent)")
    p.add_argument("--out", type=output_path, metavar="F.yaml", help="write the config overlay (for --set-file)")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.add_argument("--plot", type=output_path, metavar="DIR", help="measured vs model figures, one per segment")
    from dobhil.cli.identify_evidence import add_arguments
    add_arguments(p)
    p.set_defaults(func=run)
    c = sub.add_parser("compare", help="RMS of the force difference of two recorded runs")
    c.add_argument("first", metavar="A.mcap")
    c.add_argument("second", metavar="B.mcap")
    c.add_argument("--axis", metavar="NAME",
                   help="the axis of a log of several axes to compare (a single-axis log given with it: its one axis)")
    c.add_argument("--json", action="store_true", help="print the result as JSON")
    c.set_defaults(func=compare)


def run(args: argparse.Namespace) -> int:
    # each log read once, however many of the steps below take its path
    from dobhil.recording.reader import opened_once
    with opened_once():
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    from dobhil.drives.load import load_profile
    from dobhil.errors import ConfigError
    from dobhil.files import check_output, check_output_dir
    from dobhil.identify.data import find_segments, join, parse_segment, read_log
    if args.period is not None and not (math.isfinite(args.period) and 0.0 < args.period <= MAX_PERIOD):
        raise ConfigError(f"--period {args.period:g}: expected a control period in seconds, > 0 and <= {MAX_PERIOD:g}")
    _distinct_logs(args)
    if args.segment and len(args.log) > 1:
        raise ConfigError(f"--segment with {len(args.log)} logs: give segments for one LOG at a time "
                          "(without --segment each log's segments are found from its data)")
    if args.out:
        check_output(args.out, inputs=[*args.log, *([args.drive] if args.drive else [])],
                     suffix=(".yaml", ".yml"), what="--out")
    if args.plot:
        check_output_dir(args.plot, ["identify_segment_0.png"], inputs=args.log, what="--plot")
    profile = None if args.drive is None else load_profile(args.drive)
    from dobhil.identify.choose import closed_loop_wanted
    if closed_loop_wanted(args):
        # the checks of any log first (its protocol against --drive's, some motion), and
        # whether the run reached its environment
        one = read_log(args.log[0], profile=profile, axis=args.axis)
        return _closed_loop(args, any(s.kind == "contact" for s in find_segments(one)))
    logs = []
    for name in args.log:
        one = read_log(name, profile=profile, period=args.period, axis=args.axis)
        logs.append((one, tuple(parse_segment(s, one) for s in args.segment) or find_segments(one)))
    _same_firmware(args.log)
    data, parts = join(logs)
    from dobhil.cli import identify_evidence as evidence
    contact = any(s.kind == "contact" for part in parts for s in part.segments)
    held_out = evidence.read_validation(args, data, contact) if args.validate else None
    from dobhil.cli.progress import progress
    from dobhil.identify.fit import identify
    with progress("identify", unit="simulation", quiet=args.json) as shown:
        result = identify(data, [s for part in parts for s in part.segments],
                          progress=lambda stage: shown.update(1, stage))
    info = summary(result, data, parts)
    from dobhil.identify.closedloop import OPEN_LOOP
    info["method"] = OPEN_LOOP
    notes = [gaps_note(one) for one, _ in logs if gaps_note(one)] + [_seen_note(args)]
    if args.axis is not None:
        info["axis"] = args.axis
        notes.append(coupling_note(args.log, args.axis))
    if any(notes):
        info["note"] = "; ".join(n for n in notes if n)
    frf = evidence.frf_info(result, logs, parts, args.log) if args.frf else []
    if frf:
        info["frf"] = [{k: v for k, v in e.items() if not k.startswith("_")} for e in frf]
    if held_out is not None:
        info["validation"] = evidence.validation_info(result, *held_out)
    if args.out:
        _write_overlay(result, data.recorded, info, args.out, _overlay_axis(args))
    if args.plot:
        for path in _figures(result, data, parts, args.plot) + evidence.frf_figures(frf, args.plot):
            sys.stderr.write(f"wrote {path}\n")
    if args.json:
        print(json.dumps(info))
    else:
        _print(info)
        extra = evidence.frf_lines(frf) + (evidence.validation_lines(info["validation"]) if held_out else [])
        if extra:
            print("\n".join(extra))
    return 0


def _distinct_logs(args: argparse.Namespace) -> None:
    """Each log once: a log given twice would be fitted as two records of the same plant, its
    noise counted twice (every interval too narrow by sqrt 2). The same file by another path
    counts as the same (``os.path.samefile``); a missing one is refused later, by its reader."""
    from dobhil.errors import ConfigError
    for i, name in enumerate(args.log):
        twin = next((s for s in args.log[:i] if same_file(s, name)), None)
        if twin is not None:
            raise ConfigError(f"{name}: given twice (as {twin}); give each log once: a log fitted twice counts "
                              "its noise twice")


def _seen_note(args: argparse.Namespace) -> str:
    """A note when ``--validate`` names a log the fit read: its fit % and residual tests are
    then on data the fit has seen, which validates nothing (a model that memorised the
    noise would pass); said, not refused, as the figures are still the fit's on that log."""
    if not args.validate:
        return ""
    seen = next((name for name in args.log if same_file(name, args.validate)), None)
    if seen is None:
        return ""
    return (f"--validate {args.validate} is the fitted log {seen}: the validation is on data the fit has seen, "
            "not held out; validate on another run")


def _same_firmware(names: list[str]) -> None:
    """Logs fitted together are one drive: of one firmware, as ``--validate`` asks of its log
    (:func:`dobhil.cli.identify_evidence.read_validation`) -- another firmware may scale,
    quantise or delay the torque and motion otherwise, and the fit shares one delay and one
    plant between the logs. A log without a recorded drive (imported: decoded with --drive's
    profile) has no firmware to differ."""
    from dobhil.cli.identify_evidence import firmware_of
    from dobhil.errors import ConfigError
    first = firmware_of(names[0])
    for name in names[1:]:
        theirs = firmware_of(name)
        if first is not None and theirs is not None and theirs != first:
            raise ConfigError(f"{name}: drive {theirs}, but {names[0]}'s is {first}; "
                              "logs identified together need the same drive")


def _closed_loop(args: argparse.Namespace, contact: bool) -> int:
    """identify by simulating the recorded controller in closed loop (:mod:`dobhil.identify.closedloop`)."""
    from dobhil.cli.progress import progress
    from dobhil.identify.closedloop import CLOSED_LOOP, closed_loop_record, identify_closed_loop
    from dobhil.identify.data import Part
    from dobhil.runtime.session import build_controller
    record = closed_loop_record(args.log[0], build_controller, axis=args.axis)
    held_out = _loop_validation_record(args, record, contact) if args.validate else None
    with progress("identify", unit="simulation", quiet=args.json) as shown:
        result = identify_closed_loop(record, contact=contact, progress=lambda stage: shown.update(1, stage))
    data = argparse.Namespace(source=record.source, protocol="",
                              period=record.model.period)
    info = summary(result, data, (Part(record.source, 0, record.samples, result.segments),))
    info["protocol"] = _protocol_of(args.log[0])
    info["method"] = CLOSED_LOOP
    if args.axis is not None:
        info["axis"] = args.axis
    if _seen_note(args):
        info["note"] = _seen_note(args)
    if held_out is not None:
        from dobhil.cli.identify_evidence import loop_validation_info
        info["validation"] = loop_validation_info(result, held_out)
    if args.out:
        _write_overlay(result, record.recorded, info, args.out)
    if args.plot:
        sys.stderr.write(f"wrote {_closed_loop_figure(result, record, args.plot)}\n")
    if args.json:
        print(json.dumps(info))
    else:
        _print(info)
        if held_out is not None:
            from dobhil.cli.identify_evidence import validation_lines
            print("\n".join(validation_lines(info["validation"])))
    return 0


def _loop_validation_record(args: argparse.Namespace, fitted: Any, contact: bool = True) -> Any:
    """The validation run of a closed-loop fit, read before the fit (a refusal is then
    immediate): a dobhil force run's log of the same drive protocol and loop period; when the
    fitted run never reached its environment (``contact`` False: the fit has none), one that
    does not reach it either -- its loop simulated without an environment would be called a
    misfit of a right servo model."""
    from dobhil.errors import ConfigError
    from dobhil.identify.closedloop import closed_loop_record
    from dobhil.identify.data import find_segments, read_log
    from dobhil.runtime.session import build_controller
    name = args.validate
    from dobhil.identify.choose import recorded_mode
    if Path(name).is_file() and recorded_mode(name, args.axis) is None:
        # its loop is what the validation simulates: a log without its controller (a CAN log
        # imported) cannot be, but the open-loop fit validates on its frames
        raise ConfigError(f"--validate {name}: has no recorded controller (a CAN log imported?), and a closed-loop "
                          "fit is validated by simulating the validation run's own loop; validate on a run "
                          "recorded by dobhil, or fit with --method open-loop (and --drive NAME to decode its frames)")
    record = closed_loop_record(name, build_controller, axis=args.axis)
    if not contact and any(s.kind == "contact" for s in find_segments(read_log(name, axis=args.axis))):
        raise ConfigError(f"--validate {name}: reaches its environment, but the fitted run never did, so the fit "
                          "has no environment to simulate it with; validate on a run that stays free, or fit a "
                          "run in contact")
    mine, theirs = _protocol_of(name), _protocol_of(args.log[0])
    if mine != theirs:
        raise ConfigError(f"--validate {name}: recorded with a {mine!r} drive, but the fitted log with a "
                          f"{theirs!r} one; validate on a log of the same drive")
    from dobhil.cli.identify_evidence import firmware_of
    firmware, fitted_firmware = firmware_of(name), firmware_of(args.log[0])
    if firmware is not None and fitted_firmware is not None and firmware != fitted_firmware:
        raise ConfigError(f"--validate {name}: drive {firmware}, but the fitted log's is "
                          f"{fitted_firmware}; "
                          "validate on a log of the same drive")
    if not math.isclose(record.model.period, fitted.model.period, rel_tol=1e-9):
        raise ConfigError(f"--validate {name}: period {record.model.period:g} s, but the fitted log has "
                          f"{fitted.model.period:g} s; validate on a log of the same drive and loop period")
    return record


def _closed_loop_figure(result: Any, record: Any, out: Path) -> Path:
    """The measured motion against the closed loop simulated with the fitted values (every
    parameter as fitted: one too uncertain to report still shapes the simulation)."""
    import numpy as np

    from dobhil.identify.closedloop import simulate_loop
    from dobhil.plotting.identify_figures import measured_vs_model
    sim = simulate_loop(result.fitted, record)
    out.mkdir(parents=True, exist_ok=True)
    t = record.model.period * np.arange(record.samples)
    return Path(measured_vs_model(t, (record.position, record.velocity), (sim[:, 0], sim[:, 1]),
                                  f"{record.source}: closed loop simulated from the reference",
                                  out / "identify_segment_0.png", torque=record.torque))


def _protocol_of(log: str) -> str:
    from dobhil.drives.decode import recorded_profile
    from dobhil.recording.reader import open_log
    with open_log(log) as opened:
        return recorded_profile(opened.metadata.get("drive"), log).protocol


def coupling_note(logs: list[str], axis: str) -> str:
    """What the identified environment of a coupled axis is ("" for an axis no recorded
    coupling joins): the fit sees the axis' own servo driven by its motor torque, and as
    its environment everything else that pushes on it -- the coupling's spring and damper
    toward the other axis (whose motion the fit does not know) and the axis' own contact."""
    from dobhil.recording.axes import layout
    from dobhil.recording.reader import open_log
    partners: list[str] = []
    for name in logs:
        with open_log(name) as log:
            for c in layout(log).couplings:
                if axis in (c.get("a"), c.get("b")):
                    other = c.get("b") if c.get("a") == axis else c.get("a")
                    partners.append(f"{other} (K {float(c.get('stiffness', 0.0)):g} N m/rad, "
                                    f"D {float(c.get('damping', 0.0)):g} N m s/rad)")
    if not partners:
        return ""
    return (f"axis {axis} is coupled to {', '.join(dict.fromkeys(partners))}: the servo estimates (inertia, "
            "friction) are the axis' own; the environment estimates are the coupling plus the axis' own "
            "environment, seen from this axis with the other axis' motion as a disturbance")


def gaps_note(data: Any) -> str:
    """Which cycles of a run's log were fitted, when not all ("": all of them)."""
    if not data.cycles or (data.first_cycle == 0 and data.samples == data.cycles):
        return ""
    last = data.first_cycle + data.samples - 1
    return (f"{data.source}: cycles {data.first_cycle}-{last} of the {data.cycles} recorded, the longest run "
            f"without a skipped cycle (a late real-time cycle skips frames; --lockstep runs skip none); "
            f"times are from cycle {data.first_cycle}")


def _figures(result: Any, data: Any, parts: Any, out: Path) -> list[Path]:
    """One measured-vs-model PNG per segment, the model simulated as fitted (every fitted
    parameter: :func:`~dobhil.cli.identify_evidence.model_values`), against the time in its own log."""
    from dobhil.cli.identify_evidence import model_values
    from dobhil.identify.fit import simulate
    from dobhil.plotting.identify_figures import measured_vs_model
    values = model_values(result)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for i, (part, seg) in enumerate((p, s) for p in parts for s in p.segments):
        # the segments are result.segments in this order; each from its fitted initial state
        initial = result.initial[i] if i < len(result.initial) else None
        s = slice(seg.start, seg.stop)
        t0, t1 = part.local(seg, data.period)
        t = data.t[s] - part.offset * data.period
        title = f"{part.source}: {seg.kind} segment {t0:.3f}-{t1:.3f} s"
        written.append(measured_vs_model(t, (data.position[s], data.velocity[s]), simulate(values, data, seg, initial),
                                         title, out / f"identify_segment_{i}.png", torque=data.torque[s]))
    return written


def summary(result: Any, data: Any, parts: Any) -> dict[str, Any]:
    """The JSON of an identification: estimates, correlations, residual, segments (the log of
    each, and its times in that log)."""
    def number(x: float) -> float | None:
        return None if x != x else float(x)  # NaN (not identifiable) -> null
    segments = []
    for part in parts:
        for s in part.segments:
            t0, t1 = part.local(s, data.period)
            segments.append({"file": part.source, "kind": s.kind, "t0": t0, "t1": t1})
    return {"file": data.source, "files": [p.source for p in parts], "protocol": data.protocol,
            "period": data.period, "samples": sum(p.samples for p in parts), "segments": segments,
            "estimates": {n: {"value": number(e.value), "stderr": number(e.stderr), "low": number(e.low),
                              "high": number(e.high), "identifiable": e.identifiable, "why": e.why}
                          for n, e in result.estimates.items()},
            "correlations": [{"a": a, "b": b, "r": number(r)} for (a, b), r in result.correlations.items()],
            "residual": {"rms": number(result.residual.rms), "whiteness_p": number(result.residual.whiteness_p),
                         "misfit": result.residual.misfit, "warning": result.residual.warning}}


def _print(info: dict[str, Any]) -> None:
    many = len(info["files"]) > 1
    spans = ", ".join((f"{s['file']} " if many else "") + f"{s['kind']} {s['t0']:.3f}-{s['t1']:.3f} s"
                      for s in info["segments"])
    axis = f" axis {info['axis']}" if info.get("axis") else ""
    print(f"identified {info['file']}{axis} ({info['protocol']}, {info['samples']} samples at T = "
          f"{info['period']:g} s): {spans}")
    if info.get("method"):
        print(f"method: {info['method']}")
    if info.get("note"):
        print(f"note: {info['note']}")
    for name, e in info["estimates"].items():
        if e["identifiable"]:
            unit = f" {_unit(name)}" if _unit(name) else ""   # of the value, its interval and error
            print(f"  {name:<18} {e['value']:.6g}{unit}  95 % [{e['low']:.6g}, {e['high']:.6g}]  "
                  f"stderr {e['stderr']:.3g}")
        else:
            print(f"  {name:<18} not identifiable: {e['why']}")
    r = info["residual"]
    rms = _num(r["rms"], ".4g")
    print(f"residual RMS {rms}{'' if r['rms'] is None else ' rad/s'}, whiteness p = {_num(r['whiteness_p'], '.3g')}")
    if r["warning"]:
        print(f"warning: {r['warning']}")


def _unit(name: str) -> str:
    """The unit an estimate is printed in: its config key's (docs/config.md), the delay's
    seconds; the torque gain is a ratio."""
    from dobhil.identify.intervals import CONFIG_KEYS
    if name == "delay":
        return "s"
    key = CONFIG_KEYS.get(name)
    return str(key_fields()[key].metadata["unit"]) if key else ""


def _num(value: float | None, spec: str) -> str:
    return "n/a" if value is None else format(value, spec)


#: overlay key -> the estimate whose interval its comment gives
_OVERLAY_SOURCES = {"plant.inertia": "inertia", "plant.viscous_friction": "viscous_friction",
                    "plant.coulomb_friction": "coulomb_friction", "environment.contact_position": "contact_position",
                    "environment.stiffness": "stiffness", "environment.damping": "damping",
                    "design.identified_inertia": "inertia"}


def _overlay_axis(args: argparse.Namespace) -> str | None:
    """The axis whose keys the overlay sets: ``--axis`` of a several-axis log (None: a
    single-axis log, whose keys are the config's own)."""
    if args.axis is None:
        return None
    from dobhil.recording.axes import is_axes_log
    return args.axis if is_axes_log(args.log[0]) else None


def damping_note(result: IdentResult, recorded: Mapping[str, float]) -> str:
    """What the overlay's damping is when the record determines only friction plus damping
    (:meth:`~dobhil.identify.fit.IdentResult.overlay`), '' otherwise."""
    total = result.damping_sum()
    if total is None:
        return ""
    friction = recorded.get("plant.viscous_friction")
    if friction is None:
        return (f"environment.damping is the fitted sum of friction and damping ({total:.6g}): the record "
                "does not separate them, and the config's plant.viscous_friction adds to it in contact")
    return (f"environment.damping is the fitted sum of friction and damping ({total:.6g}) less the recorded "
            f"plant.viscous_friction ({friction:.6g}): the record does not separate them; the config's friction "
            "stays, so the loop in contact has the sum")


def overlay_text(overlay: dict[str, Any], info: dict[str, Any], axis: str | None = None, note: str = "") -> str:
    """The overlay as YAML a person can read: one ``key: value`` a line, each commented with its
    95 % interval, and what was not identifiable (and why) at the top. ``repr`` of a float is
    valid YAML and round-trips exactly (tested). ``axis``: the keys are that axis' own,
    ``axes.NAME.section.key`` -- a plain ``section.key`` given to a config that lists axes sets
    every axis, and loses to a key the axis sets itself (:func:`dobhil.config.axes.load_axes`);
    the ``identified:`` section keeps plain keys, as ``tune``/``montecarlo --axis NAME`` vary
    them on that axis' config."""
    est = info["estimates"]
    lines = [f"# written by dobhil identify from {', '.join(info['files'])}; use with --set-file",
             "# design.identified_inertia is the identified inertia as the design's J_mi: keep your own rule "
             "with --set design.identified_inertia=... after --set-file"]
    if axis is not None:
        lines.append(f"# the keys of axis {axis}: use with a config that lists axes: (and --axis {axis} for "
                     "tune and montecarlo)")
    lines += [f"# not identifiable: {name}: {e['why']}" for name, e in est.items() if not e["identifiable"]]
    if note:
        lines.append(f"# {note}")
    for key in sorted(overlay):
        value = overlay[key]
        name = "delay" if key in ("design.delay_samples", "design.input_delay") else _OVERLAY_SOURCES.get(key)
        e = est.get(name) if name else None
        note = ""
        if e and e["identifiable"]:
            whole = f"delay {e['value']:.6g} s, " if name == "delay" else ""
            note = f"  # {whole}95 % [{e['low']:.6g}, {e['high']:.6g}]"
        shown = repr(float(value)) if isinstance(value, float) else repr(int(value))
        lines.append(f"{'' if axis is None else f'axes.{axis}.'}{key}: {shown}{note}")
    from dobhil.identify.intervals import section_text
    return "\n".join(lines) + "\n" + section_text(info)


def _less_friction(info: dict[str, Any], result: IdentResult, friction: float | None) -> dict[str, Any]:
    """``info`` with the damping's estimate and interval less the recorded ``friction`` where
    the overlay writes the fitted sum of friction and damping less it (:func:`damping_note`):
    the overlay's comments and its ``identified:`` section (the box ``dobhil tune
    --uncertainty-from`` takes) then hold the value the overlay sets, not the sum."""
    if result.damping_sum() is None or not friction or not info["estimates"]["damping"]["identifiable"]:
        return info
    damping = dict(info["estimates"]["damping"])
    for key in ("value", "low", "high"):
        damping[key] = max(float(damping[key]) - friction, 0.0)
    return {**info, "estimates": {**info["estimates"], "damping": damping}}


def _write_overlay(result: IdentResult, recorded: Mapping[str, float], info: dict[str, Any], path: Path,
                   axis: str | None = None) -> None:
    from dobhil.files import atomic_path
    note = damping_note(result, recorded)
    friction = recorded.get("plant.viscous_friction")
    with atomic_path(path) as tmp:
        tmp.write_text(overlay_text(result.overlay(friction), _less_friction(info, result, friction), axis, note),
                       encoding="utf-8")
    sys.stderr.write(f"wrote {path}\n")
    if note:
        sys.stderr.write(f"note: {note}\n")


def compare(args: argparse.Namespace) -> int:
    from dobhil.identify.compare import compare_logs
    info = compare_logs(args.first, args.second, args.axis)
    if args.json:
        print(json.dumps(info))
    else:
        which = f"axis {args.axis}: " if args.axis is not None else ""
        print(f"{which}compared {info['cycles']} cycles: force (tau_int_hat) RMS difference {info['rms']:.6g} N m, "
              f"max |difference| {info['max_abs']:.6g} N m")
        if info["note"]:
            print(f"note: {info['note']}")
    return 0
