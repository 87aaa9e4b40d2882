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
    assert answer["disk_margin_at"] == cont["gain_margin"]["up_at"]
    assert answer["disk_margin_where"] == "smallest continuous gain margin"
    assert answer["disk_margin"]["continuous"]["gain_db"] <= cont["gain_margin"]["db"] + 1e-9


def test_a_margin_unbounded_both_ways_gives_the_disk_margin_at_the_box_centre(
        capsys: pytest.CaptureFixture[str]) -> None:
    """A soft box and a small C_f: stable for every scaling of C_f, so no point has the
    smallest gain margin; the disk margin is the one at the box's centre (inside the box,
    not the config's own stiffness outside it), and the line says where."""
    box = ["--range", "environment.stiffness=100:1000", "--set", "design.force_gain=0.1"]
    assert main(["certify", "paper/fig3", *box, "--loop", "continuous", "--json"]) == 0
    answer = json.loads(capsys.readouterr().out)
    assert answer["continuous"]["gain_margin"]["up"] is None and answer["continuous"]["gain_margin"]["down"] is None
    assert answer["disk_margin_at"] == {"environment.stiffness": 550.0}
    assert answer["disk_margin_where"] == "the box's centre"
    assert main(["certify", "paper/fig3", *box, "--loop", "continuous"]) == 0
    assert "disk margin (continuous) at environment.stiffness=550 (the box's centre): ±" in capsys.readouterr().out


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
    (["--range", "plant.inertia=0.2:1e20"], "allowed: > 0 and <= 1e+06"),
    # within the ranges and still not finite: one line, as analyze says of such a design
    (["--range", "plant.inertia=1e-300:1e-299", "--refinements", "10"], "the certificate cannot answer this box"),
])
def test_bad_input_is_one_line_and_exit_2(args: list[str], says: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["certify", "paper/fig3", *args]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("dobhil certify: error: ") and says in err


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
