"""One run of a campaign: pure data in (:class:`RunSpec`), one table row out (a dict).

:func:`run_one` is what a Dask worker calls (importable by name, no state): it builds the
run's config exactly as ``dobhil run CONFIG --set-file F ... --set k=v ...`` does
(:func:`dobhil.config.load_config` on the same strings), runs it in lockstep against the
in-process emulator and measures it. Whatever goes wrong -- a drawn value the config
refuses, an exception in the stack -- is the row's ``error``, never an exception: one bad
run must not end a campaign of thousands.

Metrics (all on the emulator's *true* interaction torque ``tau_int_true`` against the
reference ``tau_ref``, per cycle; ``t0`` = ``reference.start``):

- ``force_rms_error``: RMS of ``tau_ref - tau_int_true`` over the cycles at ``t >= t0``
  (before ``t0`` a step's offset may be bringing the servo into contact: not the loop's
  tracking);
- for ``reference.kind: step`` only (else empty): the response ``tau_int_true - level``
  from ``t0``, ``level`` the true torque of the last cycle before ``t0`` (0 if none), with
  ``final`` the mean of the last 10 % of its cycles (noise on): ``overshoot_pct`` above
  ``final``, ``rise_time`` 10-90 % of ``final``, ``settling_time`` into the 2 % band
  around ``final`` (:func:`dobhil.analysis.metrics.step_metrics`), relative to ``t0``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

#: share of a step response's last cycles averaged as its final value
FINAL_SHARE = 0.1

#: the row's metric columns, in table order (None: not defined for this run)
METRICS = ("force_rms_error", "overshoot_pct", "rise_time", "settling_time", "final_tau_int_true")


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

    def all_overrides(self) -> tuple[str, ...]:
        """The ``--set`` items of this run, in order (later ones win)."""
        drawn = tuple(f"{k}={v!r}" for k, v in self.draws)
        return (*self.overrides, *drawn, f"sensor.seed={self.sensor_seed}")

    def base_row(self) -> dict[str, Any]:
        """The row's columns known before the run: which run, its seed, its draws."""
        return {"run": self.index, "seed": self.seed, **dict(self.draws), "sensor_seed": self.sensor_seed}


def run_one(spec: RunSpec) -> dict[str, Any]:
    """Run ``spec`` and return its row (``error`` "" when it ran; its stop reason either way)."""
    row = {**spec.base_row(), **empty_result()}
    try:
        row.update(_run(spec))
    except Exception as exc:   # any failure is this run's row, not the campaign's end
        row["error"] = describe(exc)
    return row


def empty_result() -> dict[str, Any]:
    """The result columns of a run that did not run (an error)."""
    return {"stop_reason": "", "error": "", "cycles": 0, **{m: None for m in METRICS}, "overruns": 0}


def describe(exc: BaseException) -> str:
    """``ExcType: message`` on one line."""
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def _run(spec: RunSpec) -> dict[str, Any]:
    from dobhil.config import load_config, resolve_config
    from dobhil.runtime.session import RunSession
    config = load_config(spec.config, spec.all_overrides(), spec.set_files)
    with RunSession(config, emulate=True, lockstep=True, duration=spec.duration,
                    config_dir=resolve_config(spec.config).parent) as session:
        result = session.run()
    tr = result.trace
    ref = config.reference
    measured = metrics(tr["t"], tr["tau_ref"], tr["tau_int_true"], start=ref.start,
                       step=ref.kind == "step", amplitude=ref.amplitude)
    return {"stop_reason": result.stop.reason.name.lower(), "cycles": result.cycles,
            **measured, "overruns": result.overruns}


Array = NDArray[np.float64]


def metrics(t: Array, tau_ref: Array, tau_true: Array, *, start: float, step: bool,
            amplitude: float) -> dict[str, float | None]:
    """The metric columns of one run's trace (see the module's docstring)."""
    after = t >= start - 1e-9 * max(1.0, abs(start))   # the start cycle itself, despite rounding
    out: dict[str, float | None] = {m: None for m in METRICS}
    if not after.any():
        return out
    error = tau_ref[after] - tau_true[after]
    out["force_rms_error"] = _finite(math.sqrt(float(np.mean(error * error))))
    out["final_tau_int_true"] = _finite(float(tau_true[-1]))
    if step:
        out.update(_step(t, tau_true, after, start, amplitude))
    return out


def _step(t: Array, tau_true: Array, after: NDArray[np.bool_], start: float,
          amplitude: float) -> dict[str, float | None]:
    from dobhil.analysis.metrics import step_metrics
    before = np.flatnonzero(~after)
    level = float(tau_true[before[-1]]) if before.size else 0.0
    y = tau_true[after] - level
    tail = max(1, int(round(FINAL_SHARE * y.size)))
    m = step_metrics(t[after] - start, y, target=amplitude, final=float(np.mean(y[-tail:])))
    return {"overshoot_pct": m.overshoot_pct, "rise_time": m.rise_time, "settling_time": m.settling_time}


def _finite(x: float) -> float | None:
    return x if math.isfinite(x) else None
