"""What ``dobhil identify`` shows beside its numbers: ``--frf`` (the measured frequency response
of each segment with the fitted model's over it, :mod:`dobhil.identify.frf`) and ``--validate
B.mcap`` (the fitted model on a record the fit did not see, :mod:`dobhil.identify.validate`)."""

from __future__ import annotations

import argparse
import math
import os
from collections.abc import Mapping
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from dobhil.errors import ConfigError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--frf", action="store_true",
                   help="also measure each segment's frequency response (torque to velocity free, to force in "
                        "contact; at a multisine's lines, else Welch), with coherence, 95 %% band, the model's "
                        "response and the delay from the phase slope (figures with --plot)")
    p.add_argument("--validate", metavar="B.mcap",
                   help="check the fitted model on another log of the same drive: fit %% per signal, residual "
                        "whiteness and residual-input cross-correlation (a closed-loop fit: B's loop simulated "
                        "from its reference, the residual against the reference)")


# -- --validate ------------------------------------------------------------------------------

def read_validation(args: argparse.Namespace, fitted: Any, contact: bool = True) -> Any:
    """The validation log's data and segments, read before the fit (a refusal is then
    immediate): it must be of the drive, protocol and period the fitted logs are. ``contact``:
    whether the fitted logs have a contact segment; without one the fit has no environment, so
    the validation log's contact segments are left out (the model would press into nothing and
    call the record a misfit), said in the validation's lines; a log with no free segment then
    is refused."""
    from dobhil.identify.data import find_segments, read_log
    name = args.validate
    data = read_log(name, period=args.period, axis=args.axis,
                    profile=None if args.drive is None else _profile(args.drive))
    if data.protocol != fitted.protocol:
        raise ConfigError(f"--validate {name}: recorded with a {data.protocol!r} drive, but the fitted logs with a "
                          f"{fitted.protocol!r} one; validate on a log of the same drive")
    if not math.isclose(data.period, fitted.period, rel_tol=1e-9):
        raise ConfigError(f"--validate {name}: period {data.period:g} s, but the fitted logs have {fitted.period:g} s; "
                          "validate on a log of the same drive and loop period")
    mine, theirs = _firmware(name), _firmware(args.log[0])
    if mine is not None and theirs is not None and mine != theirs:
        raise ConfigError(f"--validate {name}: drive {mine}, but the fitted logs' is {theirs}; "
                          "validate on a log of the same drive")
    segments = find_segments(data)
    if contact:
        return data, segments, 0
    free = tuple(s for s in segments if s.kind == "free")
    if not free:
        raise ConfigError(f"--validate {name}: in contact only, but the fitted logs have no contact segment, so the "
                          "fit has no environment to validate; validate on a free run, or fit a contact run too")
    return data, free, len(segments) - len(free)


def firmware_of(path: str) -> str | None:
    """The recorded drive's identity, its firmware and what else its protocol needs to tell
    drives apart (``firmware '0.6'``; None: a log without a recorded drive, an imported one)."""
    return _firmware(path)


def _profile(name: str) -> Any:
    from dobhil.drives.load import load_profile
    return load_profile(name)


def _firmware(path: str) -> str | None:
    """The recorded drive's identity (:meth:`~dobhil.drives.plugin.DriveProtocol.drive_identity`;
    None: a log without a recorded drive, an imported one)."""
    import json

    from dobhil.drives.decode import recorded_profile
    from dobhil.drives.registry import protocol
    from dobhil.errors import DobhilError
    from dobhil.recording.reader import open_log
    if not path or not os.path.isfile(path):
        return None
    with open_log(path) as log:
        drive = log.metadata.get("drive") or {}
        raw = drive.get("firmware")
    if raw is None:
        return None
    try:
        recorded = recorded_profile(drive, path)
        return protocol(recorded.protocol).drive_identity(recorded)
    except DobhilError:   # a profile this version cannot read: its firmware is all it can tell
        return f"firmware {str(json.loads(raw))!r}"


def validation_info(result: Any, data: Any, segments: Any, skipped: int = 0) -> dict[str, Any]:
    """``skipped``: the validation log's contact segments left out (a fit without environment)."""
    from dobhil.identify.validate import validate
    if not result.estimates["inertia"].identifiable:
        raise ConfigError("--validate: the fit gave no inertia, so there is no model to validate")
    info = _info(validate(model_values(result), data, segments), data.source, "input")
    info["contact_segments_left_out"] = skipped
    return info


