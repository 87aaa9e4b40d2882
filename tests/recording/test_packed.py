"""The loop thread's packed records (dobhil/recording/packed.py): the layouts against literal
bytes, a round trip of any record that fits, and what does not fit recorded as a tuple."""

from __future__ import annotations

import math
import struct
from types import SimpleNamespace
from typing import Any

import can
import pytest
from hypothesis import given, settings, strategies as st

from dobhil.recording.packed import CYCLE_PLAIN, CYCLE_TRUTH, channel_bytes, pack_frame, unpacked, unpacked_batch
from dobhil.recording.process import encode, unpack
from dobhil.recording.runlog import RunLog
from dobhil.recording.schemas import CYCLE, LANE_STRIDE, CycleRecord, FrameRecord, Topic

RX, TX = int(Topic.CAN_RX), int(Topic.CAN_TX)
OUT = (1.0, 2.0, 3.0, 4.0, 5.0, 6.0)


def frame(msg: Any, data: bytes, kind: int = RX, t: int = 2, stamp: float = 0.5) -> bytes:
    return pack_frame(kind, t, msg, data, stamp, channel_bytes(msg.channel, {}))


def test_a_frame_is_laid_out_as_documented() -> None:
    """Little-endian: kind (2), log time (8), id (8), six flags (1 each), dlc (8), timestamp
    (8, IEEE 754), payload length (2), payload, channel length (2) and UTF-8 text."""
    msg = can.Message(arbitration_id=0x69, is_extended_id=False, is_fd=True, data=b"\x01\x02", channel="c")
    assert frame(msg, msg.data) == bytes.fromhex(
        "0100" "0200000000000000" "6900000000000000" "000000010000" "0200000000000000" "000000000000e03f"
        "0200" "0102" "0100" "63")
    msg.channel = None  # no channel: 0xFFFF, no text
    assert frame(msg, msg.data).endswith(bytes.fromhex("0200" "0102" "ffff"))


def test_a_cycle_is_laid_out_as_documented() -> None:
    """The fields of CycleRecord in order: kind (2), then 8 bytes each (overrun 1)."""
    packed = CYCLE_PLAIN.pack(16, 2, 3, 0.5, -1.0, 7, *OUT, 0.25, 0.125, True, math.nan, 1, -1, 0x1234)
    assert packed == bytes.fromhex(
        "1000" "0200000000000000" "0300000000000000" "000000000000e03f" "000000000000f0bf" "0700000000000000"
        "000000000000f03f" "0000000000000040" "0000000000000840" "0000000000001040" "0000000000001440"
        "0000000000001840" "000000000000d03f" "000000000000c03f" "01" "000000000000f87f" "0100000000000000"
        "ffffffffffffffff" "3412000000000000")
    assert same(unpacked(packed), (16, 2, 3, 0.5, -1.0, 7, *OUT, 0.25, 0.125, True, math.nan, 1, -1, 0x1234))
    assert len(unpacked(CYCLE_TRUTH.pack(0, 2, 3, 0.5, -1.0, 7, *OUT, 0.25, 0.125, True, 0.0, 1, -1, 0,
                                         1.0, 2.0, 3.0, 4.0))) == len(CycleRecord._fields)


def same(a: tuple[Any, ...], b: tuple[Any, ...]) -> bool:
    """Equal field by field, floats bit for bit (NaN, -0.0), types included."""
    def key(v: Any) -> Any:
        return (float, struct.pack("<d", v)) if type(v) is float else (type(v), v)
    return len(a) == len(b) and all(key(x) == key(y) for x, y in zip(a, b))


i64 = st.integers(-(1 << 63), (1 << 63) - 1)
f64 = st.floats(allow_nan=True, allow_infinity=True)
kinds = st.integers(0, 1000).map(lambda lane: lane * LANE_STRIDE)


@settings(max_examples=300, deadline=None)
@given(kind=kinds, ints=st.tuples(i64, i64, i64, i64, i64, i64), floats=st.lists(f64, min_size=15, max_size=15),
       overrun=st.booleans(), truth=st.booleans())
def test_any_cycle_record_that_fits_comes_back_as_it_went(kind: int, ints: tuple[int, ...], floats: list[float],
                                                          overrun: bool, truth: bool) -> None:
    t, k, seq, state, pstate, perr = ints
    record = (kind + CYCLE, t, k, floats[0], floats[1], seq, *floats[2:10], overrun, floats[10], state, pstate,
              perr, *(floats[11:] if truth else ()))
    assert same(unpacked((CYCLE_TRUTH if truth else CYCLE_PLAIN).pack(*record)), record)


