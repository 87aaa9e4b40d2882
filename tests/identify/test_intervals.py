"""The identified uncertainty carried on: the overlay's ``identified:`` section (written by
``identify --out``, skipped by ``--set-file``), ``tune --uncertainty-from`` (its intervals as
the box) and ``montecarlo --draw-from`` (a joint normal of its estimates and covariance,
truncated to physical values)."""

from __future__ import annotations

import contextlib
import io
import json
import math
from pathlib import Path

import numpy as np
import pytest
import scipy.stats

from dobhil.campaign.draws import JointNormal, Kind, Vary, draw
from dobhil.cli.identified_box import identified_box, joint_varies
from dobhil.cli.main import main
from dobhil.config.load import load_config
from dobhil.errors import ConfigError
from dobhil.identify.intervals import read_identified
from dobhil.tune.problem import IntervalUncertainty, robust_set


@pytest.fixture(scope="module")
def identified(logs: dict[str, Path], tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    """An overlay of the free and contact logs, and the JSON identify printed with it (once)."""
    out = tmp_path_factory.mktemp("overlay") / "overlay.yaml"
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed), contextlib.redirect_stderr(io.StringIO()):
        assert main(["identify", str(logs["free"]), str(logs["contact"]), "--out", str(out), "--json"]) == 0
    return out, json.loads(printed.getvalue())


def test_overlay_round_trip(identified: tuple[Path, dict]) -> None:
    out, info = identified
    ident = read_identified(out, "--uncertainty-from")
    names = {"plant.inertia": "inertia", "plant.viscous_friction": "viscous_friction",
             "plant.coulomb_friction": "coulomb_friction", "environment.contact_position": "contact_position",
             "environment.stiffness": "stiffness", "environment.damping": "damping"}
    expected = [k for k, n in names.items() if info["estimates"][n]["identifiable"]]
    assert list(ident.keys) == expected and "plant.inertia" in expected
    z = scipy.stats.norm.ppf(0.975)
    for i in ident.intervals:
        e = info["estimates"][names[i.key]]
        # repr of a float round-trips exactly through YAML
        assert (i.estimate, i.lo, i.hi) == (e["value"], e["low"], e["high"])
        # the standard error the fit gave, but at the bound 0 the interval's: its 95 % of the
        # normal truncated there is the interval
        cut = i.lo == 0.0 and e["value"] - z * e["stderr"] < 0.0
        assert i.stderr == pytest.approx((i.hi - i.estimate) / z if cut else e["stderr"], rel=1e-12)
    # the covariance: the standard errors on its diagonal, the reported correlations off it
    sd = np.sqrt(np.diag(ident.covariance))
    assert np.allclose(sd, [i.stderr for i in ident.intervals], rtol=1e-12)
    for c in info["correlations"]:
        a, b = names_index(ident.keys, names, c["a"]), names_index(ident.keys, names, c["b"])
        if a is not None and b is not None:
            assert ident.covariance[a, b] / (sd[a] * sd[b]) == pytest.approx(c["r"], rel=1e-12)
    # --set-file takes the overlay's keys and skips its identified: section
    config = load_config("demo", (), [out])
    assert config.plant.inertia == info["estimates"]["inertia"]["value"]


def names_index(keys: tuple[str, ...], names: dict[str, str], estimate: str) -> int | None:
    key = next((k for k, n in names.items() if n == estimate), None)
    return keys.index(key) if key in keys else None


def test_box_is_the_intervals(identified: tuple[Path, dict], capsys: pytest.CaptureFixture[str]) -> None:
    out, _ = identified
    ident = {i.key: i for i in read_identified(out, "--uncertainty-from").intervals}
    box = identified_box(str(out))
    err = capsys.readouterr().err
    assert all(isinstance(u, IntervalUncertainty) for u in box)
    # the loop's keys only (no Coulomb friction or contact position in the linear loop), printed with bounds
    assert {u.key for u in box} <= {"plant.inertia", "plant.viscous_friction", "environment.stiffness",
                                    "environment.damping"}
    for u in box:
        assert f"{u.key} [{ident[u.key].lo:.6g}, {ident[u.key].hi:.6g}]" in err
    grid = robust_set(load_config("demo"), [], box, 5)
    for u in box:
        assert sorted(set(grid.points[u.key])) == sorted({ident[u.key].lo, ident[u.key].estimate, ident[u.key].hi})


