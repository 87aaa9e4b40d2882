"""``dobhil montecarlo`` end to end: bad input is one line and exit 2 before anything starts;
a campaign writes its table (CSV or Parquet, read back equal), summary and plots, and exits 1
when a run failed; killing a worker mid-campaign loses no row and marks the retried ones."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from dobhil.cli.main import main

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize(("extra", "says"), [
    (["--vary", "plant.nope=normal:1:2"], "unknown config key 'plant.nope'"),
    (["--vary", "plant.inertia=cauchy:1:2"], "unknown distribution 'cauchy'; allowed: normal:MEAN:STD"),
    (["--vary", "plant.inertia=uniform:3:1"], "an empty range"),
    (["--vary", "plant.inertia=uniform:0.1:1", "--vary", "plant.inertia=normal:1:0.1"], "given twice"),
    (["--vary", "plant.inertia=uniform:0.1:1", "--runs", "0"], "--runs 0"),
    (["--vary", "plant.inertia=uniform:0.1:1", "--duration", "-1"], "--duration -1.0"),
    (["--vary", "plant.inertia=uniform:0.1:1", "--set", "plant.inertia=-1"], "plant.inertia = -1"),
    (["--vary", "plant.inertia=uniform:0.1:1", "--plot"], "--plot writes its figures into --out"),
    (["--vary", "plant.inertia=uniform:0.1:1", "--format", "parquet"],
     "--format parquet writes the table into --out DIR; give --out"),
    (["--vary", "plant.inertia=uniform:0.1:1", "--workers", "0"], "--workers 0"),
    (["--vary", "plant.inertia=uniform:0.1:1", "--seed", "-1"], "--seed -1: expected a whole number from 0 to"),
    (["--vary", "plant.inertia=uniform:0.1:1", "--seed", str(2**63), "--format", "parquet"],
     f"--seed {2**63}: expected a whole number from 0 to {2**63 - 1}"),
    # what every run, the reference first, would fail on: bad input before any run (1e15 s: loop.duration's ceiling)
    (["--vary", "plant.inertia=uniform:0.1:1", "--duration", "1e15"], "too many cycles"),
    (["--vary", "plant.inertia=uniform:0.1:1", "--set", "reference.kind=csv", "--set",
      "reference.file=/nonexistent.csv"], "reference file /nonexistent.csv does not exist"),
    (["--vary", "plant.inertia=uniform:0.1:1", "--set", "reference.kind=chirp", "--duration", "0.2"],
     "the chirp starts at 0.6 s, not before the end of the run"),
    # a CiA 402 SYNC every 1 ms, a lockstep bus stepped every 2 ms: every run would stop at its cycle 0
    (["--vary", "plant.inertia=uniform:0.1:1", "--set", "drive.profile=epos4", "--set", "loop.period=0.002"],
     "sends SYNC every 0.001 s (feedback_period); allowed in lockstep: loop.period = 0.001 s (feedback_period)"),
    # an ODrive's encoder estimates every 1 ms, a lockstep loop of 2 ms: each run would skip every other cycle
    (["--vary", "plant.inertia=uniform:0.1:1", "--set", "loop.period=0.002"],
     "lockstep timing runs one cycle per feedback frame, but drive profile 'odrive-0.6' has encoder estimates"),
    (["--vary", "loop.period=loguniform:0.001:0.01"],
     "--vary loop.period=loguniform:0.001:0.01: each run is lockstep, one cycle per feedback frame, and drive profile "
     "'odrive-0.6' sends its feedback every 0.001 s (feedback_period), which a drawn loop.period almost never "
     "equals; keep loop.period fixed (the config's 0.001 s runs)"),
    # a drawn period almost never divides that SYNC period: every run, not the reference, would be refused
    (["--vary", "loop.period=uniform:0.001:0.002", "--set", "drive.profile=epos4"],
     "--vary loop.period=uniform:0.001:0.002: each run is lockstep, whose bus sends a periodic frame only every "
     "whole number of loop periods, and drive profile 'epos4' sends SYNC every 0.001 s (feedback_period), which a "
     "drawn loop.period almost never divides; keep loop.period fixed (the config's 0.001 s runs)"),
    # --duration sets every run's length: a drawn loop.duration would be a column of lengths no run had
    (["--vary", "loop.duration=uniform:0.6:0.7", "--duration", "0.05"],
     "--vary loop.duration=uniform:0.6:0.7 with --duration 0.05: --duration sets every run's length, so the drawn "
     "loop.duration would change nothing; drop one of them"),
    # a key the controller reads only with another structure: every run would be the same loop
    (["--vary", "design.velocity_filter_bandwidth=uniform:100:1000"],
     "does not read design.velocity_filter_bandwidth (design.velocity_source is measured, not estimated)"),
])
def test_bad_input_is_one_line_and_exit_2(extra: list[str], says: str, capsys: pytest.CaptureFixture[str]) -> None:
    args = ["montecarlo", "demo", "--runs", "3", *extra]
    if "--runs" in extra:
        args = ["montecarlo", "demo", *extra]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and says in err and err.startswith("dobhil montecarlo: error: ")


@pytest.mark.parametrize(("vary", "duration", "length"), [
    ("plant.inertia=uniform:0.2:0.3", 0.05, "(0.05 s each, lockstep"),
    ("plant.inertia=uniform:0.2:0.3", None, "(1.2 s each, from loop.duration, lockstep"),
    # each run its own length: the config's 1.2 s would be no run's
    ("loop.duration=uniform:0.1:0.2", None, "(each its drawn loop.duration, uniform:0.1:0.2, lockstep"),
])
def test_the_header_gives_the_runs_length(vary: str, duration: float | None, length: str) -> None:
    from dobhil.campaign.campaign import Campaign
    from dobhil.campaign.draws import parse_vary
    from dobhil.cli.montecarlo_cmd import header
    campaign = Campaign(config="demo", set_files=(), overrides=(), varies=(parse_vary(vary),), runs=2, seed=0,
                        duration=duration)
    assert length in header(campaign, (), None, 1)


def test_existing_results_are_not_overwritten(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "runs.csv").write_text("mine\n")
    assert main(["montecarlo", "demo", "--runs", "2", "--vary", "plant.inertia=uniform:0.2:0.3",
                 "--out", str(tmp_path)]) == 2
    assert "runs.csv exists; refusing to overwrite" in capsys.readouterr().err
    assert (tmp_path / "runs.csv").read_text() == "mine\n"


def test_bad_input_as_a_process_is_one_line_exit_2() -> None:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    done = subprocess.run([sys.executable, "-m", "dobhil", "montecarlo", "demo", "--runs", "5",
                           "--vary", "environment.stiffness=lognormal:1:2"],
                          capture_output=True, text=True, env=env, timeout=60)
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr.count("\n") == 1 and "unknown distribution 'lognormal'" in done.stderr


def test_a_scheduler_that_does_not_answer_is_its_one_line_alone(capsys: pytest.CaptureFixture[str],
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """The campaign's header waits for the cluster: a closed port ends in the error line only.
    The command's connect time-out (4 s) is waited out here in 0.5 s: what is checked is the
    one line, not the time-out (tests/cluster/test_cluster.py checks a closed port at 0.5 s)."""
    import functools
    import socket

    import dobhil.cluster as cluster
    monkeypatch.setattr(cluster, "open_client", functools.partial(cluster.open_client, timeout=0.5))
    with socket.socket() as s:   # a port nothing listens on: bound, never listening
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        code = main(["montecarlo", "demo", "--runs", "2", "--vary", "plant.inertia=uniform:0.2:0.3",
                     "--scheduler", f"tcp://127.0.0.1:{port}"])
    out, err = capsys.readouterr()
    assert code == 2 and out == ""
    assert err.count("\n") == 1 and "no Dask scheduler answered within 0.5 s" in err   # the patched time-out


def run_cli(tmp_path: Path, fmt: str, *extra: str) -> tuple[int, Path]:
    out = tmp_path / fmt
    # seed 3: two of the six inertias are drawn <= 0 (refused runs)
    code = main(["montecarlo", "demo", "--runs", "6", "--seed", "3", "--duration", "0.3", "--workers", "1",
                 "--vary", "plant.inertia=normal:0.06:0.05", "--out", str(out), "--format", fmt, *extra])
    return code, out


def test_a_campaign_writes_its_table_summary_and_plots(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("pyarrow")
    from dobhil.campaign.table import read_table
    code, out = run_cli(tmp_path, "parquet", "--plot")
    text = capsys.readouterr().out
    rows = read_table(out / "runs.parquet")
    refused = [r for r in rows if r["plant.inertia"] <= 0]
    assert 0 < len(refused) < 6 and code == 1     # some runs failed: exit 1, the table written
    assert "noise on: sensor.encoder_resolution=16384, sensor.velocity_noise=0.01" in text
    assert "95 % CI" in text and "dobhil run demo --emulate --lockstep --duration 0.3" in text
    summary = json.loads((out / "summary.json").read_text())
    assert summary["runs"] == 6 and summary["succeeded"] == 6 - len(refused)
    assert summary["worst"][0]["run"] == refused[0]["run"]
    assert (out / "metrics.png").stat().st_size > 10_000 and (out / "vary.png").stat().st_size > 10_000
    # the CSV of the same campaign holds the same values
    code_csv, out_csv = run_cli(tmp_path, "csv")
    with (out_csv / "runs.csv").open() as fh:
        from_csv = list(csv.DictReader(fh))
    assert code_csv == 1 and list(from_csv[0]) == list(rows[0])
    for a, b in zip(rows, from_csv):
        assert {k: ("" if v is None else str(v)) for k, v in a.items()} == b


def test_parquet_round_trip_keeps_types_and_nulls(tmp_path: Path) -> None:
    pytest.importorskip("pyarrow")
    from dobhil.campaign.table import read_table, write_table
    columns = ["run", "seed", "plant.inertia", "sensor.encoder_resolution", "sensor_seed", "stop_reason",
               "error", "cycles", "force_rms_error", "overshoot_pct", "rise_time", "settling_time",
               "final_tau_int_true", "overruns", "retried"]
    rows: list[dict[str, Any]] = [
        dict(zip(columns, [0, 1, 0.25, 4096, 77, "done", "", 300, 0.1, 2.5, 0.003, 0.02, 1.0, 0, False])),
        dict(zip(columns, [1, 1, -0.1, 8192, 78, "", "ConfigError: x", 0, None, None, None, None, None, 0,
                           True]))]
    path = write_table(rows, columns, tmp_path / "runs.parquet", "parquet", ["sensor.encoder_resolution"])
    assert read_table(path) == rows


@dataclass(frozen=True)
class Running:
    """A campaign task the worker running it says it is executing, whose start (the event
    the task logs before it calls run_one) has reached the scheduler."""

    key: str
    index: int
    worker: str
    pid: int
    started: float   # the start event's time at the scheduler


def _running(client: Any) -> list[Running]:
    """Every campaign task that has signalled its start and is executing now, newest first."""
    def executing(dask_worker: Any) -> list[str]:
        return [str(k) for k, ts in dask_worker.state.tasks.items() if ts.state == "executing"]
    pids = client.run(os.getpid)
    starts: dict[str, float] = {}
    for topic, events in client.get_events().items():
        if str(topic).startswith("dobhil-montecarlo-") and "-attempts-" in str(topic):
            prefix, token = str(topic).split("-attempts-")
            starts.update({f"{prefix}-{token}-{i}": t for t, i in events})
    found = [Running(key, int(key.rsplit("-", 1)[1]), worker, pids[worker], starts[key])
             for worker, keys in client.run(executing).items() for key in keys if key in starts]
    return sorted(found, key=lambda r: -r.started)


def _task_state(client: Any, key: str) -> tuple[str, str | None]:
    """The scheduler's state of a task and the worker it is processing on."""
    def state(dask_scheduler: Any) -> tuple[str, str | None]:
        ts = dask_scheduler.tasks.get(key)
        if ts is None:
            return "forgotten", None
        return ts.state, ts.processing_on.address if ts.processing_on is not None else None
    found, worker = client.run_on_scheduler(state)
    return str(found), worker


