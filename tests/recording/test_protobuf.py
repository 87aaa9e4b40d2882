"""The protobuf encoding (dobhil.recording.encodings.protobuf), checked against literal bytes
and against independent readers: the ``protobuf`` library parsing the messages with the
shipped FileDescriptorSet, and ``mcap`` with ``mcap-protobuf-support``'s decoder (Foxglove's
route) decoding a recorded run's every topic without dobhil in the decode path."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from dobhil.cli.main import main
from dobhil.recording.encodings import ENCODINGS, encoding
from dobhil.recording.encodings.protobuf import fields_on_wire, varint
from dobhil.recording.reader import open_log
from dobhil.recording.schemas import TOPIC_SPECS, FieldKind, Topic, TopicSpec
from tests.recording.test_run_logging import lockstep_log_in, logged_lockstep_run

PB = encoding("protobuf")
_TYPES = {FieldKind.NUMBER: descriptor_pb2.FieldDescriptorProto.TYPE_DOUBLE,
          FieldKind.INTEGER: descriptor_pb2.FieldDescriptorProto.TYPE_SFIXED64,
          FieldKind.BOOLEAN: descriptor_pb2.FieldDescriptorProto.TYPE_BOOL,
          FieldKind.STRING: descriptor_pb2.FieldDescriptorProto.TYPE_STRING,
          FieldKind.BYTES: descriptor_pb2.FieldDescriptorProto.TYPE_BYTES}


def message_class(spec: TopicSpec) -> Any:
    """The protobuf library's class of a topic, from the schema dobhil writes."""
    pool = descriptor_pool.DescriptorPool()
    for file in descriptor_pb2.FileDescriptorSet.FromString(PB.schema(spec)).file:
        pool.Add(file)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(spec.schema_name))


def test_controller_message_is_these_bytes() -> None:
    """Tag (field << 3 | wire type 1), then the little-endian double or int64."""
    data = PB.encoder(TOPIC_SPECS[Topic.CONTROLLER], None)((0.2, 0.19, 0.01, 0.02, math.nan, 0.03, 1234))
    assert data.hex() == ("09" "9a9999999999c93f" "11" "52b81e85eb51c83f" "19" "7b14ae47e17a843f"
                          "21" "7b14ae47e17a943f" "29" "000000000000f87f" "31" "b81e85eb51b89e3f"
                          "39" "d204000000000000")


def test_can_frame_message_is_these_bytes() -> None:
    """Fixed-width fields first (bools as one-byte varints), then the length-delimited ones."""
    values = (0x69, True, False, False, False, False, False, 2, b"\x01\xff", 1.5, None)
    data = PB.encoder(TOPIC_SPECS[Topic.CAN_TX], None)(values)
    assert data.hex() == ("09" "000000000000f83f" "11" "6900000000000000" "1801" "2000" "2800" "3000" "3800"
                          "4000" "49" "0200000000000000" "52" "02" "01ff" "5a" "04" "3031" "6666"
                          "62" "02" "7478" "6a" "00")


_FLAG = st.one_of(st.booleans(), st.integers(-2, 2), st.none(), st.sampled_from(["", "x", b"", (0,)]))
_DATA = st.one_of(st.binary(max_size=200), st.binary(max_size=64).map(bytearray))
_CHANNEL = st.one_of(st.none(), st.integers(-3, 3), st.sampled_from([True, False, 1.0, "", "vcan0", "can1", b"x"]),
                     st.text(max_size=20), st.just([1, 2]))


@pytest.mark.parametrize("topic", [Topic.CAN_RX, Topic.CAN_TX], ids=lambda t: t.name.lower())
@settings(max_examples=200, deadline=None)
@given(records=st.lists(st.tuples(st.integers(0, 2 ** 29 - 1), _FLAG, _FLAG, _FLAG, _FLAG, _FLAG, _FLAG,
                                  st.integers(0, 64), _DATA,
                                  st.one_of(st.none(), st.floats(allow_nan=True), st.just(0.0)), _CHANNEL),
                        min_size=1, max_size=8))
def test_the_frame_encoder_writes_what_the_generic_path_writes(topic: Topic, records: list[tuple[Any, ...]]) -> None:
    """frame_packer's one step is byte for byte the table's fields packed field by field,
    whatever the flags' types (truthiness), the data's type and the channel (one encoder over
    several frames: its per-channel fields must follow the channel, 1 and True and 1.0 apart)."""
    from dobhil.recording.encodings.protobuf import frame_packer, packer
    from dobhil.recording.schemas import can_frame_fields
    spec = TOPIC_SPECS[topic]
    fast, slow, fields = frame_packer(spec), packer(spec), can_frame_fields(topic)
    assert fast is not None and PB.encoder(spec, None) is not None
    for values in records:
        assert fast(values) == slow(fields(values)), values


