"""``dobhil log convert``: a log copied into the other layout reads as its source
(dobhil/recording/relayout.py)."""

from __future__ import annotations

import tempfile
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dobhil.cli.main import main
from dobhil.errors import LogFileError
from dobhil.recording.reader import LogFile
from dobhil.recording.relayout import relayout
from tests.recording.test_cycle_layout import _STEP, _records, _written


@given(steps=st.lists(_STEP, max_size=40), written_as=st.sampled_from(("topics", "cycle")))
@settings(max_examples=40, deadline=None)   # folding across lanes, an offset's sign: failed within these
def test_a_copy_in_the_other_layout_reads_as_its_source(steps: list[tuple[str, int, int]], written_as: str) -> None:
    """Any records written in either layout, copied into the other and back: every copy
    gives the source's messages in its order, with its log times and values, and the same
    counts per topic."""
    records = _records(steps)
    with tempfile.TemporaryDirectory() as tmp:
        source = _written(Path(tmp) / "source.mcap", records, written_as)
        if not list(source.iter_messages()):
            return
        with pytest.raises(LogFileError, match=f"already in the {source.layout} layout"):
            relayout(source.path, source.layout)
        other = "cycle" if source.layout == "topics" else "topics"   # a cycle log without cycles reads as topics
        there = LogFile(relayout(source.path, other).output)
        copies = [there]
        if there.layout == other:   # else no cycle message to fold into: the copy has the same layout
            back = LogFile(relayout(there.path, source.layout, Path(tmp) / "back.mcap").output)
            assert back.layout == source.layout
            copies.append(back)
        else:
            assert other == "cycle" and not any(t.endswith(("/loop", "/controller")) for t in source.topics())
        for copy in copies:
            assert list(copy.iter_messages()) == list(source.iter_messages())
            assert copy.message_counts() == source.message_counts()
            assert set(copy.topics()) == set(source.topics())
            assert copy.metadata.keys() == source.metadata.keys()


def test_a_recorded_run_converts_both_ways_and_replays(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from tests.recording.test_run_logging import logged_lockstep_run
    source = tmp_path / "run.mcap"
    logged_lockstep_run(source, duration=0.3)
    assert main(["log", "convert", str(source), "--layout", "cycle"]) == 0
    cycle = tmp_path / "run.cycle.mcap"
    assert f"in the cycle layout to {cycle}" in capsys.readouterr().out
    assert main(["log", "convert", str(cycle), "--layout", "topics", "-o", str(tmp_path / "back.mcap")]) == 0
    capsys.readouterr()
    for path in (cycle, tmp_path / "back.mcap"):
        assert list(LogFile(path).iter_messages()) == list(LogFile(source).iter_messages())
        assert main(["replay", str(path), "--verify"]) == 0
    assert cycle.stat().st_size < 0.6 * source.stat().st_size


def test_convert_refuses_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The layout it is in, an output that exists, a JSON log to the cycle layout: one line,
    exit 2, nothing written, the input unchanged."""
    from tests.recording.test_run_logging import logged_lockstep_run
    source = tmp_path / "run.mcap"
    logged_lockstep_run(source, duration=0.1)
    old = tmp_path / "old.mcap"
    logged_lockstep_run(old, duration=0.1, encoding="json")
    taken = tmp_path / "taken.mcap"
    taken.write_bytes(b"mine")
    before = source.read_bytes()
    cases = [(["log", "convert", str(source), "--layout", "topics"], "already in the topics layout"),
             (["log", "convert", str(source), "--layout", "cycle", "-o", str(taken)], "exists"),
             (["log", "convert", str(old), "--layout", "cycle"], "holds protobuf messages")]
    for argv, what in cases:
        capsys.readouterr()
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len([line for line in err if "error" in line]) == 1 and what in err[-1], err
    assert source.read_bytes() == before and taken.read_bytes() == b"mine"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old.mcap", "run.mcap", "taken.mcap"]
