"""The hand-written chunk reader returns exactly what the mcap package's reader returns."""

from __future__ import annotations

from pathlib import Path

from mcap.reader import make_reader

from dobhil.cli.main import main
from dobhil.recording.fastread import iter_payloads


def test_fast_reader_equals_mcap_reader(tmp_path: Path) -> None:
    log = tmp_path / "run.mcap"
    assert main(["run", "configs/demo.yaml", "--emulate", "--lockstep", "--duration", "0.3",
                 "--log", str(log)]) == 0
    topics = ("/can/rx", "/drive/feedback", "/controller")
    with log.open("rb") as f:
        reader = make_reader(f)
        expected = [(c.topic, m.log_time, m.data)
                    for _, c, m in reader.iter_messages(topics=list(topics), log_time_order=False)]
        fast = list(iter_payloads(f, reader.get_summary(), topics))
    assert len(expected) > 900
    assert fast == expected
