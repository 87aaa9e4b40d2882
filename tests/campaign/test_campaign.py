"""Campaigns on Dask: the same table whatever the number of workers, failing and raising runs
as rows, the worst runs' commands reproducing them alone, metrics checked independently."""

from __future__ import annotations

import json
import math
import shlex
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from dobhil.campaign.campaign import Campaign, NOISE_DEFAULTS, execute, reproduce_command, summarise, worst_runs
from dobhil.campaign.draws import parse_vary
from dobhil.campaign.runner import METRICS, RunSpec, metrics, run_one

SHORT = 0.3   # s per run: the demo's contact, not its step (at 0.6 s); enough for every column


def demo_campaign(runs: int, *varies: str, seed: int = 3, duration: float = SHORT,
                  overrides: tuple[str, ...] = NOISE_DEFAULTS) -> Campaign:
    return Campaign(config="demo", set_files=(), overrides=overrides,
                    varies=tuple(parse_vary(v) for v in varies), runs=runs, seed=seed, duration=duration)


def without_retried(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [{k: v for k, v in r.items() if k != "retried"} for r in rows]


def test_the_same_seed_gives_the_same_table_on_one_and_two_workers(dask_client: Any) -> None:
    from dobhil.cluster import open_client
    c = demo_campaign(6, "plant.inertia=normal:0.25:0.03", "environment.damping=uniform:20:80")
    two = execute(dask_client, c.plan())
    with open_client(workers=1, processes=False) as one_worker:
        one = execute(one_worker, c.plan())
    assert without_retried(one) == without_retried(two)
    assert [r["run"] for r in two] == list(range(6))
    assert len({r["plant.inertia"] for r in two}) == 6 and len({r["sensor_seed"] for r in two}) == 6
    assert all(r["error"] == "" and r["stop_reason"] == "done" for r in two)
    other_seed = execute(dask_client, demo_campaign(6, "plant.inertia=normal:0.25:0.03",
                                                    "environment.damping=uniform:20:80", seed=4).plan())
    assert [r["plant.inertia"] for r in other_seed] != [r["plant.inertia"] for r in two]


def test_refused_and_raising_runs_are_rows_and_the_campaign_goes_on(dask_client: Any, tmp_path: Path) -> None:
    # a normal draw of a positive key below 0 is refused by the config for that run only
    c = demo_campaign(12, "plant.inertia=normal:0.02:0.05")
    rows = execute(dask_client, c.plan())
    refused = [r for r in rows if r["plant.inertia"] <= 0]
    assert refused and len(refused) < len(rows)
    for r in refused:
        assert r["error"].startswith("ConfigError: plant.inertia = ") and "must be > 0" in r["error"]
        assert r["stop_reason"] == "" and r["cycles"] == 0 and r["force_rms_error"] is None
    assert all(r["error"] == "" and r["cycles"] > 0 for r in rows if r["plant.inertia"] > 0)
    # a run that raises inside the stack (its reference file is missing)
    spec = RunSpec(0, 0, "demo", (), ("reference.kind=csv", f"reference.file={tmp_path / 'none.csv'}"),
                   (), 1, SHORT)
    row = run_one(spec)
    assert row["error"] and "none.csv" in row["error"] and row["stop_reason"] == ""
    s = summarise(rows)
    assert s.succeeded == len(rows) - len(refused) and s.worst[0] in [r["run"] for r in refused]


def test_a_run_stopped_by_the_safety_is_a_failed_row(dask_client: Any) -> None:
    # a tight position window: the push into the environment trips the position limit
    c = demo_campaign(3, "loop.position_max=uniform:0.0001:0.0002", duration=0.8)
    rows = execute(dask_client, c.plan())
    assert all(r["error"] == "" and r["stop_reason"] == "position_limit" for r in rows)
    assert summarise(rows).succeeded == 0
    assert summarise(rows).ci_high < 0.71 and summarise(rows).ci_low == 0.0   # exact interval, 0 of 3


def test_metrics_against_a_hand_made_trace() -> None:
    t = np.arange(0, 1.0, 1e-3)
    ref = np.where(t >= 0.5, 1.0, 0.2)
    # first order from 0.2 to 1 with a 10 ms time constant after the step
    true = np.where(t >= 0.5, 1.0 - 0.8 * np.exp(-(t - 0.5) / 0.01), 0.2)
    m = metrics(t, ref, true, start=0.5, step=True, amplitude=0.8)
    after = t >= 0.5
    assert m["force_rms_error"] == pytest.approx(math.sqrt(np.mean((ref[after] - true[after]) ** 2)))
    assert m["overshoot_pct"] == pytest.approx(0.0, abs=1e-9)
    assert m["rise_time"] == pytest.approx(0.01 * math.log(9), abs=2e-4)      # ln(0.9/0.1) tau
    assert m["settling_time"] == pytest.approx(0.01 * math.log(50), abs=1.1e-3)  # into 2 %
    assert m["final_tau_int_true"] == pytest.approx(1.0)
    sine = metrics(t, ref, true, start=0.5, step=False, amplitude=0.8)
    assert sine["overshoot_pct"] is None and sine["force_rms_error"] == m["force_rms_error"]


def test_the_worst_runs_commands_reproduce_them_alone(dask_client: Any, capsys: pytest.CaptureFixture[str]) -> None:
    from dobhil.cli.common import config_from_args
    from dobhil.cli.main import build_parser, main
    from dobhil.config import resolve_config
    from dobhil.runtime.session import RunSession
    c = demo_campaign(5, "design.force_gain=uniform:1:4", "environment.stiffness=loguniform:3e3:3e4",
                      duration=0.8)
    specs = c.plan()
    rows = execute(dask_client, specs)
    for i in worst_runs(rows, 2):
        words = shlex.split(reproduce_command(specs[i]))
        assert words[:2] == ["dobhil", "run"]
        args = build_parser().parse_args(words[1:])
        with RunSession(config_from_args(args), emulate=True, lockstep=True, duration=args.duration,
                        config_dir=resolve_config(args.config).parent) as session:
            result = session.run()
        ref = session.config.reference
        again = metrics(result.trace["t"], result.trace["tau_ref"], result.trace["tau_int_true"],
                        start=ref.start, step=True, amplitude=ref.amplitude)
        assert again == {m: rows[i][m] for m in METRICS}
        capsys.readouterr()
        assert main([*words[1:], "--summary-json"]) == 0
        info = json.loads(capsys.readouterr().out)
        assert (info["cycles"], info["stop_reason"]) == (rows[i]["cycles"], rows[i]["stop_reason"])
        assert info["final"]["tau_int_true"] == rows[i]["final_tau_int_true"]
