"""The topic table: valid JSON schemas, one per topic, and the compact encoder."""

from __future__ import annotations

import json
import math
from pathlib import Path

import jsonschema
import numpy as np
import pytest

from dobhil.errors import LogFileError
from dobhil.recording.schemas import SPECS_BY_NAME, TOPIC_SPECS, EventKind, Topic, decode, encode, spec_for

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
    payload = {"torque": 1.5}
    assert encode(payload) == b'{"torque":1.5}'
    assert decode(encode(payload)) == payload


def test_non_finite_numbers_become_null() -> None:
    out = decode(encode({"q": math.nan, "dq": math.inf, "tau_motor": 1.0, "tau_int": [1.0, -math.inf]}))
    assert out == {"q": None, "dq": None, "tau_motor": 1.0, "tau_int": [1.0, None]}


def test_numpy_scalars_are_plain_numbers() -> None:
    out = decode(encode({"cycle": np.int64(3), "overrun": np.bool_(True), "exec_time": np.float32(0.5)}))
    assert out == {"cycle": 3, "overrun": True, "exec_time": 0.5}


def test_from_values_uses_field_order() -> None:
    spec = spec_for("/loop")
    assert spec.from_values((1, 0.0, 1e-4, False)) == {
        "cycle": 1, "period_error": 0.0, "exec_time": 1e-4, "overrun": False,
    }
    with pytest.raises(LogFileError, match="expected 4 values"):
        spec.from_values((1,))


def test_unknown_topic_is_one_line_error() -> None:
    with pytest.raises(LogFileError, match="unknown topic '/nope'"):
        spec_for("/nope")


def test_docs_list_every_topic_and_field() -> None:
    doc = (Path(__file__).resolve().parents[2] / "docs" / "recording.md").read_text()
    for spec in TOPIC_SPECS.values():
        assert f"`{spec.name}` — `{spec.schema_name}`" in doc
        for f in spec.fields:
            assert f"| `{f.name}` |" in doc