def loop_validation_info(result: Any, record: Any) -> dict[str, Any]:
    """``--validate`` of a closed-loop fit: the fitted plant in the validation run's own closed
    loop (:func:`dobhil.identify.closedloop.validate_loop`)."""
    from dobhil.identify.closedloop import validate_loop
    # the model the fit simulated, every parameter as fitted: a value whose interval is too
    # wide to report (a contact position within the encoder's count) still places the contact
    return _info(validate_loop(result.fitted, record), record.source, "reference")


def _info(v: Any, source: str, against: str) -> dict[str, Any]:
    tests = {t.name: {"worst": t.worst, "worst_lag": t.worst_lag, "threshold": t.threshold,
                      "per_lag_99": t.per_lag_99, "outside_99": t.outside_99, "lags": len(t.lags), "passed": t.passed}
             for t in (v.whiteness, v.cross)}
    return {"file": source, "samples": v.samples, "against": against,
            "fits": [{"signal": f.signal, "kind": f.kind, "percent": _num(f.percent), "samples": f.samples}
                     for f in v.fits],
            "whiteness": tests[v.whiteness.name], "cross_correlation": tests[v.cross.name],
            "ljung_box_p": v.ljung_box_p, "residual_rms": v.residual_rms, "rounding": v.rounding,
            "misfit": v.misfit, "misfit_line": _misfit_line(v, source) if v.misfit else ""}


def _misfit_line(v: Any, source: str) -> str:
    failed = [t for t in (v.whiteness, v.cross) if not t.passed]
    what = "; ".join(f"{t.name} {t.worst:+.3f} at lag {t.worst_lag} beyond +-{t.threshold:.3g}" for t in failed)
    return (f"model misfit on {source}: {what}: the model does not explain this record; do not trust its "
            "numbers outside the records it was fitted to")


def validation_lines(info: dict[str, Any]) -> list[str]:
    how = ("its closed loop simulated from its reference" if info["against"] == "reference"
           else "initial states fitted")
    lines = [f"validated on {info['file']} ({info['samples']} samples, {how}): fit % "
             "100 (1 - |y - model| / |y - mean y|)"]
    if info.get("contact_segments_left_out"):
        lines.append(f"  note: {info['contact_segments_left_out']} contact segment(s) of {info['file']} left out: "
                     "the fitted logs have no contact segment, so the fit has no environment")
    lines += [f"  {f['signal']:<9} {f['kind']:<8} {_pct(f['percent'])}" for f in info["fits"]]
    for key, label in (("whiteness", "residual autocorrelation, lags 1.."),
                       ("cross_correlation", f"residual-{info['against']} cross-correlation, lags -+")):
        t = info[key]
        n = t["lags"] if key == "whiteness" else (t["lags"] - 1) // 2
        lines.append(f"  {label}{n}: worst {t['worst']:+.3f} at lag {t['worst_lag']}, threshold +-{t['threshold']:.3g}"
                     f" (0.1 % over all lags); {t['outside_99']} of {t['lags']} beyond the per-lag 99 % band "
                     f"+-{t['per_lag_99']:.3g}: {'ok' if t['passed'] else 'FAILED'}")
    lines.append(f"  Ljung-Box p = {info['ljung_box_p']:.3g}, residual RMS {info['residual_rms']:.4g} rad/s"
                 + (" (below the noise floor: rounding, no verdict on its colour)" if info["rounding"] else ""))
    if info["misfit"]:
        lines.append(f"warning: {info['misfit_line']}")
    return lines


def _pct(x: float | None) -> str:
    return "n/a (constant signal)" if x is None else f"{x:.2f} %"


def _num(x: float) -> float | None:
    return None if not math.isfinite(x) else float(x)


def _values(result: Any) -> dict[str, float]:
    """The identifiable estimates (an unidentified delay is none: 0)."""
    values = {n: e.value for n, e in result.estimates.items() if e.identifiable}
    values.setdefault("delay", 0.0)
    return values


def model_values(result: Any) -> dict[str, float]:
    """The model the fit ended at, to simulate: every fitted parameter, identifiable or not
    (:attr:`~dobhil.identify.fit.IdentResult.fitted`). A pair the record confounds (a pressed
    servo's viscous friction and D_env act as their sum) is reported as neither, yet its sum is
    what the record determined: the identifiable values alone would simulate without it."""
    return dict(result.fitted) if result.fitted else _values(result)


# -- --frf -----------------------------------------------------------------------------------

def excitation(path: str) -> Any:
    """The multisine a run's log was excited with (None: another signal, or no config)."""
    from dobhil.identify.frf import Excitation
    from dobhil.recording.reader import open_log
    from dobhil.runtime.references import multisine_frequencies
    with open_log(path) as log:
        config = log.config   # None: an imported CAN log
    reference = getattr(config, "reference", None)   # a several-axis config has its axes' instead
    if config is None or reference is None or reference.kind != "multisine":
        return None
    r = config.reference
    length = r.duration if r.duration > 0 else config.loop.duration - r.start
    return Excitation(tuple(multisine_frequencies(r.frequency, r.frequency_end, int(r.lines))), r.start,
                      r.start + length)


