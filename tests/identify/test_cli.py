"""``dobhil identify`` refusals (one line, exit 2), ``dobhil compare`` and ``--set-file``."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from dobhil.cli.main import main
from dobhil.recording.reader import open_log


def _fails(capsys: pytest.CaptureFixture[str], args: list[str], match: str) -> None:
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert match in err, err


def test_identify_bad_input(logs: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _fails(capsys, ["identify", str(logs["still"])], "no motion")
    _fails(capsys, ["identify", str(logs["contact"]), "--segment", "0.4:2"], "outside the log")
    _fails(capsys, ["identify", str(logs["contact"]), "--segment=-0.1:0.2"], "outside the log")
    for reversed_ in ("0.2:0.1", "0.2:0.2"):   # inside the log, in the wrong order
        _fails(capsys, ["identify", str(logs["contact"]), "--segment", reversed_], "T0 must be below T1")
    _fails(capsys, ["identify", str(logs["contact"]), "--segment", "0.1:nan"], "must be finite numbers")
    _fails(capsys, ["identify", str(logs["contact"]), "--drive", "mini-cheetah"],
           "'odrive' drive, but the profile given is 'mit'")
    cut = tmp_path / "cut.mcap"
    shutil.copy(logs["contact"], cut)
    with open(cut, "r+b") as f:
        f.truncate(cut.stat().st_size - 100)
    _fails(capsys, ["identify", str(cut)], "cut.mcap")
    _fails(capsys, ["identify", str(tmp_path / "none.mcap")], "none.mcap")
    _fails(capsys, ["identify", str(logs["contact"]), "--out", str(tmp_path / "o.txt")], "--out")
    _fails(capsys, ["identify", str(logs["contact"]), "--drive", "no-such-drive"], "no-such-drive")
    _fails(capsys, ["identify", str(logs["contact"]), "--period", "0.001"], "records its own period")
    _fails(capsys, ["identify", str(logs["free"]), str(logs["contact"]), "--segment", "0:0.4"], "one LOG at a time")
    _fails(capsys, ["identify", str(logs["free"]), str(logs["still"])], "still.mcap: the position never changes")
    # one log twice (by another path too) would count its noise twice: intervals too narrow
    twin = logs["free"].parent / "." / logs["free"].name
    _fails(capsys, ["identify", str(logs["free"]), str(logs["contact"]), str(twin)], "given twice")
    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(b"not an mcap file at all" * 10)
    _fails(capsys, ["identify", str(garbage)], "garbage.mcap")
    assert main(["log", "export", str(logs["contact"]), "--can", "--format", "candump",
                 "-o", str(tmp_path / "c.log")]) == 0
    assert main(["log", "import", str(tmp_path / "c.log"), "-o", str(tmp_path / "c.mcap")]) == 0
    capsys.readouterr()
    _fails(capsys, ["identify", str(tmp_path / "c.mcap")], "--drive")
    _fails(capsys, ["identify", str(tmp_path / "c.mcap"), "--drive", "mini-cheetah"], "another protocol")
    _fails(capsys, ["identify", str(tmp_path / "c.mcap"), "--drive", "odrive-0.6", "--period", "0"], "--period")
    # a period the stamps contradict scales the inertia with its square (0.002 on this 1 ms log: J doubled)
    for wrong in ("0.002", "0.0005", "0.00101"):
        _fails(capsys, ["identify", str(tmp_path / "c.mcap"), "--drive", "odrive-0.6", "--period", wrong],
               "c.mcap's motion frames come every 0.001 s")


def _forces(path: Path) -> dict[int, float]:
    with open_log(path) as log:
        return {p["cycle"]: p["tau_int_hat"] for _, _, p in log.iter_messages(["/controller"])}


def test_compare(logs: dict[str, Path], capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["compare", str(logs["contact"]), str(logs["contact"]), "--json"]) == 0
    same = json.loads(capsys.readouterr().out)
    assert same["rms"] == 0.0 and same["cycles"] == len(_forces(logs["contact"]))
    assert main(["compare", str(logs["contact"]), str(logs["free"]), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    a, b = _forces(logs["contact"]), _forces(logs["free"])
    common = sorted(a.keys() & b.keys())
    d = np.array([b[c] - a[c] for c in common])
    assert info["cycles"] == len(common) and info["rms"] == pytest.approx(float(np.sqrt(np.mean(d ** 2))))
    assert info["rms"] > 0.0


def test_compare_notes_different_references_and_lengths(logs: dict[str, Path], tmp_path: Path,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    """A shorter run of the same config, or a run of another reference, compares over what
    both have: one line says which differ and how, or the RMS reads as a model's misfit."""
    from tests.identify.conftest import emulated_log
    short = emulated_log(tmp_path / "short.mcap", duration=0.2)
    capsys.readouterr()
    assert main(["compare", str(logs["contact"]), str(logs["contact"])]) == 0
    assert len(capsys.readouterr().out.splitlines()) == 1
    assert main(["compare", str(logs["contact"]), str(short)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert len(out) == 2 and out[1].startswith("note: ") and "500 cycles" in out[1] and "200" in out[1], out
    assert "reference" not in out[1], out
    assert main(["compare", str(logs["contact"]), str(logs["free"]), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    note = info["note"]
    assert "reference.kind step vs chirp" in note and "reference.amplitude 0.8 vs 0.2" in note, note
    assert main(["compare", str(logs["contact"]), str(short), "--json"]) == 0
    assert "reference" not in json.loads(capsys.readouterr().out)["note"]


def _analyze(capsys: pytest.CaptureFixture[str], *extra: str) -> dict[str, object]:
    assert main(["analyze", "demo", "--json", *extra]) == 0
    return json.loads(capsys.readouterr().out)  # type: ignore[no-any-return]


def test_set_file_is_applied_like_set_and_before_it(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    overlay = tmp_path / "overlay.yaml"
    overlay.write_text("plant.inertia: 0.3\nenvironment:\n  stiffness: 5000.0\n", encoding="utf-8")
    by_set = _analyze(capsys, "--set", "plant.inertia=0.3", "--set", "environment.stiffness=5000")
    by_file = _analyze(capsys, "--set-file", str(overlay))
    default = _analyze(capsys)
    assert by_file == by_set != default
    later = _analyze(capsys, "--set-file", str(overlay), "--set", "plant.inertia=0.25",
                     "--set", "environment.stiffness=10000")
    assert later == default   # --set wins over --set-file


def test_set_file_bad_input(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    for command in (["analyze"], ["run"], ["check"], ["sweep", "--vary", "design.force_gain=1:2:2"]):
        # every command taking a config has it
        _fails(capsys, [command[0], "demo", *command[1:], "--set-file", str(tmp_path / "missing.yaml")],
               "--set-file")
    bad = tmp_path / "bad.yaml"
    bad.write_text("plant.mass: 1\n", encoding="utf-8")
    _fails(capsys, ["analyze", "demo", "--set-file", str(bad)], "plant.mass")
    flat = tmp_path / "flat.yaml"
    flat.write_text("inertia: 1\n", encoding="utf-8")
    _fails(capsys, ["analyze", "demo", "--set-file", str(flat)], "not a section.key")


SET_FILE_EXPECTED = "expected a YAML file of section.key: value"


@pytest.mark.parametrize(("content", "says"), [
    (None, "is a directory"),
    (b"\x89PNG\r\n\x1a\n\x00\x00", "is not UTF-8 text"),
    (b"- plant.inertia: 0.3\n", "holds a YAML list, not a mapping"),
    (b"just some text\n", "holds a YAML string (plain text), not a mapping"),
    (b"plant: [\n", "YAML syntax error at line 2"),
])
def test_set_file_that_is_no_overlay(content: bytes | None, says: str, tmp_path: Path,
                                     monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """A --set-file that is a directory, an image or YAML that is no mapping is named as the
    --set-file (not a config file, not a missing one), with what it should hold."""
    monkeypatch.chdir(tmp_path)  # a short name: a long one is shortened in the message
    given = Path("given.png")
    if content is None:
        given.mkdir()
    else:
        given.write_bytes(content)
    for command in (["analyze"], ["tune"], ["sweep", "--vary", "design.force_gain=1:2:2"]):
        _fails(capsys, [command[0], "demo", *command[1:], "--set-file", str(given)],
               f"--set-file '{given}': {says}")
    assert main(["analyze", "demo", "--set-file", str(given)]) == 2
    err = capsys.readouterr().err
    assert SET_FILE_EXPECTED in err and "config file" not in err and "no such file" not in err, err


def test_a_noise_free_contact_run_is_fitted_without_warnings(tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    """A noise-free pressed run determines some direction only to rounding: lmfit's own
    covariance (which the fit does not use) had a negative variance there, and numpy's
    "invalid value encountered in sqrt" reached the user's terminal, twice."""
    import warnings
    path = tmp_path / "pressed.mcap"
    assert main(["run", "identify-contact", "--emulate", "--lockstep", "--log", str(path),
                 "--set", "loop.duration=0.1"]) == 0
    capsys.readouterr()
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        assert main(["identify", str(path)]) == 0
    err = capsys.readouterr().err
    assert "warning" not in err and "sqrt" not in err, err


def test_a_delay_ending_a_hair_above_0_keeps_its_interval(tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    """A delay of 0 whose fit ends within scipy's 1e-10 of its bound (1e-13 s, say) was "not
    identifiable, +-1e3 s" in 7 of 12 windows of this free run: scipy takes the Jacobian with
    steps relative to that tiny value, and the delay's column came out 0 (fit.py ``_drifted``).
    Every window now says 0 with an interval of a fraction of a period."""
    import yaml
    profile = yaml.safe_load((Path(__file__).parents[2] / "drivers" / "odrive-0.6.yaml").read_text())
    profile.update(feedback_period=0.02, bus={})
    (tmp_path / "p.yaml").write_text(yaml.safe_dump(profile))
    path = tmp_path / "free.mcap"
    sets = {"drive.profile": tmp_path / "p.yaml", "loop.period": 0.02, "loop.feedback_timeout": 0.2,
            "loop.duration": 3, "reference.frequency_end": 10, "reference.lines": 20,
            "sensor.velocity_noise": 0.001, "sensor.seed": 1}
    assert main(["run", "identify-free", "--emulate", "--lockstep", "--log", str(path),
                 *[a for k, v in sets.items() for a in ("--set", f"{k}={v}")]]) == 0
    capsys.readouterr()
    for t0 in ("0.08", "0.1", "0.14"):        # each failed before
        assert main(["identify", str(path), "--segment", f"{t0}:3:free", "--json"]) == 0
        delay = json.loads(capsys.readouterr().out)["estimates"]["delay"]
        assert delay["identifiable"] and 0.0 <= delay["low"] <= delay["value"] < delay["high"] < 0.01, (t0, delay)


def test_identify_free_run_end_to_end(logs: dict[str, Path], tmp_path: Path,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    """A free-motion run: its one segment found, no environment numbers (not identifiable, said
    why), the overlay usable by analyze through --set-file, one figure per segment."""
    import yaml
    out, plots = tmp_path / "overlay.yaml", tmp_path / "plots"
    assert main(["identify", str(logs["free"]), "--json", "--out", str(out), "--plot", str(plots)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert [s["kind"] for s in info["segments"]] == ["free"] and info["samples"] > 0
    for name in ("stiffness", "damping", "contact_position"):
        e = info["estimates"][name]
        assert not e["identifiable"] and e["value"] is None and e["why"]
    text = out.read_text(encoding="utf-8")
    overlay = yaml.safe_load(text)
    assert overlay and not any(k.startswith("environment.") for k in overlay)
    # each value exactly the estimate, commented with its interval; what is missing says why
    inertia = info["estimates"]["inertia"]
    assert overlay["plant.inertia"] == inertia["value"]
    assert f"plant.inertia: {inertia['value']!r}  # 95 % [{inertia['low']:.6g}, {inertia['high']:.6g}]" in text
    assert "# not identifiable: stiffness: no contact segment" in text
    assert all(info["estimates"][k.split(".")[1]]["identifiable"] for k in overlay if k.startswith("plant."))
    assert main(["analyze", "demo", "--set-file", str(out), "--json"]) == 0
    capsys.readouterr()
    assert sorted(p.name for p in plots.iterdir()) == ["identify_segment_0.png"]


def test_identify_prints_each_estimate_with_its_unit(capsys: pytest.CaptureFixture[str]) -> None:
    """The printed estimates and the residual RMS carry their units (an inertia of 0.3 and a
    delay of 0.00026 read alike without them)."""
    from dobhil.cli.identify_cmd import _print
    def est(value: float) -> dict[str, object]:
        return {"value": value, "low": 0.9 * value, "high": 1.1 * value, "stderr": 0.05 * value,
                "identifiable": True, "why": ""}
    estimates = {"inertia": est(0.3), "viscous_friction": est(0.05), "coulomb_friction": est(0.01),
                 "contact_position": est(2e-6), "stiffness": est(15000.0), "damping": est(60.0),
                 "delay": est(2.6e-4),
                 "torque_gain": {"identifiable": False, "why": "held at 1"}}
    _print({"files": ["a.mcap"], "file": "a.mcap", "protocol": "odrive", "samples": 100, "period": 0.001,
            "segments": [{"file": "a.mcap", "kind": "contact", "t0": 0.0, "t1": 0.1}], "estimates": estimates,
            "residual": {"rms": 0.001, "whiteness_p": 0.5, "warning": ""}})
    lines = {line.split()[0]: line for line in capsys.readouterr().out.splitlines()}
    units = {"inertia": "kg m^2", "viscous_friction": "N m s/rad", "coulomb_friction": "N m",
             "contact_position": "rad", "stiffness": "N m/rad", "damping": "N m s/rad", "delay": "s"}
    for name, unit in units.items():
        assert f"{estimates[name]['value']:.6g} {unit}  95 %" in lines[name], lines[name]
    assert "residual RMS 0.001 rad/s," in lines["residual"]


class _FitReached(BaseException):
    """Raised in place of the fit: everything read before it has been read (not an
    Exception, which the CLI would report as a bug)."""


@pytest.mark.parametrize(("method", "fit"), [("open-loop", "dobhil.identify.fit.identify"),
                                             ("auto", "dobhil.identify.closedloop.identify_closed_loop")])
def test_identify_opens_each_log_once(method: str, fit: str, logs: dict[str, Path],
                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """Opening a log reads and checks the whole file (20-50 ms a 10 s run); identify asked for
    the same log 4 to 7 times before its fit (its method, its axes, its data, its drive's
    firmware, --validate's), each a new LogFile: now one per file."""
    from dobhil.recording import reader

    def stop(*args: object, **kwargs: object) -> None:
        raise _FitReached
    monkeypatch.setattr(fit, stop)
    opened: list[str] = []
    init = reader.LogFile.__init__

    def counted(self: reader.LogFile, path: str, **kwargs: bool) -> None:
        opened.append(str(path))
        init(self, path, **kwargs)
    monkeypatch.setattr(reader.LogFile, "__init__", counted)
    with pytest.raises(_FitReached):
        main(["identify", str(logs["contact"]), "--method", method, "--validate", str(logs["contact"])])
    assert opened == [str(logs["contact"])]
