"""``dobhil paper``: a claim not reproduced is a failed check (exit 1), not bad input (2)."""

from __future__ import annotations

from pathlib import Path

import pytest

from dobhil import paper
from dobhil.cli.main import main


def test_a_claim_not_reproduced_exits_1_with_one_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    real = paper.fig3_facts

    def one_fails(cases: dict[float, object]) -> list[paper.Fact]:
        facts = real(cases)  # type: ignore[arg-type]
        return [paper.Fact(facts[0].claim, False, facts[0].evidence), *facts[1:]]

    monkeypatch.setattr(paper, "fig3_facts", one_fails)
    assert main(["paper", "--out", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "1 claim(s) of the paper not reproduced" in err
    assert (tmp_path / "fig3_step.png").is_file()


def test_an_output_that_is_a_file_is_refused_before_any_work(tmp_path: Path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "taken"
    out.write_text("mine\n")
    assert main(["paper", "--out", str(out)]) == 2
    assert "exists and is not a directory" in capsys.readouterr().err and out.read_text() == "mine\n"