def _campaign_busy(client: Any) -> bool:
    """A campaign task is still waiting or processing at the scheduler."""
    def busy(dask_scheduler: Any) -> bool:
        return any(str(k).startswith("dobhil-montecarlo-") and ts.state in ("processing", "queued",
                                                                              "no-worker", "waiting")
                   for k, ts in dask_scheduler.tasks.items())
    return bool(client.run_on_scheduler(busy))


def _kill_a_running_task(client: Any) -> Running:
    """SIGKILL the worker of a task that is running run_one: the newest started one is frozen
    (SIGSTOP: from then on it can send nothing), and killed only if the scheduler still has
    its task processing there -- no result of it came back -- else it is let go and another
    is looked for. Polls until one is found; fails if the campaign ran out of tasks first."""
    while _campaign_busy(client):
        for task in _running(client):
            os.kill(task.pid, signal.SIGSTOP)
            if _task_state(client, task.key) == ("processing", task.worker):
                os.kill(task.pid, signal.SIGKILL)
                return task
            os.kill(task.pid, signal.SIGCONT)
        time.sleep(0.005)
    raise AssertionError("no campaign task was running to be killed: the campaign ended first")


def test_killing_a_worker_mid_campaign_loses_no_row(dask_client: Any) -> None:
    """A worker process SIGKILLed while it runs a campaign task: every row comes back, equal to
    an undisturbed campaign's, and the run it was running is the one marked ``retried``.

    That the kill hit a running task is shown, not assumed: the worker said it was executing
    the task, the task's own start event had reached the scheduler (so run_one was called),
    and with the worker frozen the scheduler still had no result of it. That the kill stopped
    it: Dask started the task a second time (its ``retried`` mark, from the start events), as
    it only does for a task whose worker died before its result was fetched. Other runs that
    worker had finished but this process had not yet fetched (it waits in the kill) may be
    run again and marked too; a run that had come back before the kill never is."""
    from dobhil.campaign.campaign import Campaign, execute
    from dobhil.campaign.draws import parse_vary
    from dobhil.cluster import open_client
    c = Campaign(config="demo", set_files=(), overrides=(), varies=(parse_vary("plant.inertia=uniform:0.2:0.3"),),
                 runs=8, seed=5, duration=0.6)
    undisturbed = execute(dask_client, c.plan())
    killed: list[Running] = []
    back: list[int] = []   # runs whose rows had come back before the kill
    with open_client(workers=2, processes=True) as client:
        def kill_after_three(row: dict[str, Any]) -> None:
            if not killed:
                back.append(row["run"])
            if len(back) == 3 and not killed:   # 5 runs to go: one of them has started
                killed.append(_kill_a_running_task(client))
        rows = execute(client, c.plan(), progress=kill_after_three)
        pids = set(client.run(os.getpid).values())
    assert len(killed) == 1 and killed[0].pid not in pids and killed[0].index not in back
    assert [r["run"] for r in rows] == list(range(8))
    assert all(r["error"] == "" for r in rows)
    assert [{k: v for k, v in r.items() if k != "retried"} for r in rows] == \
        [{k: v for k, v in r.items() if k != "retried"} for r in undisturbed]
    retried = {r["run"] for r in rows if r["retried"]}
    assert killed[0].index in retried and not retried & set(back), (killed[0], retried, back)