def frf_info(result: Any, logs: Any, parts: Any, paths: list[str]) -> list[dict[str, Any]]:
    """Each fitted segment's response, in its own log (``paths``: the files, in the order of
    ``logs``; a multisine is timed by its log's cycles)."""
    from dobhil.identify.data import Segment
    from dobhil.identify.frf import segment_response
    values = _values(result)
    delay = result.estimates["delay"]
    out = []
    index = 0
    for (one, _), part, path in zip(logs, parts, paths):
        exc = excitation(path)
        for seg in part.segments:
            local = Segment(seg.start - part.offset, seg.stop - part.offset, seg.kind)
            # the model from the segment's fitted initial state, on the log's own torque history
            initial = result.initial[index] if index < len(result.initial) else None
            index += 1
            r = segment_response(one, local, values, exc, simulate=partial(_simulated, one, local, initial),
                                 fitted=result.fitted)
            m = r.measured
            inside = m.within(r.model)
            entry: dict[str, Any] = {
                "file": part.source, "kind": seg.kind, "t0": local.start * one.period, "t1": local.stop * one.period,
                "output": m.output, "method": m.method, "averages": m.averages,
                "frequency": m.frequency.tolist(), "gain": np.abs(m.response).tolist(),
                "phase": np.angle(m.response).tolist(), "gain_low": m.low.tolist(), "gain_high": m.high.tolist(),
                "phase_band": m.phase_band.tolist(), "coherence": m.coherence.tolist(),
                "model_gain": np.abs(r.model).tolist(), "model_phase": np.angle(r.model).tolist(),
                "linear_gain": np.abs(r.linear).tolist(), "linear_phase": np.angle(r.linear).tolist(),
                "model_inside": int(np.count_nonzero(inside)), "lines": len(m.frequency),
                "delay_phase_slope": None if r.delay is None else
                {"value": r.delay.value, "low": r.delay.low, "high": r.delay.high, "lines": r.delay.lines},
                "delay_fitted": {"value": delay.value, "low": delay.low, "high": delay.high}
                if delay.identifiable else None}
            entry["_response"] = r
            out.append(entry)
    return out


def _simulated(data: Any, segment: Any, initial: tuple[float, float] | None,
               values: Mapping[str, float]) -> tuple[np.ndarray, np.ndarray]:
    from dobhil.identify.fit import simulate
    return simulate(values, data, segment, initial)


def frf_lines(entries: list[dict[str, Any]]) -> list[str]:
    lines = []
    for e in entries:
        what = "velocity" if e["output"] == "velocity" else "force (K e + D dq, fitted K, D)"
        how = (f"at the multisine's {e['lines']} lines, {e['averages']} periods averaged" if e["method"] == "multisine"
               else f"Welch H1, {e['lines']} bins, {e['averages']} disjoint blocks")
        coh = np.asarray(e["coherence"])
        lines.append(f"frequency response {e['file']} {e['kind']} {e['t0']:.3f}-{e['t1']:.3f} s: torque -> {what}, "
                     f"{how}; coherence median {np.median(coh):.3f}; the fitted model (simulated, same "
                     f"estimator) inside the 95 % band at {e['model_inside']} of {e['lines']}")
        d, f = e["delay_phase_slope"], e["delay_fitted"]
        slope = ("too few coherent lines (coherence >= 0.9) for a phase slope" if d is None else
                 f"{d['value']:.6g} s, 95 % [{d['low']:.6g}, {d['high']:.6g}] ({d['lines']} lines)")
        fitted = "not identifiable" if f is None else f"{f['value']:.6g} s, 95 % [{f['low']:.6g}, {f['high']:.6g}]"
        lines.append(f"  delay from the phase slope {slope}; fitted {fitted}")
    return lines


def frf_figures(entries: list[dict[str, Any]], out: Path) -> list[Path]:
    from dobhil.plotting.frf_figures import FrfCurves, frf_figure
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for i, e in enumerate(entries):
        r = e["_response"]
        m = r.measured
        unit = "rad/s / N m" if m.output == "velocity" else "N m / N m"
        title = (f"{e['file']}: {e['kind']} {e['t0']:.3f}-{e['t1']:.3f} s, torque -> {m.output}")
        written.append(frf_figure(FrfCurves(m.frequency, m.response, m.low, m.high, m.phase_band, m.coherence,
                                            r.model, unit, m.method, title, r.linear), out / f"frf_segment_{i}.png"))
    return written
