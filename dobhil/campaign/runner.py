"""One run of a campaign: pure data in (:class:`RunSpec`), one table row out (a dict).

:func:`run_one` is what a Dask worker calls (importable by name, no state): it builds the
run's config exactly as ``dobhil run CONFIG --set-file F ... --set k=v ...`` does
(:func:`dobhil.config.load_config` on the same strings), runs it in lockstep against the
in-process emulator and measures it. Whatever goes wrong -- a drawn value the config
refuses, an exception in the stack -- is the row's ``error``, never an exception: one bad
run must not end a campaign of thousands.

Metrics (all on the emulator's *true* interaction torque ``tau_int_true`` against the
reference ``tau_ref``, per cycle; ``t0`` = ``reference.start``; "the final window" = the
last :data:`FINAL_SHARE` of the cycles from ``t0``, where noise is averaged out):

- ``force_rms_error``: RMS of ``tau_ref - tau_int_true`` over the cycles at ``t >= t0``
  (before ``t0`` a step's offset may be bringing the servo into contact: not the loop's
  tracking);
- ``final_error``: the mean of ``tau_ref - tau_int_true`` over the final window (the
  steady-state error, signed: > 0 the true torque is short of the command);
- ``final_tau_int_true``: the true torque of the last cycle (what ``dobhil run`` reports as
  its final value); ``final_tau_ref``: the command of the last cycle (not a metric: what the
  final values are compared with);
- for ``reference.kind: step`` only (else empty): the response ``tau_int_true - level``
  from ``t0``, ``level`` the true torque of the last cycle before ``t0`` (0 if none), with
  ``final`` its mean over the final window: ``overshoot_pct`` above ``final`` (empty when
  ``final`` is 0), ``rise_time`` 10-90 % of ``final`` (empty when the response never
  crosses 90 %, or ``final`` is 0), ``settling_time`` into the band of ``SETTLING_BAND`` (2 %) x ``|final|``
  around ``final`` (:mod:`dobhil.analysis.metrics`), all relative to ``t0``.
  ``settled`` says whether the response is inside that band from its settling time to the
  run's end *and through the whole final window*: a response still leaving the band while its
  final value is being averaged has not settled, and then ``settling_time`` is empty -- not
  the run's end, which would read as a (slow) settling time.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from dobhil.config import Config, load_config
from dobhil.config.axes import load_axes
from dobhil.errors import exception_line

#: share of a step response's last cycles averaged as its final value
FINAL_SHARE = 0.1

#: the row's metric columns, in table order (None: not defined for this run)
METRICS = ("force_rms_error", "final_error", "overshoot_pct", "rise_time", "settling_time", "final_tau_int_true")

#: the row's columns that are measured but are no metric: whether a step settled (None: not
#: a step, or no run), the command of the last cycle
MEASURED = ("settled", "final_tau_ref")


@dataclass(frozen=True)
class RunSpec:
    """Everything run ``index`` needs, as the command line would say it: the config (a path,
    or a shipped name), ``--set-file`` files, ``--set`` overrides (the campaign's own first,
    then the draws and ``sensor.seed``), the run's duration."""

    index: int
    seed: int
    config: str
    set_files: tuple[str, ...]
    overrides: tuple[str, ...]
    draws: tuple[tuple[str, float | int], ...]
    sensor_seed: int
    duration: float | None
    #: the axis of a config that lists ``axes:`` the runs are of ("" for a single-axis config):
    #: its drawn keys are that axis' own (``axes.NAME.key``), so they win over its own values
    axis: str = ""

    def all_overrides(self) -> tuple[str, ...]:
        """The ``--set`` items of this run, in order (later ones win)."""
        own = f"axes.{self.axis}." if self.axis else ""
        drawn = tuple(f"{own}{k}={v!r}" for k, v in self.draws)
        return (*self.overrides, *drawn, f"{own}sensor.seed={self.sensor_seed}")

    def load(self) -> Config:
        """The run's config, as ``dobhil run`` builds it from the same strings."""
        return load_run_config(self.config, self.all_overrides(), self.set_files, self.axis)

    def base_row(self) -> dict[str, Any]:
        """The row's columns known before the run: which run, its seed, its draws."""
        return {"run": self.index, "seed": self.seed, **dict(self.draws), "sensor_seed": self.sensor_seed}