def test_the_table_says_which_runs_were_retried(dask_client: Any) -> None:
    """``retried`` is map_ordered's, run by run (a task's second start: its worker died)."""
    from dobhil.campaign.campaign import Campaign, _row
    from dobhil.campaign.draws import parse_vary
    from dobhil.campaign.runner import run_one
    from dobhil.cluster import MapResult
    c = Campaign(config="demo", set_files=(), overrides=(), varies=(parse_vary("plant.inertia=uniform:0.2:0.3"),),
                 runs=2, seed=5, duration=0.1)
    spec = c.spec(1)
    row = run_one(spec)
    assert _row(spec, MapResult(row, None, True))["retried"] is True
    assert _row(spec, MapResult(row, None, False))["retried"] is False
    lost = _row(spec, MapResult(None, "KilledWorker: gone three times", True))
    assert lost["retried"] is True and lost["error"] == "KilledWorker: gone three times" and lost["run"] == 1


def test_the_summary_counts_says_the_reference_and_flags(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Past the demo's step (0.6 s): each metric over the runs that have it, the reference run
    and each median against it, in the printed summary and in summary.json alike."""
    out = tmp_path / "mc"
    code = main(["montecarlo", "demo", "--runs", "4", "--seed", "1", "--duration", "0.8", "--workers", "1",
                 "--vary", "design.force_gain=uniform:1:3", "--out", str(out)])
    text = capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text())
    with (out / "runs.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert code == 0 and summary["reference"]["run"] == -1 and summary["reference"]["error"] == ""
    assert "reference run (the config as given, nothing drawn): stop done" in text
    assert summary["reference_command"].startswith("dobhil run demo --emulate --lockstep --duration 0.8")
    settled = sum(r["settled"] == "True" for r in rows)
    never = sum(r["settled"] == "False" for r in rows)
    # seed 1 draws C_f 1-3: one run settles, three do not (the lines of both cases are shown)
    assert (settled, never) == (1, 3) and summary["never_settled"] == never
    assert all((r["settling_time"] == "") == (r["settled"] == "False") for r in rows)
    p = summary["percentiles"]
    assert p["force_rms_error"]["n"] == 4 and "force_rms_error: p5 " in text and "over 4 of 4 runs" in text
    assert f"over {settled} of 4 runs; {never} never settled" in text
    flagged = [c["metric"] for c in summary["comparisons"] if c["worse"]]
    assert flagged == summary["worse_than_reference"]
    assert flagged and len(flagged) < len(summary["comparisons"])   # both kinds of line checked
    for c in summary["comparisons"]:
        line = next(line for line in text.splitlines() if line.startswith(f"  {c['metric']}: p5 "))
        assert f"reference {c['reference']:.4g}" in line and line.endswith(": WORSE than the reference") == c["worse"]


def test_the_noise_defaults_a_set_overrides_are_not_said_to_be_on() -> None:
    """The campaign's noise defaults come before --set, which overrides them: a default whose
    key the user sets is never used, and the header said "noise on: sensor.encoder_resolution=16384,
    sensor.velocity_noise=0.01" for a campaign run with --set sensor.encoder_resolution=1048576
    --set sensor.velocity_noise=0.001 (each worst run's command then carried both values)."""
    from dobhil.cli.main import build_parser
    from dobhil.cli.montecarlo_cmd import build_campaign

    def noise(*sets: str) -> tuple[str, ...]:
        argv = ["montecarlo", "demo", "--runs", "2", "--vary", "plant.inertia=normal:0.25:0.01"]
        args = build_parser().parse_args([*argv, *(a for item in sets for a in ("--set", item))])
        campaign, said = build_campaign(args, [])
        assert campaign.overrides == (*said, *sets)
        return said
    assert noise() == ("sensor.encoder_resolution=16384", "sensor.velocity_noise=0.01")
    assert noise("sensor.velocity_noise=0.001") == ("sensor.encoder_resolution=16384",)
    both = ("sensor.encoder_resolution=1048576", "sensor.velocity_noise=0.001")
    assert noise(*both) == ()
