"""The protobuf reader's fast path (``_fast``: the writer's own layout read with one unpack, no
loop per field) and its rows (``row_unpacker``), checked against literal bytes and against the
``protobuf`` library, with the fast path called on its own: the generic path reads every
message too, so a test of the decoder alone would pass with a fast path that never answers."""

from __future__ import annotations

import math
import struct
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dobhil.recording.encodings import encoding
from dobhil.recording.encodings.protobuf import _fast, _whole, packer, row_unpacker, unpacker
from dobhil.recording.schemas import TOPIC_SPECS, FieldKind, Topic, TopicSpec
from tests.recording.test_protobuf import _fields, message_class

CAN = TOPIC_SPECS[Topic.CAN_RX]
LOOP = TOPIC_SPECS[Topic.LOOP]
#: test_protobuf's literal /can/tx message: id 0x69, extended, dlc 2, data 01 ff, stamp 1.5, tx, no channel
FRAME = bytes.fromhex("09" "000000000000f83f" "11" "6900000000000000" "1801" "2000" "2800" "3000" "3800"
                      "4000" "49" "0200000000000000" "52" "02" "01ff" "5a" "04" "3031" "6666" "62" "02" "7478"
                      "6a" "00")
FRAME_PAYLOAD = {"timestamp": 1.5, "arbitration_id": 0x69, "is_extended_id": True, "is_remote_frame": False,
                 "is_error_frame": False, "is_fd": False, "bitrate_switch": False, "error_state_indicator": False,
                 "dlc": 2, "data": [1, 255], "data_hex": "01ff", "direction": "tx", "channel": ""}


def test_the_writers_frame_is_read_by_the_fast_path() -> None:
    payload = _fast(CAN)(FRAME)
    assert payload == FRAME_PAYLOAD and list(payload) == list(CAN.keys)
    assert row_unpacker(CAN, ("data", "dlc", "direction", "timestamp"))(FRAME) == (b"\x01\xff", 2, "tx", 1.5)


def test_non_finite_numbers_read_as_none_on_the_fast_path() -> None:
    spec = TOPIC_SPECS[Topic.CONTROLLER]
    data = packer(spec)((0.2, math.nan, math.inf, -math.inf, 0.0, 1e308, 7))
    assert _fast(spec)(data) == {"tau_ref": 0.2, "tau_int_hat": None, "tau_dis_hat": None, "tau_per": None,
                                 "u_unsat": 0.0, "u_sat": 1e308, "cycle": 7}
    assert row_unpacker(spec, ("cycle", "tau_dis_hat", "u_sat"))(data) == (7, None, 1e308)
    big = packer(spec)((1e308, 1e308, 0.0, 0.0, 0.0, 0.0, 1))   # finite numbers whose sum is not
    assert _fast(spec)(big) == {"tau_ref": 1e308, "tau_int_hat": 1e308, "tau_dis_hat": 0.0, "tau_per": 0.0,
                                "u_unsat": 0.0, "u_sat": 0.0, "cycle": 1}


def test_a_field_repeated_after_the_layout_is_not_the_fast_paths() -> None:
    """Protobuf takes the last of a repeated scalar field: a message of the writer's layout
    with ``direction`` (field 12) again at its end reads "rx", the second."""
    data = FRAME + bytes.fromhex("62" "02" "7278")
    assert _fast(CAN)(data) is None
    assert unpacker(CAN)(data) == {**FRAME_PAYLOAD, "direction": "rx"}
    assert row_unpacker(CAN, ("direction",))(data) == ("rx",)


def test_the_same_fields_in_another_order_are_not_the_fast_paths() -> None:
    """A /controller message of the writer's length, its first two fields swapped (protobuf
    takes fields in any order)."""
    spec = TOPIC_SPECS[Topic.CONTROLLER]
    written = packer(spec)((0.25, 0.5, 0.0, 0.0, 0.0, 0.0, 9))
    swapped = written[9:18] + written[:9] + written[18:]
    assert _fast(spec)(swapped) is None
    assert unpacker(spec)(swapped) == unpacker(spec)(written) == _fast(spec)(written)
    assert unpacker(spec)(written)["tau_int_hat"] == 0.5


