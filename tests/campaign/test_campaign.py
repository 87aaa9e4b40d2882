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
from hypothesis import given, settings
from hypothesis import strategies as st

from dobhil.campaign.campaign import Campaign, NOISE_DEFAULTS, execute, reproduce_command, summarise, worst_runs
from dobhil.campaign.draws import parse_vary
from dobhil.campaign.runner import MEASURED, METRICS, RunSpec, metrics, run_one

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
    assert m["settled"] is True and m["final_error"] == pytest.approx(0.0, abs=1e-12)
    assert m["final_tau_int_true"] == pytest.approx(1.0) and m["final_tau_ref"] == 1.0
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
        assert again == {m: rows[i][m] for m in (*METRICS, *MEASURED)}
        capsys.readouterr()
        assert main([*words[1:], "--summary-json"]) == 0
        info = json.loads(capsys.readouterr().out)
        assert (info["cycles"], info["stop_reason"]) == (rows[i]["cycles"], rows[i]["stop_reason"])
        assert info["final"]["tau_int_true"] == rows[i]["final_tau_int_true"]


def test_a_response_that_never_settles_has_no_settling_time() -> None:
    """Noise of 5 % on the response: the 2 % band is never held through the final window, so
    the settling time is empty -- not the run's end, as it was."""
    t = np.arange(0, 1.0, 1e-3)
    ref = np.ones_like(t)
    noise = 0.05 * np.sin(2 * np.pi * 37 * t)   # deterministic, never inside +-2 % for long
    true = 1.0 - np.exp(-t / 0.01) + noise
    m = metrics(t, ref, true, start=0.0, step=True, amplitude=1.0)
    assert m["settled"] is False and m["settling_time"] is None
    assert m["rise_time"] is not None and m["force_rms_error"] is not None
    # the same response, quiet: it settles
    quiet = metrics(t, ref, 1.0 - np.exp(-t / 0.01), start=0.0, step=True, amplitude=1.0)
    assert quiet["settled"] is True and quiet["settling_time"] == pytest.approx(0.01 * math.log(50), abs=1.1e-3)
    # a step to nothing: no band to settle in, no overshoot
    flat = metrics(t, ref, np.zeros_like(t), start=0.0, step=True, amplitude=1.0)
    assert flat["settled"] is None and flat["settling_time"] is None and flat["overshoot_pct"] is None
    assert flat["rise_time"] is None and flat["final_error"] == pytest.approx(1.0)


@settings(max_examples=60, deadline=None)
@given(tau=st.floats(0.002, 0.2), noise=st.floats(0.0, 0.06), freq=st.floats(5.0, 200.0),
       level=st.floats(-2.0, 2.0).filter(lambda x: abs(x) > 0.05))
def test_settled_means_inside_the_band_from_the_settling_time_to_the_end(tau: float, noise: float, freq: float,
                                                                          level: float) -> None:
    """Checked against a direct reading of the definition, sample by sample."""
    t = np.arange(0, 1.0, 1e-3)
    y = level * (1.0 - np.exp(-t / tau)) + noise * abs(level) * np.sin(2 * np.pi * freq * t)
    m = metrics(t, np.full_like(t, level), y, start=0.0, step=True, amplitude=level)
    tail = max(1, int(round(0.1 * t.size)))
    final = float(np.mean(y[-tail:]))
    inside = np.abs(y - final) <= 0.02 * abs(final)
    # the first sample from which every later one is inside
    from_here = [i for i in range(t.size) if inside[i:].all()]
    held = bool(from_here) and from_here[0] <= t.size - tail
    assert m["settled"] is held
    if held:
        assert m["settling_time"] == pytest.approx(t[from_here[0]])
        assert inside[t >= m["settling_time"] - 1e-12].all()
    else:
        assert m["settling_time"] is None


def row(i: int, *, stop: str = "done", error: str = "", **metrics_: float | bool | None) -> dict[str, Any]:
    base: dict[str, Any] = {"run": i, "stop_reason": stop, "error": error, "retried": False, "settled": None,
                            "final_tau_ref": 1.0, **{m: None for m in METRICS}}
    base.update(metrics_)
    return base


