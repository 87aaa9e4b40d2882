"""Two recorded runs side by side (``dobhil compare``): the RMS of the difference of their force,
the controller's estimated interaction torque ``tau_int_hat`` (what a real drive's run has too),
cycle by cycle over the cycles both have. It answers "does a run of the identified plant
respond like the original?"."""

from __future__ import annotations

import math
import os
from typing import Any

import numpy as np

from dobhil.errors import ConfigError, LogFileError


def force_of(path: str | os.PathLike[str]) -> tuple[float, dict[int, float]]:
    """(loop period, cycle -> tau_int_hat) of a recorded run."""
    from dobhil.recording.reader import open_log
    name = os.fspath(path)
    with open_log(path) as log:
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


def compare_logs(first: str | os.PathLike[str], second: str | os.PathLike[str]) -> dict[str, Any]:
    """RMS and max of ``second - first`` force over the common, finite cycles."""
    period_a, a = force_of(first)
    period_b, b = force_of(second)
    if not math.isclose(period_a, period_b, rel_tol=1e-9):
        raise ConfigError(f"{os.fspath(second)}: period {period_b:g} s, but {os.fspath(first)} has "
                          f"{period_a:g} s; compare needs runs at the same period")
    common = sorted(c for c in a.keys() & b.keys() if math.isfinite(a[c]) and math.isfinite(b[c]))
    if not common:
        raise LogFileError(f"{os.fspath(first)} and {os.fspath(second)}: no control cycle in common")
    d = np.array([b[c] - a[c] for c in common])
    return {"first": os.fspath(first), "second": os.fspath(second), "cycles": len(common), "period": period_a,
            "rms": float(np.sqrt(np.mean(d ** 2))), "max_abs": float(np.abs(d).max())}


__all__ = ["compare_logs", "force_of"]
