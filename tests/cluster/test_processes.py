"""dobhil.cluster with real worker processes: a worker killed mid-task (Dask runs the task
again, the row says ``retried``), and ``dobhil sweep --scheduler`` on a multi-process cluster
writing the same file as the local sweep. One cluster for the module: processes take seconds."""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from dobhil.cli.main import main
from dobhil.cluster import map_ordered, map_streaming, open_client

ROOT = Path(__file__).resolve().parents[2]
FIG2B = str(ROOT / "configs/paper/fig2b.yaml")


@pytest.fixture(scope="module")
def process_client() -> Iterator[object]:
    with open_client(workers=2, processes=True) as client:
        yield client


def _dies_once(item: tuple[int, str]) -> int:
    """Item 2's first attempt kills its own worker process (SIGKILL: no clean-up, as an OOM
    kill or a pulled node) a moment after it started, so its start has reached the
    scheduler; its second attempt (the marker file exists) finishes."""
    index, marker = item
    if index == 2 and not os.path.exists(marker):
        Path(marker).touch()
        time.sleep(1.0)
        os.kill(os.getpid(), signal.SIGKILL)
    time.sleep(0.1)
    return index * 10


def test_a_worker_killed_mid_task_loses_no_row_and_marks_the_retried_one(
        process_client: object, tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    pids_before = set(process_client.run(os.getpid).values())  # type: ignore[attr-defined]
    marker = str(tmp_path / "killed")
    results = map_ordered(process_client, _dies_once, [(i, marker) for i in range(6)])  # type: ignore[arg-type]
    assert [r.value for r in results] == [0, 10, 20, 30, 40, 50]
    assert [r.error for r in results] == [None] * 6
    assert [i for i, r in enumerate(results) if r.retried] == [2]
    assert Path(marker).exists()   # the kill did happen: the second attempt is the one that returned
    process_client.wait_for_workers(2, timeout=60)  # type: ignore[attr-defined]
    assert set(process_client.run(os.getpid).values()) != pids_before  # type: ignore[attr-defined]
    out, err = capfd.readouterr()   # the nanny and the scheduler saw it all: the terminal does not
    assert (out, err) == ("", "")


def test_the_streamed_map_marks_the_retried_one_too(process_client: object, tmp_path: Path) -> None:
    """The campaign's path: a window of 3, so the retry counts are read in several batches."""
    marker = str(tmp_path / "killed")
    items = ((i, marker) for i in range(8))
    results = list(map_streaming(process_client, _dies_once, items, index=lambda item: item[0],  # type: ignore[arg-type]
                                 window=3))
    assert [i for i, _ in results] == list(range(8)) and [r.value for _, r in results] == [10 * i for i in range(8)]
    assert [i for i, r in results if r.retried] == [2] and Path(marker).exists()
    process_client.wait_for_workers(2, timeout=60)  # type: ignore[attr-defined]


#: 65 x 65 = 4225 points: two chunks of the command's 4096
VARY = ["--vary", "design.identified_inertia=0.05:0.6:65", "--vary", "environment.stiffness=log:1e3:1e5:65"]


def test_the_sweep_on_a_process_cluster_writes_the_local_sweeps_file(process_client: object, tmp_path: Path,
                                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """Through the command: a tcp scheduler (the remote path) and --scheduler local (a cluster
    of its own), each chunk run in another process, against the sweep in this one."""
    address = process_client.scheduler.address  # type: ignore[attr-defined]
    outputs = {}
    for name, extra in [("here", []), ("remote", ["--scheduler", address]),
                        ("local", ["--scheduler", "local", "--workers", "1"])]:
        out = tmp_path / f"{name}.csv"
        assert main(["sweep", FIG2B, "--sampled", *VARY, "--out", str(out), *extra]) == 0
        outputs[name] = out.read_bytes()
    assert outputs["remote"] == outputs["here"] and outputs["local"] == outputs["here"]
    assert outputs["here"].count(b"\n") == 1 + 4225
    assert capsys.readouterr().err == ""
