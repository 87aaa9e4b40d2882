"""Two recorded runs side by side (``dobhil compare``): the RMS of the difference of their force,
the controller's estimated interaction torque ``tau_int_hat`` (what a real drive's run has too),
cycle by cycle over the cycles both have. It answers "does a run of the identified plant
respond like the original?".

A log of several axes is compared by one of its axes, named by ``--axis`` (refused without
one, naming the axes, as ``dobhil identify`` and ``dobhil replay`` refuse it:
:func:`dobhil.recording.axes.axis_log`); a single-axis log given with it is read as its one
axis, so an axis of a several-axis run compares with a run of that axis alone (the
identify workflow of docs/identify.md)."""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from dobhil.errors import ConfigError, LogFileError
from dobhil.recording.reader import LogFile, open_log


def force_of(path: str | os.PathLike[str] | LogFile, axis: str | None = None, *,
             one_axis: bool = False) -> tuple[float, dict[int, float]]:
    """(loop period, cycle -> tau_int_hat) of a recorded run: of its axis ``axis`` (None: its
    one axis; a several-axis log without it is refused, naming its axes); ``one_axis``: a
    single-axis log is read as its one axis whatever ``axis`` says."""
    run = _run_of(path, axis, one_axis=one_axis)
    return run.period, run.force


@dataclass(frozen=True)
class _Run:
    """What compare reads of a recorded run: its period [s], cycle -> tau_int_hat and
    cycle -> tau_ref [N m], and its config's reference keys."""

    period: float
    force: dict[int, float]
    reference: dict[int, float]
    keys: dict[str, Any]


def _run_of(path: str | os.PathLike[str] | LogFile, axis: str | None, *, one_axis: bool) -> _Run:
    """:func:`force_of`'s run, with its reference (recorded and configured)."""
    from dobhil.recording.axes import axis_log, is_axes_log
    whole = path if isinstance(path, LogFile) else open_log(path)
    name = os.fspath(whole.path)
    with axis_log(whole, axis if is_axes_log(whole) or not one_axis else None) as log:
        log.require_topic("/controller")
        if log.config is None:
            raise LogFileError(f"{name}: no 'config' metadata (not a recorded run?)")
        force: dict[int, float] = {}
        reference: dict[int, float] = {}
        try:
            for _, _, p in log.iter_messages(["/controller"]):
                value, ref = p["tau_int_hat"], p.get("tau_ref")
                force[int(p["cycle"])] = math.nan if value is None else float(value)
                reference[int(p["cycle"])] = math.nan if ref is None else float(ref)
        except (KeyError, TypeError, ValueError) as exc:
            raise LogFileError(f"{name}: a /controller message does not match its schema ({exc})") from None
        keys = {f"reference.{k}": v for k, v in dataclasses.asdict(log.config.reference).items()}
        return _Run(log.config.loop.period, force, reference, keys)


#: tau_ref [N m] two runs may differ by and still count as of the same reference (the same
#: config computes the same double; a reference rewritten through a CSV file rounds)
REFERENCE_TOLERANCE = 1e-9


def _note(first: str, second: str, a: _Run, b: _Run, common: list[int]) -> str:
    """One line saying how the two runs differ in what they were asked to do, '' when they do
    not: a difference of their force is then partly the difference of their references or
    left out where one run went on longer -- not the plants' or the designs' misfit."""
    parts = []
    if a.force.keys() != b.force.keys():
        parts.append(f"{first} has {len(a.force)} cycles, {second} {len(b.force)}: "
                     f"compared over the {len(common)} both have")
    apart = [abs(a.reference[c] - b.reference[c]) for c in common
             if math.isfinite(a.reference.get(c, math.nan)) and math.isfinite(b.reference.get(c, math.nan))]
    worst = max(apart, default=0.0)
    if worst > REFERENCE_TOLERANCE:
        keys = ", ".join(f"{k} {a.keys[k]!s} vs {b.keys[k]!s}" for k in a.keys if a.keys[k] != b.keys.get(k))
        parts.append(f"the references differ ({keys or 'the same keys'}): tau_ref up to {worst:.6g} N m apart")
    return "; ".join(parts)


def compare_logs(first: str | os.PathLike[str], second: str | os.PathLike[str],
                 axis: str | None = None) -> dict[str, Any]:
    """RMS and max of ``second - first`` force over the common, finite cycles; ``axis``: the
    axis of each several-axis log to compare (module docstring); ``note``: how the runs'
    cycles or references differ, '' when they do not (:func:`_note`)."""
    from dobhil.recording.axes import is_axes_log
    logs = (open_log(first), open_log(second))
    # --axis names an axis of the several-axis logs; with none of those it is checked against
    # the single-axis logs' one axis (refused unless it names it), as replay checks it
    several = any(is_axes_log(log) for log in logs)
    run_a, run_b = (_run_of(log, axis, one_axis=several) for log in logs)
    (period_a, a), (period_b, b) = (run_a.period, run_a.force), (run_b.period, run_b.force)
    if not math.isclose(period_a, period_b, rel_tol=1e-9):
        raise ConfigError(f"{os.fspath(second)}: period {period_b:g} s, but {os.fspath(first)} has "
                          f"{period_a:g} s; compare needs runs at the same period")
    common = sorted(c for c in a.keys() & b.keys() if math.isfinite(a[c]) and math.isfinite(b[c]))
    if not common:
        raise LogFileError(f"{os.fspath(first)} and {os.fspath(second)}: no control cycle in common")
    d = np.array([b[c] - a[c] for c in common])
    return {"first": os.fspath(first), "second": os.fspath(second), **({"axis": axis} if axis is not None else {}),
            "cycles": len(common), "period": period_a, "rms": float(np.sqrt(np.mean(d ** 2))),
            "max_abs": float(np.abs(d).max()), "note": _note(os.fspath(first), os.fspath(second), run_a, run_b, common)}


__all__ = ["compare_logs", "force_of"]
