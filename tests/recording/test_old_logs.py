"""Logs of earlier dobhil versions stay readable: ``/drive/feedback`` with a numeric
``axis_state`` and ``axis_error`` (the first schema) or ``drive_state`` by name and
``axis_error`` (the second, before the drive's own codes were recorded as ``protocol_state``
and ``protocol_error``), and ``/can/tx`` frames with bus timestamp 0.0."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.writer import Writer

from dobhil.canio.canlog import CanLogFormat, export_can
from dobhil.cli.main import main
from dobhil.recording.reader import open_log
from dobhil.recording.schemas import SPECS_BY_SCHEMA
from dobhil.run_report import report, summary_text
from tests.recording.helpers import decode_message
from tests.recording.test_run_logging import logged_lockstep_run

#: /drive/feedback's properties (JSON types) in each earlier version
_OLD_FIELDS = {
    "numeric_state": (("position", ["number", "null"]), ("velocity", ["number", "null"]), ("axis_state", "integer"),
                      ("axis_error", "integer"), ("seq", "integer"), ("cycle", "integer")),
    "axis_error": (("position", ["number", "null"]), ("velocity", ["number", "null"]), ("drive_state", "string"),
                   ("axis_error", "integer"), ("seq", "integer"), ("cycle", "integer")),
}
_CODES = {"disabled": 0, "enabled": 1, "fault": 2}


def _old_schema(version: str) -> dict[str, object]:
    fields = _OLD_FIELDS[version]
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": "dobhil.DriveFeedback",
            "description": "drive feedback decoded from the bus", "type": "object",
            "properties": {k: {"type": t} for k, t in fields}, "required": [k for k, _ in fields]}


def _old_feedback(p: dict[str, object], version: str) -> dict[str, object]:
    state = _CODES[str(p["drive_state"])] if version == "numeric_state" else p["drive_state"]
    return {"position": p["position"], "velocity": p["velocity"],
            "axis_state" if version == "numeric_state" else "drive_state": state,
            "axis_error": p["protocol_error"], "seq": p["seq"], "cycle": p["cycle"]}


def as_old_log(src: Path, dst: Path, version: str = "numeric_state") -> None:
    """``src`` as an earlier writer wrote it (same library string, that version's
    ``/drive/feedback`` schema, tx 0.0)."""
    with open(src, "rb") as f_in, open(dst, "wb") as f_out:
        reader = make_reader(f_in)
        summary, header = reader.get_summary(), reader.get_header()
        assert summary is not None
        writer = Writer(f_out)
        writer.start(profile=header.profile, library=header.library)
        # every channel JSON with a JSON schema, as those versions wrote them
        schemas = {sid: writer.register_schema(s.name, "jsonschema", json.dumps(_old_schema(version)).encode()
                                               if s.name == "dobhil.DriveFeedback"
                                               else SPECS_BY_SCHEMA[s.name].schema_bytes())
                   for sid, s in summary.schemas.items()}
        channels = {cid: writer.register_channel(c.topic, "json", schemas[c.schema_id])
                    for cid, c in summary.channels.items()}
        for record in reader.iter_metadata():
            writer.add_metadata(record.name, record.metadata)
        for attachment in reader.iter_attachments():
            writer.add_attachment(attachment.create_time, attachment.log_time, attachment.name,
                                  attachment.media_type, attachment.data)
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            p = decode_message(schema, channel, message.data)
            if channel.topic == "/drive/feedback":
                p = _old_feedback(p, version)
            elif channel.topic == "/can/tx":
                p["timestamp"] = 0.0
            writer.add_message(channels[channel.id], message.log_time, json.dumps(p).encode(), message.publish_time)
        writer.finish()


@pytest.fixture(scope="module")
def new_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("new") / "new.mcap"
    logged_lockstep_run(path, duration=0.2)
    return path


@pytest.fixture(scope="module", params=sorted(_OLD_FIELDS))
def old_log(request: pytest.FixtureRequest, new_log: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("old") / f"{request.param}.mcap"
    as_old_log(new_log, path, request.param)
    return path


def test_the_old_log_is_old(old_log: Path) -> None:
    version = old_log.stem
    with open_log(old_log) as log:
        feedback = [p for _, _, p in log.iter_messages(["/drive/feedback"])]
        tx = [p for _, _, p in log.iter_messages(["/can/tx"])]
    assert feedback and all(set(p) == {k for k, _ in _OLD_FIELDS[version]} for p in feedback)
    assert tx and all(p["timestamp"] == 0.0 for p in tx)


def test_replay_report_and_export_read_an_old_log(old_log: Path, tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["replay", str(old_log), "--verify"]) == 0
    assert main(["report", str(old_log), "--out", str(tmp_path / "report"), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out.splitlines()[-1])
    assert summary["cycles"] == 200
    # the drive's codes named by the recorded profile's protocol; its state was not recorded
    assert summary["drive_states"] == [{"time_s": 0.0, "cycle": -1, "drive_state": "enabled", "protocol_state": -1,
                                        "protocol_state_name": "not reported", "protocol_error": 0,
                                        "protocol_error_text": "0x00000000 (none)"}]
    assert export_can(old_log, tmp_path / "old.asc", CanLogFormat.ASC) > 0  # tx 0.0: the log time is used


def test_the_new_log_names_the_drives_codes_and_the_report_lists_them(new_log: Path) -> None:
    """Today's ``/drive/feedback``: dobhil's state, the drive's own codes and their names
    from the protocol (an ODrive in closed loop, no error), and the report's state lines
    (the summary text ``dobhil report`` prints; its figures, the command's costliest part,
    drawn from old logs above and from new ones in tests/recording/test_report.py)."""
    with open_log(new_log) as log:
        feedback = [p for _, _, p in log.iter_messages(["/drive/feedback"])]
    assert {(p["drive_state"], p["protocol_state"], p["protocol_state_name"], p["protocol_error"],
             p["protocol_error_text"]) for p in feedback} == {
        ("enabled", 8, "CLOSED_LOOP_CONTROL", 0, "0x00000000 (none)")}
    out = summary_text(report(new_log)[1])
    assert ("drive state at 0.000 s (cycle -1): enabled; the drive's state 8 (CLOSED_LOOP_CONTROL), "
            "error 0x00000000 (none)") in out
