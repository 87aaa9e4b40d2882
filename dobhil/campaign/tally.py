"""What a campaign's summary needs of its rows, kept in memory bounded in the number of runs.

Counts (runs, succeeded, retried, never settled, each metric's ``n`` and ``max``) are exact
whatever the number of runs. Percentiles need the values themselves: the metric columns of
the first :data:`SAMPLE` rows are kept, and past that a uniform sample of :data:`SAMPLE`
rows (Vitter's algorithm R, "Random sampling with a reservoir", ACM TOMS 11(1), 1985), so a
campaign of up to :data:`SAMPLE` runs has exact percentiles and a longer one percentiles of a
sample of that size (a percentile's rank error is then about ``sqrt(p (1 - p) / SAMPLE)``:
0.16 % of the runs at the median). The sample's generator is seeded from the campaign's seed
and rows arrive in run order, so the same seed gives the same summary on any number of
workers. The worst runs are a list of the :data:`~dobhil.campaign.campaign.WORST` rows.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from dobhil.campaign.runner import METRICS

#: rows whose metric and drawn columns are kept for percentiles and plots (8 bytes per cell:
#: 100,000 rows of 6 metrics, 3 draws and the success flag are 8 MB)
SAMPLE = 100_000


def badness(row: dict[str, Any]) -> tuple[int, float, int]:
    """Sort key of the worst runs: failed runs first (errors, then early stops), then by
    force RMS error, largest first; ties by run number."""
    rank = 0 if row["error"] else 1 if row["stop_reason"] != "done" else 2
    rms = row["force_rms_error"]
    return rank, -(rms if rms is not None else math.inf), int(row["run"])


def succeeded(row: dict[str, Any]) -> bool:
    return not row["error"] and row["stop_reason"] == "done"


class Tally:
    """Rows added one by one (:meth:`add`), in run order; counts, a sample, the worst rows."""

    def __init__(self, drawn: Sequence[str], seed: int, *, sample: int = SAMPLE, worst: int = 5) -> None:
        self.drawn = tuple(drawn)
        self.columns = (*METRICS, *self.drawn)
        self.runs = self.succeeded = self.retried = self.never_settled = 0
        self.count = dict.fromkeys(METRICS, 0)
        self.max = dict.fromkeys(METRICS, -math.inf)
        self.capacity = sample
        self._values = np.full((min(sample, 1024), len(self.columns)), np.nan)
        self._ok = np.zeros(self._values.shape[0], bool)
        self._kept = 0
        # its own stream of the campaign's seed: no run draws from it (theirs are its children)
        self._rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(2**32,)))
        self._worst_count = worst
        self._worst: list[dict[str, Any]] = []   # worst first

    def add(self, row: dict[str, Any]) -> None:
        self.runs += 1
        ok = succeeded(row)
        self.succeeded += ok
        self.retried += bool(row["retried"])
        self.never_settled += row.get("settled") is False
        for m in METRICS:
            if row[m] is not None:
                self.count[m] += 1
                self.max[m] = max(self.max[m], float(row[m]))
        slot = self._slot()
        if slot is not None:
            self._values[slot] = [np.nan if row[c] is None else float(row[c]) for c in self.columns]
            self._ok[slot] = ok
        self._keep_if_worst(row)

    def _slot(self) -> int | None:
        """Where the row just counted goes in the sample (None: not kept)."""
        if self._kept < self.capacity:
            if self._kept == self._values.shape[0]:   # grow by doubling up to the capacity
                size = min(self.capacity, 2 * self._kept)
                self._values = np.vstack([self._values, np.full((size - self._kept, len(self.columns)), np.nan)])
                self._ok = np.concatenate([self._ok, np.zeros(size - self._kept, bool)])
            self._kept += 1
            return self._kept - 1
        j = int(self._rng.integers(self.runs))   # algorithm R: keep row n with probability k/n
        return j if j < self.capacity else None

    def _keep_if_worst(self, row: dict[str, Any]) -> None:
        # a handful of rows: a sorted list is simpler than a heap and as fast
        if len(self._worst) < self._worst_count or badness(row) < badness(self._worst[-1]):
            self._worst = sorted([*self._worst, row], key=badness)[:self._worst_count]

    @property
    def sampled(self) -> bool:
        """Whether the percentiles come from a sample (more runs than :data:`SAMPLE`)."""
        return self.runs > self._kept

    @property
    def kept(self) -> int:
        return self._kept

    def column(self, name: str) -> np.ndarray:
        """A kept column (NaN: the row has no value), in the sample's order."""
        return np.array(self._values[:self._kept, self.columns.index(name)])

    def ok(self) -> np.ndarray:
        return np.array(self._ok[:self._kept])

    def worst(self) -> list[dict[str, Any]]:
        """The worst rows, worst first."""
        return list(self._worst)

    def percentiles(self, which: Sequence[float]) -> dict[str, dict[str, float]]:
        out: dict[str, dict[str, float]] = {}
        for m in METRICS:
            values = self.column(m)
            values = values[~np.isnan(values)]
            if values.size:
                out[m] = {**{f"p{p:g}": float(np.percentile(values, p)) for p in which},
                          "max": self.max[m], "n": self.count[m]}
        return out


__all__ = ["SAMPLE", "Tally", "badness", "succeeded"]
