"""A campaign: its plan (one :class:`~dobhil.campaign.runner.RunSpec` per run), its execution
as Dask tasks (:func:`dobhil.cluster.map_ordered`: one task per run, rows back in run
order), and what is said about the table: the success rate with its exact confidence
interval, the metrics' percentiles over the runs that have each, their medians against the
reference run (the config as given: :mod:`dobhil.campaign.compare`), the worst runs and the
command reproducing each alone.

A run *succeeded* when it ran to its end: no error and stop reason ``done``. Any other stop
reason is the runtime's, by name, whatever it is: the campaign keeps no list of them.
"""

from __future__ import annotations

import math
import shlex
import uuid
from collections.abc import Callable, Generator, Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from dobhil.campaign.compare import CommandCheck, Comparison, Floors, command_check, compare
from dobhil.campaign.draws import Vary, draw
from dobhil.campaign.tally import Tally, badness, succeeded
from dobhil.campaign.runner import MEASURED, METRICS, RunSpec, empty_result, load_run_config, run_one
from dobhil.config import Config

#: the noise and quantisation a campaign turns on when the config has neither: a 14-bit
#: absolute encoder (16384 counts per revolution, 0.38 mrad) and 0.01 rad/s of velocity
#: estimate noise, the order of a drive's PLL estimate from such an encoder at 1 kHz
NOISE_DEFAULTS: tuple[str, ...] = ("sensor.encoder_resolution=16384", "sensor.velocity_noise=0.01")

#: the percentiles the summary gives of each metric
PERCENTILES = (5.0, 50.0, 95.0)

#: how many of the worst runs the summary lists
WORST = 5

#: the table's columns after the drawn keys (the drawn keys come after run, seed)
RESULT_COLUMNS = ("sensor_seed", "stop_reason", "error", "cycles", *METRICS, *MEASURED, "overruns", "retried")

#: the reference run's index in its :class:`RunSpec` (no run of the campaign has it)
REFERENCE = -1


@dataclass(frozen=True)
class Campaign:
    """What ``dobhil montecarlo`` was asked: ``overrides`` are the ``--set`` items the runs
    share (the campaign's noise defaults first, then the user's), ``duration`` None for the
    config's ``loop.duration``."""

    config: str
    set_files: tuple[str, ...]
    overrides: tuple[str, ...]
    varies: tuple[Vary, ...]
    runs: int
    seed: int
    duration: float | None
    #: the axis of a config that lists ``axes:`` (:attr:`RunSpec.axis`), "" for a single-axis one
    axis: str = ""

    def load(self) -> Config:
        """The shared config (the campaign's overrides, nothing drawn): the axis' for an axis."""
        return load_run_config(self.config, self.overrides, self.set_files, self.axis)

    def plan(self) -> list[RunSpec]:
        """Every run's spec in a list: for a few runs; a campaign streams :meth:`specs`."""
        return list(self.specs())

    def specs(self) -> Iterator[RunSpec]:
        """Each run's spec, drawn when asked for: run ``i``'s draws depend on ``(seed, i)``
        alone (:func:`~dobhil.campaign.draws.draw`), so drawing them lazily gives the same
        values as drawing them all first, and memory does not grow with ``runs``."""
        return (self.spec(i) for i in range(self.runs))

    def spec(self, index: int) -> RunSpec:
        values, sensor_seed = draw(self.varies, self.seed, index)
        return RunSpec(index=index, seed=self.seed, config=self.config, set_files=self.set_files,
                       overrides=self.overrides, draws=tuple(values.items()), sensor_seed=sensor_seed,
                       duration=self.duration, axis=self.axis)

    def reference_spec(self) -> RunSpec:
        """The config as given -- nominal values, nothing drawn -- with the campaign's
        overrides (its noise) and an emulator seed from ``SeedSequence(seed)`` itself, which
        no run uses (the runs' come from its children)."""
        sensor_seed = int(np.random.SeedSequence(self.seed).generate_state(1, np.uint32)[0])
        return RunSpec(index=REFERENCE, seed=self.seed, config=self.config, set_files=self.set_files,
                       overrides=self.overrides, draws=(), sensor_seed=sensor_seed, duration=self.duration,
                       axis=self.axis)

    def columns(self) -> list[str]:
        return ["run", "seed", *(v.key for v in self.varies), *RESULT_COLUMNS]


def execute(client: Any, specs: Sequence[RunSpec], *,
            progress: Callable[[dict[str, Any]], None] | None = None) -> list[dict[str, Any]]:
    """Every run of ``specs`` as one Dask task on ``client``; the rows in run order. A task
    that failed outside :func:`run_one` (its worker lost too often) is a row with the error.
    ``progress(row)`` as each run comes back (``retried`` not known yet)."""
    from dobhil.cluster import MapResult, map_ordered
    # a prefix of its own: two campaigns on one scheduler must not share task keys
    prefix = f"dobhil-montecarlo-{uuid.uuid4().hex[:12]}"

    def arrived(index: int, value: Any, error: str | None) -> None:
        if progress is not None:
            progress(_row(specs[index], MapResult(value, error, False)))
    results = map_ordered(client, run_one, specs, key_prefix=prefix, arrived=arrived)
    return [_row(spec, r) for spec, r in zip(specs, results)]


