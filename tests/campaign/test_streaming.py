"""A campaign of any length: its plan drawn as the cluster has room (the first row back before
the rest is drawn), rows in run order equal to the eager path's, a summary in bounded memory,
``--workers`` past the cores capped in one line, a local cluster that does not start in time
one line too."""

from __future__ import annotations

import itertools
import threading
import tracemalloc
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dobhil.campaign.campaign import Campaign, execute, stream, summarise, worst_runs
from dobhil.campaign.draws import parse_vary
from dobhil.campaign.runner import METRICS
from dobhil.campaign.tally import Tally
from dobhil.cli.main import main
from dobhil.cluster import START_THREAD, ClusterError, local_workers, map_streaming, open_client, usable_cores


def _campaign(runs: int, seed: int = 3) -> Campaign:
    return Campaign(config="demo", set_files=(), overrides=(), seed=seed, duration=0.05, runs=runs,
                    varies=(parse_vary("plant.inertia=normal:0.25:0.02"),
                            parse_vary("environment.damping=uniform:20:80")))


def test_a_billion_run_plan_is_drawn_lazily_with_the_eager_plans_values() -> None:
    huge = _campaign(10**9).specs()
    assert isinstance(huge, Iterator)
    # run i's draws depend on (seed, i) only: the lazy plan of a billion runs starts as the eager
    # plan of five does
    assert list(itertools.islice(huge, 5)) == _campaign(5).plan()


def _square(x: int) -> int:
    return x * x


def test_the_first_result_arrives_before_the_items_are_all_drawn(dask_client: Any) -> None:
    drawn = [0]

    def items() -> Iterator[int]:
        for i in range(2000):
            drawn[0] += 1
            yield i
    window = 8
    results = map_streaming(dask_client, _square, items(), index=lambda i: i, window=window)
    first = next(results)
    assert first[0] == 0 and first[1].value == 0
    assert drawn[0] <= window   # only the window was drawn, not the 2000
    got = [first, *itertools.islice(results, 40)]
    assert [i for i, _ in got] == list(range(41)) and all(r.value == i * i for i, r in got)
    assert drawn[0] <= len(got) + window
    results.close()   # the rest is cancelled, never drawn


def test_a_billion_run_campaigns_first_row_comes_back_with_only_a_window_drawn(dask_client: Any) -> None:
    drawn = [0]

    def specs() -> Iterator[Any]:
        # the billion-run plan's first 8 (the test ends them all: no run left running after it)
        for spec in itertools.islice(_campaign(10**9).specs(), 8):
            drawn[0] += 1
            yield spec
    rows = stream(dask_client, specs(), window=4)
    first = next(rows)
    assert first["run"] == 0 and first["error"] == "" and drawn[0] <= 4
    assert [first["run"], *(row["run"] for row in rows)] == list(range(8))


def test_streamed_rows_equal_the_eager_tables_in_run_order(dask_client: Any) -> None:
    c = _campaign(7)
    eager = execute(dask_client, c.plan())
    seen: list[int] = []
    streamed = list(stream(dask_client, c.specs(), progress=lambda row: seen.append(row["run"]), window=2))
    assert streamed == eager
    assert sorted(seen) == list(range(7))


def _row(run: int, rng: np.random.Generator) -> dict[str, Any]:
    error = "ValueError: x" if rng.random() < 0.05 else ""
    row: dict[str, Any] = {"run": run, "error": error, "stop_reason": "" if error else "done", "retried": False,
                           "settled": None, "k": float(rng.normal())}
    for m in METRICS:
        row[m] = None if error or rng.random() < 0.1 else float(rng.random())
    return row