@settings(max_examples=300, deadline=None)
@given(lane=st.integers(0, 1000), tx=st.booleans(), t=i64, arb=i64, flags=st.lists(st.booleans(), min_size=6,
       max_size=6), dlc=i64, data=st.binary(max_size=64), stamp=f64, channel=st.none() | st.text(max_size=40))
def test_any_frame_record_that_fits_comes_back_as_it_went(lane: int, tx: bool, t: int, arb: int, flags: list[bool],
                                                          dlc: int, data: bytes, stamp: float,
                                                          channel: str | None) -> None:
    kind = lane * LANE_STRIDE + (TX if tx else RX)
    msg = SimpleNamespace(arbitration_id=arb, is_extended_id=flags[0], is_remote_frame=flags[1],
                          is_error_frame=flags[2], is_fd=flags[3], bitrate_switch=flags[4],
                          error_state_indicator=flags[5], dlc=dlc, channel=channel)
    record = (kind, t, arb, *flags, dlc, data, stamp, channel)
    assert same(unpacked(frame(msg, data, kind, t, stamp)), record)
    assert len(record) == len(FrameRecord._fields)


def test_a_cut_or_foreign_packed_record_is_refused() -> None:
    msg = can.Message(arbitration_id=0x69, data=b"\x01\x02", channel="c")
    with pytest.raises(ValueError, match="lengths"):
        unpacked(frame(msg, msg.data) + b"x")
    with pytest.raises(ValueError, match="not a cycle or a frame"):
        unpacked(struct.pack("<H", int(Topic.EVENTS)) + bytes(40))


def test_what_does_not_fit_is_recorded_as_the_tuple_it_was() -> None:
    """A None position, a sequence number beyond 64 bits, an int channel, a list payload, an
    output of another length: each recorded as before packing (a tuple, values as given)."""
    log = RunLog(SimpleNamespace(opened=False))  # type: ignore[arg-type]
    log.clock_ns = lambda: 5
    fb = SimpleNamespace(position=None, velocity=0.0, seq=1)
    log.cycle(1, 0.0, fb, OUT, 0.0, 0.0, False)
    fb.position, fb.seq = 0.5, 1 << 70
    log.cycle(2, 0.0, fb, OUT, 0.0, 0.0, False)
    log.cycle(3, 0.0, SimpleNamespace(position=0.5, velocity=0.0, seq=1), OUT[:5], 0.0, 0.0, False)
    log.cycle(4, 0.0, SimpleNamespace(position=0.5, velocity=0.0, seq=1), OUT, 0.0, 0.0, False)
    log.received(RX, can.Message(arbitration_id=1, data=b"\x01", channel=3))
    listed = can.Message(arbitration_id=1, channel="c")
    listed.data = [1, 2]  # type: ignore[assignment]
    log.sent(TX, listed)
    log.received(RX, can.Message(arbitration_id=1, data=b"\x01", channel="c"))
    records = log.take()
    assert [type(r) for r in records] == [tuple, tuple, tuple, bytes, tuple, tuple, bytes]
    assert records[0][3] is None and records[1][5] == 1 << 70 and len(records[2]) == len(CycleRecord._fields) - 4 - 1
    assert records[4][-1] == 3 and records[5][10] == b"\x01\x02"  # a sent frame's data copied, as before
    assert unpacked(records[6])[-1] == "c"
    # across the hand-over every record is a plain tuple of its topic's layout again
    (batch,), _ = unpack(encode(records))
    expected = unpacked_batch(records)
    assert len(batch) == len(expected) and all(same(a, b) for a, b in zip(batch, expected))
    assert all(type(r) is tuple for r in batch)


def _codes(fmt: str) -> list[str]:
    """A struct format's field codes, counts expanded (``6d`` -> six ``d``)."""
    import re
    return [code for count, code in re.findall(r"(\d*)([a-zA-Z?])", fmt.lstrip("<"))
            for _ in range(int(count or 1))]


def test_the_cycle_layout_is_cycle_records_fields_by_type() -> None:
    """The packed cycle follows ``CycleRecord``'s annotations field by field (``d`` a float,
    ``q`` an int, ``?`` a flag; the kind ``H``): a field added to the named record without its
    place in the layout fails here, not as shifted numbers in a log."""
    import typing
    hints = typing.get_type_hints(CycleRecord)
    wanted = ["H"] + [{float: "d", int: "q", bool: "?"}[hints[name]] for name in CycleRecord._fields[1:]]
    assert _codes(CYCLE_TRUTH.format) == wanted
    assert _codes(CYCLE_PLAIN.format) == wanted[:wanted.index("?") + 5]   # up to protocol_error
    assert CycleRecord._fields[wanted.index("?") + 4] == "protocol_error"
