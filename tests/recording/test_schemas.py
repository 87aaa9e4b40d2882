"""The topic table: valid JSON schemas, one per topic, and the compact encoder."""

from __future__ import annotations

import json
import math
from pathlib import Path
from types import SimpleNamespace

import jsonschema
import numpy as np
import pytest

from dobhil.errors import LogFileError
from dobhil.recording.schemas import (
    CYCLE,
    SPECS_BY_NAME,
    TOPIC_SPECS,
    EventKind,
    Topic,
    can_frame_message,
    can_frame_payload,
    can_frame_record,
    decode,
    message_count,
    spec_for,
)

EXPECTED_TOPICS = {
    "/can/rx", "/can/tx", "/drive/feedback", "/drive/command",
    "/controller", "/loop", "/emulator/truth", "/events",
}


def test_every_topic_enum_has_one_spec() -> None:
    assert set(TOPIC_SPECS) == set(Topic)
    assert set(SPECS_BY_NAME) == EXPECTED_TOPICS


@pytest.mark.parametrize("topic", list(Topic), ids=lambda t: t.name)
def test_schema_is_valid_json_schema_object(topic: Topic) -> None:
    spec = TOPIC_SPECS[topic]
    schema = json.loads(spec.schema_bytes())
    jsonschema.Draft202012Validator.check_schema(schema)
    assert schema["title"] == spec.schema_name
    assert schema["type"] == "object"
    assert tuple(schema["properties"]) == spec.keys


def test_required_fields_of_the_brief() -> None:
    assert {"tau_ref", "tau_int_hat", "tau_dis_hat", "tau_per", "u_unsat", "u_sat", "cycle"} <= set(
        spec_for("/controller").keys
    )
    assert {"timestamp", "arbitration_id", "data", "data_hex", "direction", "channel"} <= set(spec_for("/can/rx").keys)
    kinds = json.loads(spec_for(Topic.EVENTS).schema_bytes())["properties"]["kind"]["enum"]
    assert kinds == ["enable", "disable", "stop", "fault", "watchdog", "loss", "info"]
    assert len(kinds) == len(EventKind)


def test_encode_is_compact_and_round_trips() -> None:
    spec = spec_for("/drive/command")
    assert spec.encode((1.5,)) == b'{"torque":1.5}'
    assert decode(spec.encode((1.5,))) == {"torque": 1.5}


def test_non_finite_numbers_become_null() -> None:
    out = decode(spec_for(Topic.EMULATOR_TRUTH).encode((math.nan, math.inf, 1.0, -math.inf)))
    assert out == {"q": None, "dq": None, "tau_motor": 1.0, "tau_int": None}


def test_numpy_scalars_are_plain_numbers() -> None:
    out = decode(spec_for("/loop").encode((np.int64(3), np.float32(0.5), np.float64(1e-4), np.bool_(True),
                                           np.float64(2.5e-4))))
    assert out == {"cycle": 3, "period_error": 0.5, "exec_time": 1e-4, "overrun": True, "sample_latency": 2.5e-4}


def test_a_cycle_record_becomes_one_message_per_cycle_topic(tmp_path: Path) -> None:
    """Through the one writer: the messages a cycle record becomes, with and without truth."""
    from dobhil.recording.reader import open_log
    from dobhil.recording.writer import LogWriter

    def written(record: tuple[object, ...]) -> dict[str, dict[str, object]]:
        path = tmp_path / f"{len(record)}.mcap"
        log = LogWriter(open(path, "wb"), metadata={}, fsync=False)
        log.write([record])
        log.finish(None)
        return {topic: payload for topic, _, payload in open_log(path).iter_messages()}

    record = (CYCLE, 7, 3, 0.1, 0.2, 4, 1.0, 0.9, 0.01, 0.5, 0.6, 0.55, 1e-6, 2e-5, False, 3e-4, 1, 8, 0)
    out = written(record)
    assert set(out) == {"/drive/feedback", "/controller", "/drive/command", "/loop"}
    assert out["/drive/feedback"] == {"position": 0.1, "velocity": 0.2, "drive_state": "enabled",
                                      "protocol_state": 8, "protocol_state_name": "8", "protocol_error": 0,
                                      "protocol_error_text": "none", "seq": 4, "cycle": 3}
    assert out["/drive/command"] == {"torque": 0.55} and out["/controller"]["u_unsat"] == 0.6
    assert out["/loop"] == {"cycle": 3, "period_error": 1e-6, "exec_time": 2e-5, "overrun": False,
                            "sample_latency": 3e-4}
    assert written((*record[:15], math.nan, *record[16:]))["/loop"]["sample_latency"] is None
    assert message_count(record) == 4 and message_count((*record, 1.0, 2.0, 3.0, 4.0)) == 5
    truth = written((*record, 1.0, 2.0, 3.0, 4.0))["/emulator/truth"]
    assert truth == {"q": 1.0, "dq": 2.0, "tau_motor": 3.0, "tau_int": 4.0}


