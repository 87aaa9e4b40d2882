"""``dobhil tune`` as a command: bad input is one line and exit 2 before any work; the
tuned config is a config ``dobhil analyze`` accepts with the chosen values; the same seed
gives the same design; a constraint no design can meet is one line and exit 1."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from dobhil.cli.main import main
from dobhil.config import load_config

#: a small, fast problem: one range key on a coarse grid, few generations
SMALL = ["paper/fig3", "--range", "environment.stiffness=1e3:1e5", "--grid", "6", "--generations", "4"]


@pytest.mark.parametrize(("args", "says"), [
    (["--range", "environment.stiffness=1e5:1e3"], "empty range"),
    (["--range", "environment.stiffness=5:5"], "empty range"),
    (["--range", "design.force_gain=1:2"], "not a plant or environment key"),
    (["--range", "nothing.here=1:2"], "unknown config key"),
    (["--range", "environment.stiffness=1e3"], "expected KEY=LO:HI"),
    (["--range", "environment.stiffness=nan:1"], "finite"),
    (["--range", "environment.stiffness=1:2", "--uncertainty", "plant.inertia=±150%"], "0 < P < 100"),
    (["--range", "environment.stiffness=1:2", "--uncertainty", "environment.stiffness=±10%"], "more than once"),
    (["--range", "environment.stiffness=1:2", "--uncertainty", "plant.viscous_friction=±50%"], "is 0, so"),
    (["--range", "environment.stiffness=1:2", "--margin", "gain=6"], "expected gm=DB"),
    # the box's ends are values of the key: past its floor the matrices overflow (an internal
    # error, SVD did not converge), past its ceiling the value is physically meaningless
    (["--range", "environment.stiffness=1:2", "--uncertainty", "plant.inertia=±99.99999999999999%"],
     "--uncertainty plant.inertia = 2.7755575615628914e-17: out of range; allowed: >= 1e-12 and <= 1e+06 kg m^2"),
    (["--range", "environment.damping=1:2", "--set", "environment.stiffness=1e10", "--uncertainty",
      "environment.stiffness=±50%"], "--uncertainty environment.stiffness = 15000000000.0: out of range"),
    # K_env = 0: the position drifts at every C_f, no design to search for
    (["--range", "environment.stiffness=0:1e3"], "drifts at every C_f, so no design is stable there"),
    (["--range", "environment.damping=1:2", "--set", "environment.stiffness=0"], "environment.stiffness is 0"),
    (["--range", "environment.stiffness=1:2", "--margin", "pm=200"], "0 <= pm < 180"),
    (["--range", "environment.stiffness=1:2", "--margin", "gm=6,gm=7"], "--margin gm: given more than once"),
    (["--range", "environment.stiffness=1:2", "--margin", "os=10", "--margin", "pm=40,os=30"], "os=10, os=30"),
    (["--range", "environment.stiffness=1:2", "--bound", "design.force_gain=1:2", "--bound",
      "design.force_gain=3:4"], "--bound design.force_gain: given more than once"),
    (["--range", "environment.stiffness=1:2", "--bound", "design.nominal_inertia=1:2"], "--bound"),
    (["--range", "environment.stiffness=1:2", "--bound", "design.force_gain=0:2"], "LO must be > 0"),
    (["--range", "environment.stiffness=1:2", "--margin", "noise=0.1"], "nothing quantises"),
    (["--range", "environment.stiffness=1:2", "--grid", "1"], "--grid 1"),
    (["--range", "environment.stiffness=1:2", "--seed", "4294967296"], "from 0 to 4294967295"),
    (["--range", "environment.stiffness=1:2", "--seed", "-1"], "from 0 to 4294967295"),
    (["--range", "environment.stiffness=1e3:1e300"], "environment.stiffness"),
    (["--range", "environment.stiffness=1:2", "--range", "environment.damping=1:2", "--grid", "400",
      "--range", "plant.inertia=0.1:1"], "at most"),
])
def test_bad_input_is_one_line_and_exit_2(args: list[str], says: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["tune", "paper/fig3", *args]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("dobhil tune: error: ") and says in err


def test_an_unwritable_out_is_refused_before_the_search(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["tune", *SMALL, "--out", str(tmp_path / "x.txt")]) == 2
    assert "expected a .yaml or .yml file name" in capsys.readouterr().err


def test_json_out_and_the_tuned_config(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "tuned.yaml"
    assert main(["tune", *SMALL, "--json", "--out", str(out), "--set", "environment.damping=80"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["feasible"] and report["grid_points"] == 6
    tuned = load_config(str(out))
    for key, value in report["design"].items():
        assert tuned.flat()[key] == pytest.approx(value, rel=1e-5)
    assert tuned.environment.damping == 80.0            # the --set is part of what was tuned
    assert "# tuned" in out.read_text()
    assert main(["analyze", str(out)]) == 0


def test_the_tuned_config_reads_the_files_the_tuned_one_did(tmp_path: Path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    """A config of a dobhil init workspace names its reference file relative to its directory
    and its profile by a name found in the workspace's drivers/: the tuned config, written
    elsewhere, must still run with those two files, not fail or fall back to the shipped
    profile."""
    from dobhil.drives.load import load_drive_profile
    from dobhil.drives.profile import default_drivers_dir
    configs, drivers = tmp_path / "ws" / "configs", tmp_path / "ws" / "drivers"
    configs.mkdir(parents=True)
    drivers.mkdir()
    (drivers / "odrive-0.6.yaml").write_text((default_drivers_dir() / "odrive-0.6.yaml").read_text())
    (configs / "ref.csv").write_text("time,tau_ref\n0,0\n0.1,1\n")
    (configs / "c.yaml").write_text("reference:\n  kind: csv\n  file: ref.csv\n")
    out = tmp_path / "out" / "tuned.yaml"
    out.parent.mkdir()
    assert main(["tune", str(configs / "c.yaml"), "--range", "environment.stiffness=1e3:1e5", "--grid", "2",
                 "--generations", "1", "--json", "--out", str(out)]) == 0
    capsys.readouterr()
    tuned = load_config(str(out))
    assert Path(tuned.reference.file) == configs / "ref.csv"
    assert Path(load_drive_profile(tuned, out.parent).directory) == drivers


def test_the_same_seed_gives_the_same_design(capsys: pytest.CaptureFixture[str]) -> None:
    designs = []
    for seed in ("3", "3", "4"):
        assert main(["tune", *SMALL, "--json", "--seed", seed]) == 0
        designs.append(json.loads(capsys.readouterr().out)["design"])
    assert designs[0] == designs[1]
    assert designs[0] != designs[2]


def test_a_constraint_no_design_meets_is_one_line_and_exit_1(capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["tune", *SMALL, "--margin", "gm=80", "--bound", "design.force_gain=20:40"])
    err = capsys.readouterr().err
    assert code == 1
    # the search's progress lines (stderr is no terminal here), then the one line saying why
    said = [line for line in err.splitlines() if not line.startswith("tune: ")]
    assert err.startswith("tune: 1 generation, ") and len(said) == 1
    assert "gain margin >= 80 dB" in said[0] and "the best found has" in said[0]


def test_a_margin_at_an_unstable_point_has_no_value(capsys: pytest.CaptureFixture[str]) -> None:
    """C_f bounded to 500..1000 with fast observers on a stiff environment: no design in the
    bounds is stable there, and the margins there are none, not the search's stand-ins
    (-100 dB, -180 deg, 100 dB) printed as if measured."""
    code = main(["tune", "paper/fig3", "--range", "environment.stiffness=1e4:1e5", "--grid", "3",
                 "--generations", "1", "--json", "--bound", "design.force_gain=500:1000",
                 "--bound", "design.dob_bandwidth=1000:1500", "--bound", "design.rtob_bandwidth=1000:1500"])
    constraints = json.loads(capsys.readouterr().out)["constraints"]
    assert code == 1 and not constraints["stability"]["ok"]
    for name in ("gain_margin", "phase_margin", "peak_sensitivity"):
        assert constraints[name]["value"] is None and not constraints[name]["ok"], constraints[name]


def test_plots_are_written(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    args = ["paper/fig3", "--range", "environment.stiffness=1e3:1e5", "--range", "environment.damping=10:200",
            "--grid", "5", "--generations", "2", "--plot", str(tmp_path)]
    assert main(["tune", *args]) in (0, 1)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["margins.png", "stability_map.png", "worst_step.png"]


def test_a_quantising_profile_gets_a_noise_constraint(capsys: pytest.CaptureFixture[str]) -> None:
    """mit-demo's MIT codec quantises: the noise of tau_int^ is a constraint when asked for."""
    args = ["mit-demo", "--range", "environment.stiffness=1e2:1e4", "--grid", "4", "--generations", "3", "--json"]
    assert main(["tune", *args, "--margin", "noise=0.05"]) == 0
    noise = json.loads(capsys.readouterr().out)["constraints"]["noise"]
    assert noise["ok"] and 0 < noise["value"] <= 0.05


