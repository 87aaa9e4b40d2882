"""The stability gate of a config that lists axes (:mod:`dobhil.cli.axes_gate`,
:mod:`dobhil.analysis.coupled_gate`): coupled axes are judged as one sampled closed loop
before anything is opened. A pair whose axes are each stable alone but unstable through
their coupling is refused by ``run``, ``demo`` and ``check`` (one line, exit 2); with
``--allow-unstable`` the run goes on, and the emulated run shows what the gate predicted.
Without coupling the coupled verdict is the single-axis gate's, axis by axis."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dobhil.analysis.coupled import axis_designs
from dobhil.analysis.coupled_gate import assess_coupled
from dobhil.analysis.gate import GateStatus, assess
from dobhil.cli.main import main
from dobhil.config.axes import load_axes
from dobhil.drives.load import load_drive_profile

REPO = Path(__file__).resolve().parents[1]
DEMO = REPO / "configs" / "two-axis-demo.yaml"
#: a bus no test can open: a refusal naming something else came before any bus was opened
NO_BUS = "socketcan:dobhil-no-such-interface"


def pair(tmp_path: Path, *, gain: float = 7.0, damping: float = 300.0, **extra: Any) -> Path:
    """Two ODrive axes, each pressing on its own wall (K_env 1e4, D_env 50) at C_f = ``gain``,
    joined by a coupling (K 5000, D ``damping``). Alone each axis is stable up to C_f 8.7
    (left) and 7.6 (right); the coupling's damping decides the pair."""
    data: dict[str, Any] = yaml.safe_load(DEMO.read_text())
    data["environment"] = {"stiffness": 10000.0, "damping": 50.0,
                           "coupling": [{"axes": ["left", "right"], "stiffness": 5000.0, "damping": damping}]}
    data["design"]["force_gain"] = gain
    data["loop"]["duration"] = 0.3
    data.update(extra)
    path = tmp_path / "pair.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def verdicts(path: Path, sets: list[str] | None = None) -> tuple[Any, list[Any]]:
    """(the coupled verdict, each axis' single-axis verdict on its own wall)."""
    axes = load_axes(path, sets or [], [])
    profiles = {a.name: load_drive_profile(a.config, path.parent) for a in axes.axes}
    coupled = assess_coupled(list(axis_designs(axes, profiles)), list(axes.couplings))
    return coupled, [assess(a.config, profiles[a.name]) for a in axes.axes]