def stream(client: Any, specs: Iterable[RunSpec], *, progress: Callable[[dict[str, Any]], None] | None = None,
           window: int | None = None) -> Generator[dict[str, Any], None, None]:
    """:func:`execute` for a campaign of any length: ``specs`` consumed as the cluster has room
    (:func:`dobhil.cluster.map_streaming`), each row given back in run order as soon as it and
    the runs before it are done. Memory holds a bounded window of runs, not the campaign."""
    from dobhil.cluster import MapResult, map_streaming
    prefix = f"dobhil-montecarlo-{uuid.uuid4().hex[:12]}"
    in_flight: dict[int, RunSpec] = {}

    def specs_seen() -> Iterator[RunSpec]:
        for spec in specs:
            in_flight[spec.index] = spec
            yield spec

    def arrived(index: int, value: Any, error: str | None) -> None:
        if progress is not None:
            progress(_row(in_flight[index], MapResult(value, error, False)))
    for index, result in map_streaming(client, run_one, specs_seen(), key_prefix=prefix, arrived=arrived,
                                       index=lambda spec: spec.index, window=window):
        yield _row(in_flight.pop(index), result)


def _row(spec: RunSpec, result: Any) -> dict[str, Any]:
    if result.error is not None or not isinstance(result.value, dict):
        row = {**spec.base_row(), **empty_result(), "error": result.error or "no result"}
    else:
        row = dict(result.value)
    row["retried"] = bool(result.retried)
    return row


@dataclass(frozen=True)
class Summary:
    runs: int
    succeeded: int
    rate: float
    ci_low: float
    ci_high: float
    retried: int
    #: metric -> {"p5": .., "p50": .., "p95": .., "max": .., "n": ..} over the ``n`` runs
    #: where the metric is defined (a metric no run has is absent)
    percentiles: dict[str, dict[str, float]]
    #: the worst runs' numbers, worst first
    worst: tuple[int, ...]
    #: step responses that never settled into the band (``settled`` False)
    never_settled: int = 0
    #: the reference run's row (None: not run)
    reference: dict[str, Any] | None = None
    #: each metric's median against the reference's
    comparisons: tuple[Comparison, ...] = ()
    #: the final true torque against the command
    command: CommandCheck | None = None
    #: the worst runs' rows, worst first
    worst_rows: tuple[dict[str, Any], ...] = ()
    #: 0: the percentiles are over every run; else over a uniform sample of this many runs
    sampled: int = 0

    def as_dict(self) -> dict[str, Any]:
        return {"runs": self.runs, "succeeded": self.succeeded, "success_rate": self.rate,
                "success_rate_ci95": [self.ci_low, self.ci_high], "retried": self.retried,
                "percentiles": self.percentiles,
                "percentiles_sampled_runs": self.sampled or None, "never_settled": self.never_settled,
                "reference": self.reference, "comparisons": [c.as_dict() for c in self.comparisons],
                "worse_than_reference": [c.metric for c in self.comparisons if c.worse],
                "final_vs_command": self.command.as_dict() if self.command else None}


def summarise(rows: Iterable[dict[str, Any]], reference: dict[str, Any] | None = None,
              floors: Floors | None = None, *, seed: int = 0, drawn: Sequence[str] = ()) -> Summary:
    """:meth:`Tally.add` of each row, then :func:`summary_of`."""
    tally = Tally(drawn, seed, worst=WORST)
    for row in rows:
        tally.add(row)
    return summary_of(tally, reference, floors)


def summary_of(tally: Tally, reference: dict[str, Any] | None = None, floors: Floors | None = None) -> Summary:
    """The success rate (95 % Clopper-Pearson interval), retries, metric percentiles (of the
    tally's sample past :data:`~dobhil.campaign.tally.SAMPLE` runs), worst runs; with a
    ``reference`` row (and the campaign's tolerance ``floors``), each metric's median
    against it (:mod:`dobhil.campaign.compare`)."""
    from scipy.stats import binomtest
    n, k = tally.runs, tally.succeeded
    ci = binomtest(k, n).proportion_ci(0.95, method="exact") if n else None
    percentiles = tally.percentiles(PERCENTILES)
    comparisons: tuple[Comparison, ...] = ()
    command = None
    if reference is not None and floors is not None:
        comparisons = tuple(compare(percentiles, reference, floors))
        command = command_check(percentiles, reference, floors)
    worst = tally.worst()
    return Summary(runs=n, succeeded=k, rate=k / n if n else math.nan,
                   ci_low=float(ci.low) if ci else math.nan, ci_high=float(ci.high) if ci else math.nan,
                   retried=tally.retried, percentiles=percentiles,
                   worst=tuple(int(r["run"]) for r in worst), never_settled=tally.never_settled,
                   reference=reference, comparisons=comparisons, command=command,
                   worst_rows=tuple(worst), sampled=tally.kept if tally.sampled else 0)


def worst_runs(rows: Sequence[dict[str, Any]], count: int = WORST) -> tuple[int, ...]:
    """Indices of the ``count`` worst rows (:func:`~dobhil.campaign.tally.badness`)."""
    return tuple(sorted(range(len(rows)), key=lambda i: (*badness(rows[i])[:2], i))[:count])


def reproduce_command(spec: RunSpec) -> str:
    """The shell command that runs ``spec`` alone, as the campaign ran it."""
    words = ["dobhil", "run", spec.config, "--emulate", "--lockstep", *(["--axis", spec.axis] if spec.axis else [])]
    if spec.duration is not None:
        words += ["--duration", repr(spec.duration)]
    for f in spec.set_files:
        words += ["--set-file", f]
    for item in spec.all_overrides():
        words += ["--set", item]
    return shlex.join(words)


__all__ = ["Campaign", "NOISE_DEFAULTS", "REFERENCE", "Summary", "execute", "reproduce_command", "stream", "succeeded",
           "summarise", "summary_of", "worst_runs"]