def load_run_config(config: str, overrides: Sequence[str], set_files: Sequence[str], axis: str = "") -> Config:
    """``load_config`` of a config, or for ``axis`` that axis' of a config that lists ``axes:``
    (:func:`dobhil.config.axes.load_axes`)."""
    if axis:
        return load_axes(config, overrides, set_files).axis(axis).config
    return load_config(config, overrides, set_files)


def run_one(spec: RunSpec) -> dict[str, Any]:
    """Run ``spec`` and return its row (``error`` "" when it ran; its stop reason either way)."""
    row = {**spec.base_row(), **empty_result()}
    try:
        row.update(_run(spec))
    except Exception as exc:   # any failure is this run's row, not the campaign's end
        row["error"] = exception_line(exc)
    return row


def empty_result() -> dict[str, Any]:
    """The result columns of a run that did not run (an error)."""
    return {"stop_reason": "", "error": "", "cycles": 0, **{m: None for m in (*METRICS, *MEASURED)},
            "overruns": 0}


def _run(spec: RunSpec) -> dict[str, Any]:
    from dobhil.config import resolve_config
    from dobhil.runtime.session import RunSession
    config = spec.load()
    with RunSession(config, emulate=True, lockstep=True, duration=spec.duration,
                    config_dir=resolve_config(spec.config).parent) as session:
        result = session.run()
    tr = result.trace
    ref = config.reference
    measured = metrics(tr["t"], tr["tau_ref"], tr["tau_int_true"], start=ref.start,
                       step=ref.kind == "step", amplitude=ref.amplitude)
    # the stop reason by its enum name, whichever it is: a reason added to the runtime flows
    # into the table as it is
    return {"stop_reason": result.stop.reason.name.lower(), "cycles": result.cycles,
            **measured, "overruns": result.overruns}


Array = NDArray[np.float64]


def metrics(t: Array, tau_ref: Array, tau_true: Array, *, start: float, step: bool,
            amplitude: float) -> dict[str, float | bool | None]:
    """The metric (and :data:`MEASURED`) columns of one run's trace (see the module's docstring)."""
    after = t >= start - 1e-9 * max(1.0, abs(start))   # the start cycle itself, despite rounding
    out: dict[str, float | bool | None] = {m: None for m in (*METRICS, *MEASURED)}
    if not after.any():
        return out
    error = tau_ref[after] - tau_true[after]
    tail = final_window(int(error.size))
    out["force_rms_error"] = _finite(math.sqrt(float(np.mean(error * error))))
    out["final_error"] = _finite(float(np.mean(error[-tail:])))
    out["final_tau_int_true"] = _finite(float(tau_true[-1]))
    out["final_tau_ref"] = _finite(float(tau_ref[-1]))
    if step:
        out.update(_step(t, tau_true, after, start, amplitude))
    return out


def final_window(cycles: int) -> int:
    """How many of the last cycles make the final window (at least one)."""
    return max(1, int(round(FINAL_SHARE * cycles)))


def _step(t: Array, tau_true: Array, after: NDArray[np.bool_], start: float,
          amplitude: float) -> dict[str, float | bool | None]:
    from dobhil.analysis.metrics import step_metrics
    before = np.flatnonzero(~after)
    level = float(tau_true[before[-1]]) if before.size else 0.0
    y = tau_true[after] - level
    tail = final_window(int(y.size))
    final = float(np.mean(y[-tail:]))
    m = step_metrics(t[after] - start, y, target=amplitude, final=final)
    settled = _settled(y, final, tail) if m.final_value is not None else None
    # a response that ends where it began has no 10-90 % of anything (step_metrics says 0)
    rise = m.rise_time if final != 0 else None
    return {"overshoot_pct": m.overshoot_pct, "rise_time": rise, "settled": settled,
            "settling_time": m.settling_time if settled else None}


def _settled(y: Array, final: float, tail: int) -> bool | None:
    """Inside the band around ``final`` from some cycle on, through the last ``tail`` cycles;
    None when ``final`` is 0 (a band of width 0 says nothing)."""
    from dobhil.analysis.metrics import SETTLING_BAND
    if final == 0 or not math.isfinite(final):
        return None
    outside = np.flatnonzero(np.abs(y - final) > SETTLING_BAND * abs(final))
    return bool(outside.size == 0 or outside[-1] < y.size - tail)


def _finite(x: float) -> float | None:
    return x if math.isfinite(x) else None