def test_joint_draws(identified: tuple[Path, dict], capsys: pytest.CaptureFixture[str]) -> None:
    out, _ = identified
    ident = read_identified(out, "--draw-from")
    varies = joint_varies(str(out))
    assert "truncated to >= 0" in capsys.readouterr().err
    assert [v.key for v in varies] == list(ident.keys) and all(v.kind is Kind.JOINT_NORMAL for v in varies)
    x = np.array([[draw(varies, 3, i)[0][k] for k in ident.keys] for i in range(4000)])
    # the same run index, the same values (a run's draws depend on (seed, index) only)
    assert draw(varies, 3, 17)[0] == draw(varies, 3, 17)[0]
    # the truncated normal's moments, from an independent sample rejected the same way: an
    # estimate within a few standard errors of its bound 0 (the noise-free fixture's Coulomb
    # friction, fitted at 0) moves the mean and correlations of the draws off the normal's
    mean = np.array([i.estimate for i in ident.intervals])
    sd = np.sqrt(np.diag(ident.covariance))
    lower = np.array(varies[0].joint.lower)
    ref = np.random.default_rng(0).multivariate_normal(mean, ident.covariance, 400_000)
    ref = ref[np.all(ref >= lower, axis=1)]
    assert np.all(np.abs(x.mean(axis=0) - ref.mean(axis=0)) < 4 * sd / math.sqrt(len(x)))
    assert np.allclose(np.corrcoef(x.T), np.corrcoef(ref.T), atol=0.06)


def test_a_key_at_its_bound_is_drawn_inside_its_interval() -> None:
    """A friction fitted at 0 has its interval's high end from the profile likelihood, here
    well inside the linearised ``z s`` (an AK80-9 free run's Coulomb friction: [0, 3.2e-4],
    s 5.5e-4): the covariance the draws use puts 95 % of the normal truncated at 0 inside the
    interval, not over half of it above; a key inside its bounds keeps the fit's s."""
    from dobhil.identify.intervals import section_text
    est = {"inertia": {"value": 0.2485, "low": 0.24745, "high": 0.24957, "stderr": 5.39e-4, "identifiable": True},
           "coulomb_friction": {"value": 5.9e-10, "low": 0.0, "high": 3.2e-4, "stderr": 5.49e-4,
                                "identifiable": True}}
    text = section_text({"estimates": est, "correlations": [{"a": "inertia", "b": "coulomb_friction", "r": -0.3}]})
    import yaml
    section = yaml.safe_load(text)["identified"]
    assert section["intervals"]["plant.inertia"]["stderr"] == 5.39e-4
    s = section["intervals"]["plant.coulomb_friction"]["stderr"]
    cov = np.array(section["covariance"]["matrix"])
    assert math.sqrt(cov[1, 1]) == pytest.approx(s, rel=1e-12)
    assert cov[0, 1] / (5.39e-4 * s) == pytest.approx(-0.3, rel=1e-12)   # the correlation kept
    # the 95 % point of the normal at 0 truncated there (a half-normal) is the interval's end
    assert scipy.stats.halfnorm(scale=s).ppf(0.95) == pytest.approx(3.2e-4, rel=1e-5)


def test_truncation_is_exact_rejection() -> None:
    """A normal straddling 0: every draw >= 0, distributed as the normal conditioned on it (its
    mean the truncated normal's, an independent calculation by scipy)."""
    import scipy.stats
    joint = JointNormal(keys=("plant.viscous_friction", "plant.inertia"), mean=(0.01, 0.25),
                        covariance=((1e-4, 0.0), (0.0, 1e-6)), lower=(0.0, 0.0), source="t")
    varies = tuple(Vary(k, Kind.JOINT_NORMAL, m, 0.0, False, joint) for k, m in zip(joint.keys, joint.mean))
    x = np.array([draw(varies, 1, i)[0]["plant.viscous_friction"] for i in range(6000)])
    assert x.min() >= 0.0
    truth = scipy.stats.truncnorm(-1.0, np.inf, loc=0.01, scale=0.01)
    assert abs(x.mean() - truth.mean()) < 4 * truth.std() / math.sqrt(len(x))
    assert joint.acceptance() == pytest.approx(scipy.stats.norm.sf(-1.0), abs=0.01)