def test_percentiles_count_only_the_runs_that_have_the_metric() -> None:
    rows = [row(i, settling_time=0.1 * (i + 1), settled=True, force_rms_error=0.01) for i in range(3)]
    rows += [row(3 + i, settled=False, force_rms_error=0.02) for i in range(2)]
    s = summarise(rows)
    assert s.percentiles["settling_time"]["n"] == 3 and s.percentiles["settling_time"]["p50"] == pytest.approx(0.2)
    assert s.percentiles["force_rms_error"]["n"] == 5 and s.never_settled == 2
    assert "rise_time" not in s.percentiles          # no run has one


def test_an_unknown_stop_reason_is_a_failed_run_like_any_other() -> None:
    """No list of reasons in the campaign: a reason the runtime adds flows through as text."""
    from dobhil.cli.montecarlo_cmd import describe_row
    rows = [row(0, force_rms_error=0.01), row(1, stop="some_new_reason", force_rms_error=0.001)]
    s = summarise(rows)
    assert s.succeeded == 1 and s.worst[0] == 1
    c = demo_campaign(2)
    assert "stop some_new_reason" in describe_row(rows[1], c)


def test_the_median_is_compared_with_the_reference_run() -> None:
    from dobhil.campaign.compare import Floors
    floors = Floors.of(1e-3, 1.0)                    # torque floor 0.01 N m, time floor 2 ms
    reference = row(-1, force_rms_error=0.050, rise_time=0.010, final_error=0.001, final_tau_int_true=1.0,
                    overshoot_pct=10.0, settled=True, settling_time=0.2)
    rms = [0.050, 0.051, 0.062, 0.063, 0.064]        # p50 0.062: 0.012 past, tolerance max(0.005, 0.01)
    rows = [row(i, force_rms_error=e, rise_time=0.0105, final_error=-0.02 + 0.01 * i, overshoot_pct=10.5,
                final_tau_int_true=1.0 + 0.03 * (i - 2), settled=i < 3, settling_time=0.2 if i < 3 else None)
            for i, e in enumerate(rms)]
    s = summarise(rows, reference, floors)
    by = {c.metric: c for c in s.comparisons}
    assert by["force_rms_error"].worse and by["force_rms_error"].past == pytest.approx(0.012)
    assert by["force_rms_error"].tolerance == pytest.approx(0.01)
    assert not by["rise_time"].worse and by["rise_time"].tolerance == pytest.approx(0.002)
    assert not by["overshoot_pct"].worse and by["overshoot_pct"].tolerance == pytest.approx(1.0)
    # the signed final error: |p50| = 0 against |0.001|: better
    assert not by["final_error"].worse and by["final_error"].past == pytest.approx(-0.001)
    assert s.never_settled == 2 and s.as_dict()["worse_than_reference"] == ["force_rms_error"]
    # the final torque's spread against the command: 0.94..1.06 is off by more than 0.1? no
    assert s.command is not None and not s.command.runs_off and not s.command.reference_off
    wide = [{**r, "final_tau_int_true": 1.0 + 0.06 * (r["run"] - 2)} for r in rows]   # 0.88..1.12
    assert summarise(wide, reference, floors).command.runs_off  # type: ignore[union-attr]
    json.dumps(s.as_dict())   # the summary is JSON as it is


def test_the_reference_run_is_the_config_as_given(dask_client: Any) -> None:
    c = demo_campaign(2, "plant.inertia=normal:0.25:0.03", duration=0.8)   # past the demo's step at 0.6 s
    spec = c.reference_spec()
    assert spec.draws == () and spec.overrides == c.overrides
    assert spec.sensor_seed not in {s.sensor_seed for s in c.plan()}
    ref = execute(dask_client, [spec])[0]
    assert ref["error"] == "" and ref["stop_reason"] == "done" and ref["run"] == -1
    assert "plant.inertia" not in ref and ref["force_rms_error"] is not None and ref["settled"] is not None