def _tally_held(runs: int) -> int:
    """Bytes held by what the tally allocated (any frame in its module: its numpy arrays
    too), after ``runs`` rows; other threads' allocations (a Dask client's) are not counted."""
    import dobhil.campaign.tally as module
    rng = np.random.default_rng(1)
    tracemalloc.start(8)
    try:
        tally = Tally(["k"], seed=0, sample=500)
        for i in range(runs):
            tally.add(_row(i, rng))
        snapshot = tracemalloc.take_snapshot()
    finally:
        tracemalloc.stop()
    assert tally.runs == runs and tally.kept == min(runs, 500)
    mine = snapshot.filter_traces([tracemalloc.Filter(True, module.__file__, all_frames=True)])
    return sum(stat.size for stat in mine.statistics("filename"))


def test_the_summarys_memory_does_not_grow_with_the_runs() -> None:
    small, large = _tally_held(1_000), _tally_held(10_000)
    # ten times the rows: a summary that kept them would hold about ten times the memory
    assert large < 1.5 * small, (small, large)


def test_past_the_sample_counts_and_maxima_stay_exact_and_percentiles_close() -> None:
    rng = np.random.default_rng(7)
    rows = [_row(i, rng) for i in range(5_000)]
    tally = Tally(["k"], seed=0, sample=1_000)
    for row in rows:
        tally.add(row)
    p = tally.percentiles((50.0,))
    values = np.array([r["force_rms_error"] for r in rows if r["force_rms_error"] is not None])
    assert tally.sampled and p["force_rms_error"]["n"] == values.size
    assert p["force_rms_error"]["max"] == values.max()
    # a sample of 1000: the median's rank is off by about sqrt(0.25/1000) = 1.6 % of the runs
    rank = np.mean(values <= p["force_rms_error"]["p50"])
    assert abs(rank - 0.5) < 5 * np.sqrt(0.25 / 1_000)
    assert summarise(rows).sampled == 0   # the default sample holds all 5000: exact


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.sampled_from(["", "E: x"]), st.sampled_from(["done", "fault"]),
                          st.one_of(st.none(), st.floats(0, 10))), max_size=40),
       st.integers(1, 6))
def test_the_tallys_worst_runs_are_the_whole_tables(cells: list[tuple[str, str, float | None]],
                                                     count: int) -> None:
    rows = [{"run": i, "error": e, "stop_reason": s, "force_rms_error": rms, "retried": False, "settled": None,
             **{m: None for m in METRICS if m != "force_rms_error"}} for i, (e, s, rms) in enumerate(cells)]
    tally = Tally([], seed=0, worst=count)
    for row in rows:
        tally.add(row)
    assert [r["run"] for r in tally.worst()] == list(worst_runs(rows, count))


def test_workers_past_the_cores_are_capped_with_one_line() -> None:
    cores = usable_cores()
    assert local_workers(None) == (cores, None)
    assert local_workers(cores) == (cores, None)
    n, note = local_workers(cores + 998)
    assert n == cores and note is not None and "\n" not in note
    assert f"--workers {cores + 998}: capped at {cores}" in note


def test_the_command_caps_workers_in_one_line_and_runs(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["montecarlo", "demo", "--runs", "2", "--duration", "0.05", "--workers", "1000",
                 "--vary", "plant.inertia=normal:0.25:0.02"]) == 0
    out, err = capsys.readouterr()
    capped = [line for line in err.splitlines() if "capped at" in line]
    assert capped == [f"montecarlo: --workers 1000: capped at {usable_cores()}, the cores this machine gives "
                      "this process (more local processes than cores run no faster); a --scheduler's workers "
                      "are not capped"]
    assert "Traceback" not in err and f"a local cluster of {usable_cores()} worker process" in out


def test_a_local_cluster_that_does_not_start_in_time_is_one_line() -> None:
    with pytest.raises(ClusterError, match=r"^the local cluster of 1 worker process did not start within 1e-06 s; "
                                           r"give fewer --workers"), \
            open_client(workers=1, processes=False, start_within=1e-6):
        pass
    # the cluster given up on is closed by its own thread once it is up: nothing is left running
    for thread in threading.enumerate():
        if thread.name == START_THREAD:
            thread.join()