def _fails(capsys: pytest.CaptureFixture[str], args: list[str], match: str) -> None:
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert match in err, err


def test_overlay_without_intervals(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    plain = tmp_path / "plain.yaml"
    plain.write_text("plant.inertia: 0.25\n")
    _fails(capsys, ["tune", "demo", "--uncertainty-from", str(plain)], "no identified intervals")
    _fails(capsys, ["montecarlo", "demo", "--runs", "2", "--draw-from", str(plain)], "no identified intervals")
    _fails(capsys, ["tune", "demo", "--uncertainty-from", str(tmp_path / "none.yaml")], "no such file")
    # a directory is said to be one, and an image is no config file: both named by their option
    _fails(capsys, ["tune", "demo", "--uncertainty-from", str(tmp_path)],
           f"--uncertainty-from {tmp_path}: is a directory")
    image = tmp_path / "plot.png"
    image.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00")
    _fails(capsys, ["montecarlo", "demo", "--runs", "2", "--draw-from", str(image)],
           f"--draw-from {image}: is not UTF-8 text (byte 0x89 at offset 0); expected an overlay written by dobhil")
    bad = tmp_path / "bad.yaml"
    bad.write_text("identified:\n  intervals:\n    plant.inertia: {estimate: 0.25, lo: 0.3, hi: 0.2, stderr: 1}\n"
                   "  covariance: {keys: [plant.inertia], matrix: [[1.0]]}\n")
    _fails(capsys, ["montecarlo", "demo", "--runs", "2", "--draw-from", str(bad)], "malformed")
    _fails(capsys, ["tune", "demo"], "no robust set")
    _fails(capsys, ["montecarlo", "demo", "--runs", "2"], "nothing to draw")
    with pytest.raises(ConfigError, match="covariance does not match"):
        skew = tmp_path / "skew.yaml"
        skew.write_text("identified:\n  intervals:\n    plant.inertia: {estimate: 0.25, lo: 0.2, hi: 0.3, stderr: 1}\n"
                        "  covariance: {keys: [plant.inertia], matrix: [[1.0, 0.0]]}\n")
        read_identified(skew, "--draw-from")


@pytest.mark.parametrize(("section", "says"), [
    ("  level: 5\n", "level 5 is no confidence level"),
    ("  level: 0\n", "level 0 is no confidence level"),
    ("", "not positive semi-definite"),      # the covariance below, with no level
])
def test_an_overlay_that_is_no_distribution_is_refused(tmp_path: Path, section: str, says: str) -> None:
    """A level printed as "500 % intervals", a covariance with a negative eigenvalue: drawn
    from before, exit 0. Refused in the overlay's one line."""
    path = tmp_path / "o.yaml"
    matrix = "[[1.0, 0.0], [0.0, 1.0]]" if section else "[[1.0, 2.0], [2.0, 1.0]]"   # eigenvalues -1, 3
    path.write_text("identified:\n" + section +
                    "  intervals:\n    plant.inertia: {estimate: 0.25, lo: 0.2, hi: 0.3, stderr: 0.02}\n"
                    "    environment.stiffness: {estimate: 1.0e4, lo: 9.0e3, hi: 1.1e4, stderr: 500}\n"
                    "  covariance: {keys: [plant.inertia, environment.stiffness], matrix: " + matrix + "}\n")
    with pytest.raises(ConfigError, match=says):
        read_identified(path, "--draw-from")


def test_a_negative_standard_error_is_malformed(tmp_path: Path) -> None:
    path = tmp_path / "o.yaml"
    path.write_text("identified:\n  intervals:\n    plant.inertia: {estimate: 0.25, lo: 0.2, hi: 0.3, stderr: -0.02}\n"
                    "  covariance: {keys: [plant.inertia], matrix: [[0.0004]]}\n")
    with pytest.raises(ConfigError, match=r"malformed .*stderr -0.02: expected a standard error >= 0"):
        read_identified(path, "--draw-from")


def test_the_certificate_of_tune_is_over_the_identified_box(tmp_path: Path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    """tune certifies its design over the box it tuned on: each interval's own ends (asymmetric,
    a friction fitted at its bound 0), not the config's value +- the wider half -- which, without
    --set-file, centred the box on the config and, for an estimate at 0, divided by it."""
    from dobhil.cli.certify_cmd import tuned_certificate
    path = tmp_path / "o.yaml"
    path.write_text("identified:\n  intervals:\n"
                    "    plant.inertia: {estimate: 0.3, lo: 0.28, hi: 0.34, stderr: 0.015}\n"
                    "    plant.viscous_friction: {estimate: 0.0, lo: 0.0, hi: 0.004, stderr: 0.002}\n"
                    "  covariance: {keys: [plant.inertia, plant.viscous_friction], "
                    "matrix: [[2.25e-4, 0.0], [0.0, 4.0e-6]]}\n")
    box = identified_box(str(path))
    assert "plant.viscous_friction [0, 0.004]" in capsys.readouterr().err
    answer, _ = tuned_certificate(load_config("demo"), {}, [], box)
    assert answer is not None and answer["box"] == {"plant.inertia": [0.28, 0.34],
                                                    "plant.viscous_friction": [0.0, 0.004]}


@pytest.mark.parametrize("argv", [
    ["tune", "demo", "--uncertainty-from", "{o}", "--range", "environment.stiffness=1e3:2e3"],
    ["tune", "demo", "--uncertainty-from", "{o}", "--bound", "design.force_gain=-1:2"],
    ["tune", "demo", "--uncertainty-from", "{o}", "--margin", "gm=abc"],
    ["montecarlo", "demo", "--runs", "2", "--draw-from", "{o}", "--workers", "0"],
    ["montecarlo", "demo", "--runs", "2", "--draw-from", "{o}", "--vary", "plant.inertia=normal:0.3:0.01"],
    ["montecarlo", "demo", "--runs", "2", "--draw-from", "{o}", "--out", "{o}"],
])
def test_bad_input_beside_an_overlay_is_one_line(argv: list[str], tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """The line saying which box or draw an overlay gives comes once every input is checked:
    a refusal after the overlay was read stays its one line (it printed the box first)."""
    path = tmp_path / "o.yaml"
    path.write_text("identified:\n  intervals:\n    plant.inertia: {estimate: 0.25, lo: 0.2, hi: 0.3, stderr: 0.02}\n"
                    "    environment.stiffness: {estimate: 1.0e4, lo: 9.0e3, hi: 1.1e4, stderr: 500}\n"
                    "  covariance: {keys: [plant.inertia, environment.stiffness], "
                    "matrix: [[0.0004, 0.0], [0.0, 250000.0]]}\n")
    assert main([a.format(o=path) for a in argv]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"dobhil {argv[0]}: error: "), err


def test_tune_says_which_loop_keys_the_overlay_did_not_identify(tmp_path: Path) -> None:
    """An overlay of a pressed CAN log identifies the inertia and the stiffness but not the
    damping or the friction (only their sum): tune's box then holds those at the config's
    values, the truth outside it (the demo's 50 for a true 60), and nothing said so. The box
    line now names them, but a key a --range gives."""
    import argparse
    from dobhil.cli.tune_cmd import _robust_keys
    path = tmp_path / "o.yaml"
    path.write_text("identified:\n  intervals:\n    plant.inertia: {estimate: 0.3, lo: 0.29, hi: 0.31, stderr: 0.005}\n"
                    "    environment.stiffness: {estimate: 1.5e4, lo: 1.46e4, hi: 1.52e4, stderr: 150}\n"
                    "  covariance: {keys: [plant.inertia, environment.stiffness], "
                    "matrix: [[2.5e-5, 0.0], [0.0, 22500.0]]}\n")

    def said(*ranges: str) -> str:
        notes: list[str] = []
        _robust_keys(argparse.Namespace(ranges=list(ranges), uncertainty=[], uncertainty_from=str(path)), notes)
        return " ".join(notes)
    assert "not identified, at the config's value: plant.viscous_friction, environment.damping" in said()
    text = said("environment.damping=40:80")
    assert "not identified, at the config's value: plant.viscous_friction" in text
    assert "environment.damping" not in text.partition("not identified")[2]
