"""``dobhil sweep`` with its chunks as Dask tasks: bit for bit the local sweep (NaN and inf
points included), the progress in points, and bad --scheduler/--workers as one line, exit 2."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dobhil.analysis.sweep import Axis, SweepResult, parse_vary, sweep
from dobhil.cli.main import main
from dobhil.cluster import map_values
from dobhil.config import load_config

ROOT = Path(__file__).resolve().parents[2]
FIG2B = str(ROOT / "configs/paper/fig2b.yaml")
#: the command line's grid (within the keys' ranges)
VARY = ["plant.inertia=log:1e-12:1:8", "design.dob_bandwidth=log:1:1e7:5"]
#: a grid with finite, unanswered (NaN: the matrices overflow at an inertia of 1e-300, past the
#: key's floor, so built here as --vary cannot) and, continuous, unbounded (inf) points; 40
#: points in chunks of 7: six chunks, the last one short
AXES = (Axis("plant.inertia", np.geomspace(1e-300, 1, 8)), parse_vary(VARY[1]))


def assert_identical(a: SweepResult, b: SweepResult) -> None:
    for name in ("stable", "minimum_phase", "max_stable_gain", "interval_count", "drifting"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape, name
        assert np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), name
    assert [ax.key for ax in a.axes] == [ax.key for ax in b.axes]


@pytest.mark.parametrize("sampled", [False, True])
def test_the_sweep_on_dask_is_the_local_sweep_bit_for_bit(dask_client: object, sampled: bool) -> None:
    config, axes = load_config(FIG2B), AXES
    local_points: list[int] = []
    dask_points: list[int] = []
    local = sweep(config, axes, sampled=sampled, chunk=7, progress=local_points.append)
    on_dask = sweep(config, axes, sampled=sampled, chunk=7, progress=dask_points.append,
                    map_chunks=lambda fn, chunks, done: map_values(dask_client, fn, chunks, progress=done))  # type: ignore[arg-type]
    assert_identical(local, on_dask)
    # the grid really has unanswered and finite points (and unbounded ones, continuous), or the
    # comparison proves less than it says
    gains = local.max_stable_gain
    assert np.isnan(gains).any() and np.isfinite(gains).any() and np.isinf(gains).any() != sampled
    assert local_points == [7, 7, 7, 7, 7, 5]
    assert sorted(dask_points) == [5, 7, 7, 7, 7, 7] and sum(dask_points) == 40


def run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.parametrize(("extra", "message"), [
    (["--scheduler", "nonsense"], "dobhil sweep: error: --scheduler 'nonsense': not a scheduler address; allowed: "
     "tcp://HOST:PORT or HOST:PORT (e.g. tcp://10.0.0.5:8786), or local"),
    (["--scheduler", "tls://h:1"], "dobhil sweep: error: --scheduler 'tls://h:1': not a scheduler address"),
    (["--workers", "2"], "dobhil sweep: error: --workers N goes with --scheduler local"),
    (["--scheduler", "tcp://h:1", "--workers", "2"], "dobhil sweep: error: --workers N goes with --scheduler local"),
    (["--scheduler", "local", "--workers", "0"], "dobhil sweep: error: --workers 0: must be at least 1"),
])
def test_bad_cluster_arguments_are_one_line_and_exit_2(extra: list[str], message: str,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = run(["sweep", FIG2B, "--vary", VARY[0], *extra], capsys)
    assert (code, out) == (2, "")
    assert err.startswith(message) and err.count("\n") == 1


def test_a_scheduler_that_does_not_answer_ends_the_process_with_one_line(silent_listener: str) -> None:
    """As a process (imports, Dask's threads and all): exit 2, one line, no traceback -- on
    the silent listener, the case Dask alone hangs on (a closed port is the same one line,
    in-process: tests/cluster/test_cluster.py, tests/campaign/test_cli.py). The limit here
    only catches a hang; the 10 s bound is measured on an idle machine, not
    asserted on a shared one."""
    address = f"tcp://{silent_listener}"
    done = subprocess.run([sys.executable, "-m", "dobhil", "sweep", FIG2B, "--vary", VARY[0],
                           "--scheduler", address], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert (done.returncode, done.stdout) == (2, "")
    assert done.stderr.startswith(f"dobhil sweep: error: --scheduler {address}: no Dask scheduler answered "
                                  "within 4 s (") and done.stderr.count("\n") == 1, done.stderr


def test_workers_past_the_cores_are_capped_in_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    from dobhil.cluster import usable_cores
    code, out, err = run(["sweep", FIG2B, "--vary", VARY[0], "--scheduler", "local", "--workers", "1000"], capsys)
    assert code == 0 and "Traceback" not in err
    capped = [line for line in err.splitlines() if "capped" in line]
    assert capped == [f"sweep: --workers 1000: capped at {usable_cores()}, the cores this machine gives this "
                      "process (more local processes than cores run no faster); a --scheduler's workers are "
                      "not capped"]
