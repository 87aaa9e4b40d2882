"""Logs of dobhil's earlier schema stay readable: ``/drive/feedback`` with a numeric
``axis_state`` (its old schema) and ``/can/tx`` frames with bus timestamp 0.0."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.writer import Writer

from dobhil.canio.canlog import CanLogFormat, export_can
from dobhil.cli.main import main
from dobhil.recording.reader import open_log
from tests.recording.test_run_logging import logged_lockstep_run

_OLD_FEEDBACK_SCHEMA = {
    "$schema": "https://json-schema.org/draft/2020-12/schema", "title": "dobhil.DriveFeedback",
    "description": "drive feedback decoded from the bus", "type": "object",
    "properties": {k: {"type": t} for k, t in (("position", ["number", "null"]), ("velocity", ["number", "null"]),
                                               ("axis_state", "integer"), ("axis_error", "integer"),
                                               ("seq", "integer"), ("cycle", "integer"))},
    "required": ["position", "velocity", "axis_state", "axis_error", "seq", "cycle"],
}
_CODES = {"disabled": 0, "enabled": 1, "fault": 2}


def as_old_log(src: Path, dst: Path) -> None:
    """``src`` as the writer before the fix wrote it (same library string, old schema, tx 0.0)."""
    with open(src, "rb") as f_in, open(dst, "wb") as f_out:
        reader = make_reader(f_in)
        summary, header = reader.get_summary(), reader.get_header()
        assert summary is not None
        writer = Writer(f_out)
        writer.start(profile=header.profile, library=header.library)
        schemas = {sid: writer.register_schema(s.name, s.encoding, json.dumps(_OLD_FEEDBACK_SCHEMA).encode()
                                               if s.name == "dobhil.DriveFeedback" else s.data)
                   for sid, s in summary.schemas.items()}
        channels = {cid: writer.register_channel(c.topic, c.message_encoding, schemas[c.schema_id])
                    for cid, c in summary.channels.items()}
        for record in reader.iter_metadata():
            writer.add_metadata(record.name, record.metadata)
        for attachment in reader.iter_attachments():
            writer.add_attachment(attachment.create_time, attachment.log_time, attachment.name,
                                  attachment.media_type, attachment.data)
        for _, channel, message in reader.iter_messages(log_time_order=False):
            p = json.loads(message.data)
            if channel.topic == "/drive/feedback":
                p = {"position": p["position"], "velocity": p["velocity"], "axis_state": _CODES[p["drive_state"]],
                     "axis_error": p["axis_error"], "seq": p["seq"], "cycle": p["cycle"]}
            elif channel.topic == "/can/tx":
                p["timestamp"] = 0.0
            writer.add_message(channels[channel.id], message.log_time, json.dumps(p).encode(), message.publish_time)
        writer.finish()


@pytest.fixture(scope="module")
def old_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("old")
    logged_lockstep_run(folder / "new.mcap", duration=0.2)
    as_old_log(folder / "new.mcap", folder / "old.mcap")
    return folder / "old.mcap"


def test_the_old_log_is_old(old_log: Path) -> None:
    with open_log(old_log) as log:
        feedback = [p for _, _, p in log.iter_messages(["/drive/feedback"])]
        tx = [p for _, _, p in log.iter_messages(["/can/tx"])]
    assert feedback and all("axis_state" in p and "drive_state" not in p for p in feedback)
    assert tx and all(p["timestamp"] == 0.0 for p in tx)


def test_replay_report_and_export_read_an_old_log(old_log: Path, tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["replay", str(old_log), "--verify"]) == 0
    assert main(["report", str(old_log), "--out", str(tmp_path / "report"), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out.splitlines()[-1])
    assert summary["cycles"] == 200
    assert export_can(old_log, tmp_path / "old.asc", CanLogFormat.ASC) > 0  # tx 0.0: the log time is used
