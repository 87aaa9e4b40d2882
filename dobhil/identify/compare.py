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

import math
import os
from typing import Any

import numpy as np

from dobhil.errors import ConfigError, LogFileError
from dobhil.recording.reader import LogFile, open_log


def force_of(path: str | os.PathLike[str] | LogFile, axis: str | None = None, *,
             one_axis: bool = False) -> tuple[float, dict[int, float]]:
    """(loop period, cycle -> tau_int_hat) of a recorded run: of its axis ``axis`` (None: its
    one axis; a several-axis log without it is refused, naming its axes); ``one_axis``: a
    single-axis log is read as its one axis whatever ``axis`` says."""
    from dobhil.recording.axes import axis_log, is_axes_log
    whole = path if isinstance(path, LogFile) else open_log(path)
    name = os.fspath(whole.path)
    with axis_log(whole, axis if is_axes_log(whole) or not one_axis else None) as log:
        log.require_topic("/controller")
        if log.config is None:
            raise LogFileError(f"{name}: no 'config' metadata (not a recorded run?)")
        force: dict[int, float] = {}
        try:
            for _, _, p in log.iter_messages(["/controller"]):
                value = p["tau_int_hat"]
                force[int(p["cycle"])] = math.nan if value is None else float(value)
        except (KeyError, TypeError, ValueError) as exc:
            raise LogFileError(f"{name}: a /controller message does not match its schema ({exc})") from None
        return log.config.loop.period, force


def compare_logs(first: str | os.PathLike[str], second: str | os.PathLike[str],
                 axis: str | None = None) -> dict[str, Any]:
    """RMS and max of ``second - first`` force over the common, finite cycles; ``axis``: the
    axis of each several-axis log to compare (module docstring)."""
    from dobhil.recording.axes import is_axes_log
    logs = (open_log(first), open_log(second))
    # --axis names an axis of the several-axis logs; with none of those it is checked against
    # the single-axis logs' one axis (refused unless it names it), as replay checks it
    several = any(is_axes_log(log) for log in logs)
    period_a, a = force_of(logs[0], axis, one_axis=several)
    period_b, b = force_of(logs[1], axis, one_axis=several)
    if not math.isclose(period_a, period_b, rel_tol=1e-9):
        raise ConfigError(f"{os.fspath(second)}: period {period_b:g} s, but {os.fspath(first)} has "
                          f"{period_a:g} s; compare needs runs at the same period")
    common = sorted(c for c in a.keys() & b.keys() if math.isfinite(a[c]) and math.isfinite(b[c]))
    if not common:
        raise LogFileError(f"{os.fspath(first)} and {os.fspath(second)}: no control cycle in common")
    d = np.array([b[c] - a[c] for c in common])
    return {"first": os.fspath(first), "second": os.fspath(second), **({"axis": axis} if axis is not None else {}),
            "cycles": len(common), "period": period_a, "rms": float(np.sqrt(np.mean(d ** 2))),
            "max_abs": float(np.abs(d).max())}


__all__ = ["compare_logs", "force_of"]