def test_a_quantising_profile_says_its_noise_even_unbounded(capsys: pytest.CaptureFixture[str]) -> None:
    """Without --margin noise the figure is still reported (no limit: JSON null, and the text
    says how to bound it), and it does not constrain the search."""
    args = ["mit-demo", "--range", "environment.stiffness=1e2:1e4", "--grid", "4", "--generations", "3"]
    assert main(["tune", *args, "--json"]) == 0
    noise = json.loads(capsys.readouterr().out)["constraints"]["noise"]
    assert noise["ok"] and noise["limit"] is None and noise["value"] > 0 and not noise["active"]
    assert main(["tune", *args]) == 0
    assert "(not bounded: --margin noise=X)" in capsys.readouterr().out


def test_a_design_whose_step_never_rises_is_not_feasible(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Bounds that allow only creeping observers and a tiny C_f: every margin holds, but the
    force step does not reach 90 % within the simulated horizon at any point (rise time
    inf). That is no tuned design: exit 1, no --out, one line saying why."""
    out = tmp_path / "tuned.yaml"
    code = main(["tune", "paper/fig3", "--range", "environment.stiffness=1e3:1e4", "--grid", "2",
                 "--generations", "1", "--json", "--out", str(out), "--bound", "design.force_gain=0.001:0.002",
                 "--bound", "design.dob_bandwidth=1:2", "--bound", "design.rtob_bandwidth=1:2"])
    captured = capsys.readouterr()
    report = json.loads(captured.out)
    assert all(c["ok"] for c in report["constraints"].values()) and report["worst_objective"] is None
    assert code == 1 and not report["feasible"] and not out.exists()
    said = [line for line in captured.err.splitlines() if line.startswith("dobhil tune: ")]
    assert len(said) == 1 and "90 %" in said[0] and "analysis.step_duration" in said[0], said



def test_a_point_too_soft_to_judge_is_named_not_widen_the_bounds() -> None:
    """A stiffness range from 1e-9 N m/rad (D_env 50): there the position's pole is at
    |z| = 1 - 2e-14, inside the analysis' resolution of the unit circle, for every design
    (``dobhil tune paper/fig3 --range environment.stiffness=1e-9:1e3``). Widening --bound or
    relaxing --margin, what the line advised, cannot help; it says what is wrong there."""
    import math
    from dobhil.tune.optimise import TuneResult, Worst
    from dobhil.tune.report import infeasible_line
    at = {"environment.stiffness": 1e-9}
    stability = Worst("stability", 1.0 - 2e-14, 1.0, at, False, False)
    result = TuneResult(design={}, objective="rise_time", worst_objective=math.inf, worst_at=at,
                        constraints=(stability,), feasible=False, grid_points=2, rounds=3, set_points=2,
                        generations=3, metrics=None, grid=None)  # type: ignore[arg-type]
    line = infeasible_line(result, 0.1)
    assert "environment.stiffness=1e-09" in line and "resolution" in line and "--bound" not in line, line
    assert "0.99999999999998" in line
