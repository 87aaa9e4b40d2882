"""``dobhil certify`` as a command: the Fig. 3 box refuted for the paper's gains (with the
point) and certified for the tuned design; bad input one line, exit 2, before any work."""

from __future__ import annotations

import json

import pytest

from dobhil.cli.main import main

BOX = ["--range", "environment.stiffness=1e3:1e5", "--range", "environment.damping=10:200"]
TUNED = ["--set", "design.dob_bandwidth=40.6673", "--set", "design.rtob_bandwidth=29.2889",
         "--set", "design.identified_inertia=0.125154", "--set", "design.force_gain=0.623056"]


def test_the_paper_gains_are_refuted_at_a_point(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["certify", "paper/fig3", *BOX, "--refinements", "20"]) == 1
    out = capsys.readouterr().out
    assert "continuous loop (edge theorem): refuted at environment.stiffness=100000, environment.damping=10" in out
    assert "sampled loop (interval enclosure + Lyapunov bound): refuted at" in out
    assert "disk margin (continuous) at environment.stiffness=100000, environment.damping=10 (refuting " \
           "point): the loop is unstable there" in out


def test_the_tuned_design_is_certified_in_the_continuous_loop(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["certify", "paper/fig3", *BOX, *TUNED, "--loop", "continuous", "--json"]) == 0
    answer = json.loads(capsys.readouterr().out)
    assert answer["certified"] is True
    cont = answer["continuous"]
    assert cont["verdict"] == "certified" and cont["edges"] == 4 and cont["edges_unstable"] == 0
    # (the margin itself is checked against eigenvalues in test_certify.py)
    assert cont["gain_margin"]["db"] > 6.0 and cont["gain_margin"]["down"] is None   # unbounded below
    disk = answer["disk_margin"]["continuous"]
    assert disk["stable"] and "points searched; not a bound" in disk["where"]
    assert disk["gain_db"] <= cont["gain_margin"]["db"] + 1e-9


def _scan_alpha(config_args: list[str], ranges: dict[str, tuple[float, float]], sampled: bool,
                per_key: int) -> float:
    """The smallest disk margin (alpha) on a dense grid of the box, each point on its own."""
    import itertools

    import numpy as np

    from dobhil.analysis.worst_disk import disk_margin_at
    from dobhil.config.load import load_config
    config = load_config("paper/fig3", overrides=[a for a in config_args if a != "--set"])
    grids = [np.geomspace(lo, hi, per_key) if lo > 0 and hi >= 10 * lo else np.linspace(lo, hi, per_key)
             for lo, hi in ranges.values()]
    alphas = []
    for values in itertools.product(*grids):
        margin = disk_margin_at(config, dict(zip(ranges, map(float, values))), sampled)
        assert margin is not None
        alphas.append(margin.alpha)
    return min(alphas)


@pytest.mark.parametrize(("sets", "ranges"), [
    # the tuned design over the Fig. 3 box
    (TUNED, {"environment.stiffness": (1e3, 1e5), "environment.damping": (10.0, 200.0)}),
    # a small C_f: stable for every scaling of C_f, no smallest gain margin; the smallest
    # disk margin inside the range (near K 3000), not at an end
    (["--set", "design.force_gain=0.1"], {"environment.stiffness": (100.0, 1e5)}),
    # the tuned design's smallest one inside the range too (near K 1200)
    (TUNED, {"environment.stiffness": (100.0, 1e5)}),
])
def test_the_disk_margin_is_the_smallest_a_dense_scan_finds(
        capsys: pytest.CaptureFixture[str], sets: list[str], ranges: dict[str, tuple[float, float]]) -> None:
    """The disk margin reported over a certified box is met at a point inside the box, and a
    scan (40 points of one key, 8 per key of two; a key of a decade or more log-spaced)
    finds none smaller by more than 1e-3 of it, both loops."""
    box = [a for key, (lo, hi) in ranges.items() for a in ("--range", f"{key}={lo}:{hi}")]
    assert main(["certify", "paper/fig3", *box, *sets, "--json"]) == 0
    answer = json.loads(capsys.readouterr().out)
    for name in ("continuous", "sampled"):
        disk = answer["disk_margin"][name]
        assert disk["stable"], disk
        assert all(lo <= disk["at"][k] <= hi for k, (lo, hi) in ranges.items()), disk
        scanned = _scan_alpha(sets, ranges, name == "sampled", 40 if len(ranges) == 1 else 8)
        assert disk["alpha"] <= scanned * (1 + 1e-3), (name, disk, scanned)
    assert main(["certify", "paper/fig3", *box, *sets, "--loop", "continuous"]) == 0
    assert "points searched; not a bound): ±" in capsys.readouterr().out


