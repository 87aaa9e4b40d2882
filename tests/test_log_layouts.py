"""tools/log_layouts.py: the bytes per cycle of one log in three MCAP layouts, checked
against what MCAP's format says each message costs, not against the tool's own figures."""

from __future__ import annotations

from pathlib import Path

import pytest
from tool_module import load_tool

from dobhil.recording.reader import open_log
from tests.recording.test_run_logging import lockstep_log_in

layouts = load_tool(Path(__file__).resolve().parents[1] / "tools" / "log_layouts.py", "log_layouts_under_test")

#: a Message Index entry (mcap.dev/spec, op 0x07): log time u64 + offset u64
INDEX_ENTRY = 16


@pytest.fixture(scope="module")
def run_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return lockstep_log_in(tmp_path_factory, "layouts", 0.2)


def test_fewer_messages_per_cycle_save_their_index_entries(run_log: Path) -> None:
    path = run_log
    with open_log(path) as log:
        counts = {c.topic: c.message_count for c in log.channels()}
    figures = layouts.layouts(path)
    cycles = figures["cycles"]
    assert cycles == counts["/loop"] == 200
    frames = counts["/can/rx"] + counts["/can/tx"]
    per_cycle = sum(counts.values()) / cycles
    assert per_cycle > 7   # five signal topics, a frame each way, and events
    # merging the signals drops (messages - frames - one per cycle) index entries; folding the
    # frames in drops theirs too: each layout at least that many bytes smaller than the one
    # before (the compressed chunks shrink as well: fewer record headers)
    signals = sum(counts.values()) - frames
    assert figures["per_topic"] - figures["signals_merged"] >= INDEX_ENTRY * (signals - cycles) / cycles
    assert figures["signals_merged"] - figures["all_merged"] >= INDEX_ENTRY * frames / cycles
    # the rewrite leaves out what the writer adds besides messages (the schemas' descriptors,
    # metadata, attachments): never larger than the log itself
    assert figures["per_topic"] < figures["recorded"]


def test_the_command_line_prints_each_layout(run_log: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert layouts.main([str(run_log)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith(f"{run_log}: 200 cycles")
    assert [line.split()[0] for line in lines[1:]] == list(layouts.LAYOUTS)