def test_the_schema_is_a_file_descriptor_set_foxglove_takes() -> None:
    """Foxglove and mcap-protobuf-support look the schema's name up as a message's full
    name in the FileDescriptorSet; the fields are the table's, numbered from 1, and the
    bytes are what the protobuf library serializes for the same descriptor."""
    for spec in TOPIC_SPECS.values():
        data = PB.schema(spec)
        fds = descriptor_pb2.FileDescriptorSet.FromString(data)
        (file,) = fds.file
        assert (file.package, file.syntax) == ("dobhil", "proto3")
        (message,) = file.message_type
        assert f"{file.package}.{message.name}" == spec.schema_name
        assert [(f.name, f.number, f.type) for f in message.field] == [
            (f.name, i, _TYPES[f.kind]) for i, f in enumerate(spec.fields, 1)]
        expected = descriptor_pb2.FileDescriptorSet()
        built = expected.file.add(name=file.name, package="dobhil", syntax="proto3")
        m = built.message_type.add(name=message.name)
        for i, f in enumerate(spec.fields, 1):
            m.field.add(name=f.name, number=i, label=descriptor_pb2.FieldDescriptorProto.LABEL_OPTIONAL,
                        type=_TYPES[f.kind])
        assert expected.SerializeToString() == data
        assert PB.schema_fields(data, spec.schema_name) == spec.keys


_VALUES = {FieldKind.NUMBER: st.floats(allow_nan=True, allow_infinity=True),
           FieldKind.INTEGER: st.integers(-(2 ** 63), 2 ** 63 - 1), FieldKind.BOOLEAN: st.booleans(),
           FieldKind.STRING: st.text(max_size=200), FieldKind.BYTES: st.binary(max_size=200)}


def _fields(spec: TopicSpec) -> st.SearchStrategy[tuple[Any, ...]]:
    return st.tuples(*(_VALUES[f.kind] for f in spec.fields))


def _same(a: Any, b: Any) -> bool:
    return a == b or (isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b))


@pytest.mark.parametrize("topic", list(TOPIC_SPECS), ids=lambda t: t.name.lower())
@settings(max_examples=60, deadline=None)
@given(data=st.data())
def test_the_protobuf_library_reads_what_dobhil_writes_and_back(topic: Topic, data: st.DataObject) -> None:
    """Every topic's fields, any values: the library parses dobhil's bytes to the same values
    (NaN and infinity kept); dobhil reads the library's canonical bytes (defaults left out,
    field order) to the same dict, non-finite numbers as None like JSON's null."""
    spec = TOPIC_SPECS[topic]
    fields = data.draw(_fields(spec))
    from dobhil.recording.encodings.protobuf import packer
    parsed = message_class(spec).FromString(packer(spec)(fields))
    assert all(_same(getattr(parsed, f.name), v) for f, v in zip(spec.fields, fields))
    canonical = parsed.SerializeToString()
    payload = PB.decoder(spec)(canonical)
    expect = {f.name: (None if f.kind == FieldKind.NUMBER and not math.isfinite(v) else
                       list(v) if f.kind == FieldKind.BYTES else v) for f, v in zip(spec.fields, fields)}
    assert payload == expect and list(payload) == list(spec.keys)
    assert PB.decoder(spec)(packer(spec)(fields)) == expect


def test_a_message_cut_inside_a_field_is_refused_not_misread() -> None:
    """Cut between two fields, a message is a valid shorter one (protobuf has no end mark:
    MCAP's record length and chunk CRC guard that); cut inside a field, it is refused."""
    spec = TOPIC_SPECS[Topic.LOOP]
    good = PB.encoder(spec, None)((3, 1e-6, 2e-5, True, 0.5))
    ends = {9: 1, 18: 2, 27: 3, 29: 4}   # byte where a field ends -> fields before it
    for cut in range(1, len(good)):
        if cut in ends:
            payload = PB.decoder(spec)(good[:cut])
            assert list(payload.values())[:ends[cut]] == [3, 1e-6, 2e-5, True][:ends[cut]]
            assert list(payload.values())[ends[cut]:] == [0, 0.0, 0.0, False, 0.0][ends[cut]:]
        else:
            with pytest.raises(ValueError, match="runs past the end"):
                PB.decoder(spec)(good[:cut])
    with pytest.raises(ValueError, match="wire type 4"):   # a group (deprecated): no dobhil field is one
        list(fields_on_wire(varint(37 << 3 | 4) + varint(1)))
    assert list(fields_on_wire(varint(3 << 3) + varint(2 ** 64 - 1))) == [(3, 0, 2 ** 64 - 1)]