def test_can_frame_record_payload_and_message_round_trip() -> None:
    import can
    msg = can.Message(timestamp=12.5, arbitration_id=0x1ABCDEF, is_extended_id=True, data=b"\x01\xff",
                      channel="vcan0")
    record = can_frame_record(msg, Topic.CAN_TX, 99)
    assert record[:2] == (int(Topic.CAN_TX), 99)
    payload = can_frame_payload(record[2:], Topic.CAN_TX)
    assert payload["data"] == [1, 255] and payload["data_hex"] == "01ff" and payload["direction"] == "tx"
    assert payload == decode(TOPIC_SPECS[Topic.CAN_TX].encode(record[2:]))
    back = can_frame_message(payload, 99)
    assert back.equals(msg, timestamp_delta=None, check_direction=False) and not back.is_rx


def test_unknown_topic_is_one_line_error() -> None:
    with pytest.raises(LogFileError, match="unknown topic '/nope'"):
        spec_for("/nope")


def test_docs_list_every_topic_and_field() -> None:
    doc = (Path(__file__).resolve().parents[2] / "docs" / "recording.md").read_text()
    for spec in TOPIC_SPECS.values():
        assert f"`{spec.name}` — `{spec.schema_name}`" in doc
        for f in spec.fields:
            assert f"| `{f.name}` |" in doc


def test_the_loops_frame_record_is_the_tables() -> None:
    """:meth:`RunLog.frame` spells :func:`can_frame_record` out for speed: both give the same
    record for every flag alone and all together, received (data kept) and sent (copied)."""
    import can

    from dobhil.recording.packed import unpacked
    from dobhil.recording.runlog import RunLog
    from dobhil.recording.schemas import FRAME_ATTRIBUTES
    flags = [a for a in FRAME_ATTRIBUTES if a.startswith(("is_", "bitrate", "error"))]
    assert len(flags) == 6
    batch = RunLog(SimpleNamespace(opened=False))  # type: ignore[arg-type]
    batch.clock_ns = lambda: 7
    for on in [[f] for f in flags] + [flags]:
        msg = can.Message(arbitration_id=0x1F, data=b"\x01\x02", channel="can1", timestamp=2.5, check=False)
        for name in on:
            setattr(msg, name, True)
        for topic in (Topic.CAN_RX, Topic.CAN_TX):
            batch.frame(int(topic), msg)
            want = can_frame_record(msg, topic, 7)
            if topic == Topic.CAN_TX:  # a sent frame is stamped with its send time on the log clock
                want = (*want[:-2], 7 / 1e9, want[-1])
            assert [unpacked(r) for r in batch.take()] == [want]  # packed on the loop thread


def test_drive_state_is_recorded_by_name_not_as_a_code_a_drive_uses_otherwise() -> None:
    """``/drive/feedback`` names dobhil's DriveState: its code (1 = enabled) would read as
    ODrive's (1 = IDLE) in Foxglove."""
    from dobhil.drives.base import DriveState
    from dobhil.recording.schemas import DRIVE_STATE_NAMES, drive_state_name
    assert DRIVE_STATE_NAMES == tuple(s.name.lower() for s in sorted(DriveState))
    assert [drive_state_name(int(s)) for s in DriveState] == ["disabled", "enabled", "fault"]
    assert drive_state_name(7) == "code 7"
    spec = spec_for("/drive/feedback")
    assert "axis_state" not in spec.keys and spec.json_schema()["properties"]["drive_state"]["type"] == "string"
    import numpy as np  # the loop hands numpy values over as they are (the default encoder takes them too)
    payload = spec.encode((np.float64(0.5), np.float64(-1.25), np.int64(2), np.int64(-1), np.int64(0), np.int64(7), -1))
    assert json.loads(payload) == {"position": 0.5, "velocity": -1.25, "drive_state": "fault", "protocol_state": -1,
                                   "protocol_state_name": "not reported", "protocol_error": 0,
                                   "protocol_error_text": "none", "seq": 7, "cycle": -1}