def one_line(args: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    code = main(args)
    out, err = capsys.readouterr()
    assert code == 2 and out == "" and err.count("\n") == 1 and "Traceback" not in err, (code, out, err)
    return err.strip()


def test_the_pair_is_unstable_only_through_its_coupling(tmp_path: Path) -> None:
    coupled, alone = verdicts(pair(tmp_path))
    assert [v.status for v in alone] == [GateStatus.STABLE, GateStatus.STABLE]
    assert coupled.status is GateStatus.UNSTABLE and coupled.refuses
    assert 0 < coupled.max_scale < 1
    # with the coupling's damping of the demo the same gains are stable
    assert verdicts(pair(tmp_path, damping=30.0))[0].status is GateStatus.STABLE


@pytest.mark.parametrize("command", [["run", "--emulate", "--lockstep"], ["demo", "--no-log"],
                                     ["check", "--bus", NO_BUS]])
def test_run_demo_and_check_refuse_it_before_anything_opens(tmp_path: Path, command: list[str],
                                                            capsys: pytest.CaptureFixture[str],
                                                            monkeypatch: pytest.MonkeyPatch) -> None:
    import dobhil.runtime.axes_session as axes_session

    def no_session(*_: Any, **__: Any) -> None:
        raise AssertionError("a session was opened")
    monkeypatch.setattr(axes_session, "AxesSession", no_session)
    line = one_line([command[0], str(pair(tmp_path)), *command[1:]], capsys)
    assert "refused: the coupled sampled loop of axes left, right (T = 0.001 s" in line
    assert "at C_f = left 7, right 7 is UNSTABLE; max stable scale of every C_f: 0.95" in line
    assert "--allow-unstable" in line


def test_allow_unstable_runs_it_and_the_run_shows_the_instability(tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    """The override is printed and recorded; the emulated pair then oscillates until a safety
    stop (the gate's prediction, seen by the emulator's plants, not by the analysis)."""
    code = main(["run", str(pair(tmp_path)), "--emulate", "--lockstep", "--allow-unstable", "--summary-json"])
    out, err = capsys.readouterr()
    assert "dobhil run: warning: stability gate overridden (--allow-unstable): the coupled sampled loop" in err
    info = json.loads(out)
    gate = info["stability_gate"]["left+right"]
    assert gate["status"] == "unstable" and gate["overridden"] is True and gate["allow_unstable"] is True
    assert code == 1 and info["stop_reason"] != "done"


def test_stable_pair_runs_and_records_the_gate(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["run", str(pair(tmp_path, damping=30.0)), "--emulate", "--lockstep", "--summary-json"])
    out, err = capsys.readouterr()
    info = json.loads(out)
    gate = info["stability_gate"]["left+right"]
    assert code == 0 and gate["status"] == "stable" and gate["overridden"] is False
    # the margin is the distance in dB from the design (scale 1) to the largest stable scale
    assert gate["gain_margin_db"] == pytest.approx(20 * math.log10(gate["max_stable_scale"]), rel=1e-12)
    assert gate["phase_margin_deg"] is None   # a loop of two inputs has no one phase margin
    assert "stability gate" not in err        # above analysis.min_gain_margin: nothing said


def test_a_margin_below_min_gain_margin_is_one_warning(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = pair(tmp_path, damping=30.0)
    coupled, _ = verdicts(path)
    above = coupled.gain_margin_db + 1.0
    code = main(["run", str(path), "--emulate", "--lockstep", "--set", f"analysis.min_gain_margin={above}",
                 "--duration", "0.01"])
    err = capsys.readouterr().err
    warned = [line for line in err.splitlines() if "stability" in line]
    assert code == 0 and len(warned) == 1
    assert warned[0].startswith(f"dobhil run: warning: low stability margin: gain margin "
                                f"{coupled.gain_margin_db:.3g} dB (every C_f scaled together) < "
                                f"analysis.min_gain_margin = {above:g} dB")


def test_check_says_the_coupled_verdict_once_for_the_pair(tmp_path: Path) -> None:
    """Before any bus: the verdict in ``dobhil check``'s lines is the group's."""
    from dobhil.cli.axes_check import _lines
    coupled, _ = verdicts(pair(tmp_path, damping=30.0))
    lines = _lines([], [("left+right", coupled)], [], True)
    assert lines[0] == f"axes left+right: stability gate: {coupled.summary()}"


def test_the_demo_passes_the_coupled_gate() -> None:
    coupled, _ = verdicts(DEMO)
    assert coupled.stable and coupled.gain_margin_db > coupled.min_gain_margin_db
    assert coupled.warning() is None


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                 HealthCheck.function_scoped_fixture])
@given(left=st.floats(0.5, 12.0), right=st.floats(0.5, 12.0))
def test_without_coupling_the_verdict_is_each_axis_own(tmp_path: Path, left: float, right: float) -> None:
    """A coupling of zero stiffness and damping joins nothing: the pair is stable exactly when
    both axes are, and its largest scale is the smaller of the axes' own (their max stable
    C_f over their C_f), from two independent computations (the single-axis gain map)."""
    path = pair(tmp_path, damping=0.0)
    text = path.read_text().replace("stiffness: 5000.0", "stiffness: 0.0")
    path.write_text(text)
    coupled, alone = verdicts(path, [f"axes.left.design.force_gain={left!r}",
                                     f"axes.right.design.force_gain={right!r}"])
    assert coupled.stable == all(v.stable for v in alone)
    expected = min(v.max_stable_gain / v.force_gain for v in alone)
    assert np.isclose(coupled.max_scale, expected, rtol=1e-6)