@pytest.fixture(scope="module")
def protobuf_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return lockstep_log_in(tmp_path_factory, "pb", 0.3)


def test_mcap_and_its_protobuf_decoder_read_every_topic(protobuf_log: Path) -> None:
    """mcap's reader with mcap-protobuf-support's DecoderFactory (no dobhil in the decode
    path) decodes every message of a recorded run to the values dobhil reads."""
    with open(protobuf_log, "rb") as f:
        decoded = [(channel.topic, message.log_time, proto)
                   for _, channel, message, proto in make_reader(f, decoder_factories=[DecoderFactory()])
                   .iter_decoded_messages(log_time_order=False)]
    ours = list(open_log(protobuf_log).iter_messages())
    assert {topic for topic, _, _ in decoded} == set(spec.name for spec in TOPIC_SPECS.values())
    assert len(decoded) == len(ours)
    for (topic, t, proto), (our_topic, our_t, payload) in zip(decoded, ours):
        assert (topic, t) == (our_topic, our_t)
        for name, value in payload.items():
            theirs = getattr(proto, name)
            if value is None:
                assert not math.isfinite(theirs)
            else:
                assert (list(theirs) if isinstance(theirs, bytes) else theirs) == value, (topic, name)


def test_log_info_names_the_encoding(protobuf_log: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["log", "info", str(protobuf_log)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert "encoding:   protobuf" in out
    assert any(x.endswith("dobhil.Controller (protobuf)") for x in out)


@pytest.fixture(scope="module")
def json_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A log as dobhil wrote it before protobuf (the JSON encoding, kept for these logs)."""
    path = tmp_path_factory.mktemp("json") / "old.mcap"
    logged_lockstep_run(path, duration=0.3, encoding="json")
    return path


def test_a_json_log_is_still_read_replayed_and_reported(json_log: Path, tmp_path: Path,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    log = open_log(json_log)
    assert log.encodings() == ("json",) and log.info().encoding == "json"
    assert main(["replay", "--verify", str(json_log)]) == 0
    assert main(["report", str(json_log), "--out", str(tmp_path / "report")]) == 0
    assert main(["log", "info", str(json_log)]) == 0
    assert "encoding:   json" in capsys.readouterr().out.splitlines()


def test_the_same_run_reads_the_same_in_both_encodings(json_log: Path, protobuf_log: Path) -> None:
    """Lockstep runs are deterministic: the two logs' messages are equal dicts (what the wall
    clock stamps aside: log times, the frames' bus stamps, /loop's timing, /events; and the
    frames' channel, the name of each run's own in-process bus)."""
    def messages(path: Path) -> list[tuple[str, dict[str, Any]]]:
        return [(topic, {k: v for k, v in p.items() if k not in ("timestamp", "channel")})
                for topic, _, p in open_log(path).iter_messages() if topic not in ("/events", "/loop")]
    old, new = messages(json_log), messages(protobuf_log)
    assert len(old) == len(new) > 0
    assert old == new


def test_the_registry_names_each_encoding_once() -> None:
    assert set(ENCODINGS) == {"protobuf", "json"}
    assert {encoding(name).name for name in ENCODINGS} == set(ENCODINGS)
    from dobhil.errors import LogFileError
    with pytest.raises(LogFileError, match="unknown message encoding 'cbor'; expected one of protobuf, json"):
        encoding("cbor")


def test_the_field_values_are_what_the_json_encoders_hold() -> None:
    """The protobuf encoder's fields come from schemas.field_values, the JSON encoder's from
    its own dict: for records of every derived topic they agree, name for name."""
    import orjson

    from dobhil.recording.codes import ProtocolCodes
    from dobhil.recording.encodings.json_messages import ENCODING as JSON
    from dobhil.recording.schemas import field_values
    samples = {Topic.CAN_RX: (0x69, True, False, True, False, True, False, 3, bytearray(b"\x01\x02\xff"), 2.5,
                              "can0"),
               Topic.CAN_TX: (0x1FFFFFFF, False, True, False, True, False, True, 0, b"", None, None),
               Topic.DRIVE_FEEDBACK: (0.25, -1.5, 2, 8, 0x8130, 41, 40),
               Topic.EVENTS: (6, "pipe full", "3 batches", 17)}
    for codes in (None, ProtocolCodes()):
        for topic, values in samples.items():
            spec = TOPIC_SPECS[topic]
            make = field_values(spec, codes)
            assert make is not None
            fields = {k: list(v) if isinstance(v, bytes) else v for k, v in zip(spec.keys, make(values))}
            assert fields == orjson.loads(JSON.encoder(spec, codes)(values)), topic