@pytest.mark.parametrize(("args", "says"), [
    (["--range", "design.force_gain=1:2"], "treats only environment.stiffness, environment.damping, "
                                           "plant.inertia, plant.viscous_friction"),
    (["--range", "environment.stiffness=1e5:1e3"], "expected LO < HI"),
    (["--range", "environment.stiffness=x:1e3"], "two finite numbers"),
    (["--range", "environment.stiffness=1:2", "--range", "environment.stiffness=3:4"], "more than once"),
    (["--range", "environment.stiffness=1:2", "--refinements", "-1"], "--refinements -1"),
    (["--range", "environment.stiffness=1:2", "--set", "nothing.here=1"], "nothing.here"),
    # past the key's ceiling (the config's, as --set has it): the coefficients would overflow
    (["--range", "environment.stiffness=1e3:1e20"], "allowed: >= 0 and <= 1e+10"),
    (["--range", "plant.inertia=0.2:1e20"], "allowed: >= 1e-12 and <= 1e+06"),
    # within > 0 and past the key's floor, where the coefficients overflow: the floor's line
    (["--range", "plant.inertia=1e-300:1e-299", "--refinements", "10"],
     "--range plant.inertia = 1e-300: out of range; allowed: >= 1e-12 and <= 1e+06 kg m^2"),
])
def test_bad_input_is_one_line_and_exit_2(args: list[str], says: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["certify", "paper/fig3", *args]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("dobhil certify: error: ") and says in err


def test_a_box_past_the_keys_ranges_is_one_line_not_a_numpy_error() -> None:
    """Built past parse_range's checks (as no command can any more): one line saying the
    certificate cannot answer, not numpy's error."""
    from dobhil.analysis.certify import Box
    from dobhil.cli.certify_cmd import _answered
    from dobhil.config import load_config
    from dobhil.errors import AnalysisError
    with pytest.raises(AnalysisError, match="the certificate cannot answer this box"):
        _answered(load_config("paper/fig3"), Box(("plant.inertia",), (1e-300,), (1e-299,)), "both", 10)


def test_tune_reports_the_certificate_of_its_design_over_its_box(capsys: pytest.CaptureFixture[str]) -> None:
    """The design tune prints, certified again here by dobhil certify over the same box, gives
    the same answer tune printed (the --uncertainty key's ends are the box's)."""
    args = ["paper/fig3", "--range", "environment.stiffness=1e3:1e5", "--uncertainty", "plant.inertia=±10%",
            "--grid", "6", "--generations", "4"]
    assert main(["tune", *args, "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    cert = report["certificate"]
    assert cert["box"] == {"environment.stiffness": [1e3, 1e5], "plant.inertia": [0.225, 0.275]}
    sets = [x for k, v in report["design"].items() for x in ("--set", f"{k}={v!r}")]
    assert main(["certify", "paper/fig3", "--range", "environment.stiffness=1e3:1e5",
                 "--range", "plant.inertia=0.225:0.275", *sets, "--json"]) in (0, 1)
    again = json.loads(capsys.readouterr().out)
    assert again["continuous"] == cert["continuous"] and again["sampled"]["verdict"] == cert["sampled"]["verdict"]


def test_tune_names_a_key_the_certificate_cannot_treat(capsys: pytest.CaptureFixture[str]) -> None:
    from dobhil.cli.certify_cmd import tuned_certificate
    from dobhil.config import load_config
    from dobhil.tune.problem import Range, parse_range
    config = load_config("paper/fig3")
    answer, lines = tuned_certificate(config, {"design.force_gain": 1.0},
                                      [parse_range("environment.stiffness=1e3:1e4"),
                                       Range("plant.coulomb_friction", 0.0, 0.1)], [])
    assert answer is None and lines == [
        "certificate over the box: not computed (plant.coulomb_friction is not a key it treats; it treats "
        "environment.stiffness, environment.damping, plant.inertia, plant.viscous_friction)"]
    answer, lines = tuned_certificate(config, {"design.force_gain": 1.0},
                                      [parse_range("environment.stiffness=1e3:1e4")], [])
    assert answer is not None and answer["continuous"]["verdict"] == "certified"
    assert lines[0].startswith("certificate over the whole box")