def test_a_flag_written_as_a_longer_varint_is_not_read_as_one_byte() -> None:
    """A valid /loop message whose ``overrun`` is the two-byte varint 80 29 lines up with the
    writer's tags: read byte by byte, the bytes after it would be ``sample_latency``'s double;
    it is a float32 (wire type 5) and an unknown field 6."""
    head = (bytes.fromhex("09") + struct.pack("<q", 3) + bytes.fromhex("11") + struct.pack("<d", 1e-6)
            + bytes.fromhex("19") + struct.pack("<d", 2e-5))
    data = head + bytes.fromhex("20" "80" "29" "2d") + struct.pack("<f", 0.5) + bytes.fromhex("30" "80" "00")
    assert len(data) == len(packer(LOOP)((3, 1e-6, 2e-5, True, 0.5)))   # the writer's length, its tags in place
    assert _fast(LOOP)(data) is None
    assert unpacker(LOOP)(data) == {"cycle": 3, "period_error": 1e-6, "exec_time": 2e-5, "overrun": True,
                                    "sample_latency": 0.5}


def test_a_length_of_two_bytes_is_not_the_fast_paths() -> None:
    """A channel name of 200 bytes: the writer's own message, its length a two-byte varint."""
    values = (1.5, 0x69, True, False, False, False, False, False, 2, b"\x01\xff", "01ff", "tx", "c" * 200)
    data = packer(CAN)(values)
    assert _fast(CAN)(data) is None
    assert unpacker(CAN)(data)["channel"] == "c" * 200


def test_a_cut_message_is_not_the_fast_paths() -> None:
    for cut in range(len(FRAME)):
        assert _fast(CAN)(FRAME[:cut]) is None, cut


def test_the_whole_tail_memo_forgets_past_its_limit_and_reads_alike() -> None:
    seen: list[int] = []

    def by_field(data: bytes) -> tuple[Any, ...]:
        seen.append(len(data))
        return (data[2:].decode(),)
    read = _whole(by_field, 2, limit=2)
    assert [read(b"xxa"), read(b"xxb"), read(b"yya"), read(b"xxc"), read(b"xxa")] == [("a",), ("b",), ("a",),
                                                                                     ("c",), ("a",)]
    assert seen == [3, 3, 3, 3]   # "a" again found, then forgotten with the third distinct tail


def _expected(spec: TopicSpec, fields: tuple[Any, ...]) -> dict[str, Any]:
    """The payload dict of ``fields``, parsed by the protobuf library from dobhil's bytes."""
    parsed = message_class(spec).FromString(packer(spec)(fields))
    out: dict[str, Any] = {}
    for f in spec.fields:
        value = getattr(parsed, f.name)
        out[f.name] = (None if f.kind == FieldKind.NUMBER and not math.isfinite(value) else
                       list(value) if f.kind == FieldKind.BYTES else value)
    return out


def _short(spec: TopicSpec, fields: tuple[Any, ...]) -> bool:
    """Every length-delimited field shorter than 128 bytes (a one-byte length)."""
    return all(len(v.encode() if isinstance(v, str) else v) < 128
               for f, v in zip(spec.fields, fields) if f.kind in (FieldKind.STRING, FieldKind.BYTES))


@pytest.mark.parametrize("topic", list(TOPIC_SPECS), ids=lambda t: t.name.lower())
@settings(max_examples=80, deadline=None)
@given(data=st.data())
def test_the_fast_path_reads_what_the_protobuf_library_reads(topic: Topic, data: st.DataObject) -> None:
    """Any values, the writer's bytes: the fast path gives the library's values (a length of
    two bytes: it declines, the generic path reads it); rows of any fields too, bytes as
    bytes; the library's canonical bytes (defaults left out) are declined or read alike."""
    spec = TOPIC_SPECS[topic]
    fields = data.draw(_fields(spec))
    written, expect = packer(spec)(fields), _expected(spec, fields)
    fast = _fast(spec)(written)
    assert fast == expect if _short(spec, fields) else fast is None
    names = data.draw(st.lists(st.sampled_from(spec.keys), unique=True, min_size=1))
    row = tuple(bytes(expect[n]) if isinstance(expect[n], list) else expect[n] for n in names)
    assert row_unpacker(spec, names)(written) == row
    canonical = message_class(spec).FromString(written).SerializeToString()
    assert _fast(spec)(canonical) in (None, expect)
    assert row_unpacker(spec, names)(canonical) == row


def test_the_json_rows_take_defaults_for_an_older_logs_missing_fields() -> None:
    json_rows = encoding("json").row_decoder(CAN, ("dlc", "data", "channel"), {"channel": None})
    assert json_rows(b'{"dlc": 2, "data": [1, 255], "channel": "can0"}') == (2, b"\x01\xff", "can0")
    assert json_rows(b'{"dlc": 2, "data": [1, 255]}') == (2, b"\x01\xff", None)
    with pytest.raises(KeyError):
        json_rows(b'{"data": [1, 255]}')
