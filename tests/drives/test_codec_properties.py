"""Property-based tests of the ODrive codec and emulator (hypothesis; fixed seed, bounded).

- every message of both firmwares: encode -> decode returns the message (floats to
  float32 precision) and the frame has the DBC's length;
- decode of arbitrary ids, bytes, DLCs and RTR flags raises nothing but CodecError;
- the host drive and the emulator fed arbitrary frames keep running, the emulator never
  hands a non-finite torque to its plant and never needs its last-resort handler.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import struct
from typing import Any

import can
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dobhil.drives import load_profile, make_drive
from dobhil.drives.odrive import codec
from dobhil.drives.odrive.codec import Firmware, Flags, MessageSpec, Scalar
from dobhil.drives.odrive.emulator import EmulatedODrive
from dobhil.errors import CodecError

from .test_drive_emulated import FakePlant

PROPERTY = settings(max_examples=150, derandomize=True, deadline=None, database=None,
                    suppress_health_check=[HealthCheck.too_slow])
_CHANNELS = itertools.count()
_INT_RANGES = {"B": 0xFF, "I": 0xFFFFFFFF, "Q": 0xFFFFFFFFFFFFFFFF}
ALL_SPECS = [(fw, spec) for fw in Firmware for spec in codec.specs(fw)]


def _slot_strategy(slot: Scalar | Flags, fmt: str) -> dict[str, st.SearchStrategy[Any]]:
    if isinstance(slot, Flags):
        return {name: st.booleans() for name, _ in slot.bits}
    if slot.scale is not None:  # a float32 on the wire, scaled to SI
        wire = st.floats(width=32, allow_nan=False, allow_infinity=True)
        return {slot.name: wire.map(lambda v, s=slot.scale: v * s)}
    return {slot.name: st.integers(0, _INT_RANGES[fmt])}


def message_strategy(spec: MessageSpec) -> st.SearchStrategy[Any]:
    formats = [c for c in spec.struct.format.lstrip("<") if c != "x"]
    fields: dict[str, st.SearchStrategy[Any]] = {}
    for slot, fmt in zip(spec.slots, formats):
        fields.update(_slot_strategy(slot, fmt))
    return st.fixed_dictionaries(fields).map(lambda kw: spec.cls(**kw))


@st.composite
def firmware_and_message(draw: st.DrawFn) -> tuple[Firmware, MessageSpec, Any]:
    fw, spec = draw(st.sampled_from(ALL_SPECS))
    return fw, spec, draw(message_strategy(spec))


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, float):
        return a == b or math.isclose(a, b, rel_tol=1e-6)
    return bool(a == b)


@PROPERTY
@given(firmware_and_message(), st.integers(0, codec.MAX_NODE_ID))
def test_encode_decode_round_trip(case: tuple[Firmware, MessageSpec, Any], node: int) -> None:
    fw, spec, msg = case
    frame = codec.encode(msg, node_id=node, firmware=fw)
    assert frame.dlc == spec.dlc and len(frame.data) == spec.dlc
    assert bytes(frame.data[spec.size:]) == bytes(spec.dlc - spec.size)  # zero padding
    assert codec.split_id(frame.arbitration_id) == (node, int(spec.cmd))
    back = codec.decode_message(frame, fw)
    if spec.size == 0 or type(back) is codec.Request:  # empty payloads
        return
    for name in codec.message_fields(spec.cls):
        assert _same(getattr(back, name), getattr(msg, name)), name


@PROPERTY
@given(st.sampled_from(ALL_SPECS), st.binary(min_size=8, max_size=8))
def test_decode_encode_is_stable(case: tuple[Firmware, MessageSpec], data: bytes) -> None:
    """decode(encode(decode(b))) == decode(b): the codec's view of any payload is a fixed point."""
    fw, spec = case
    arb = codec.arbitration_id(3, spec.cmd)
    first = codec.decode(arb, data[: spec.dlc] if spec.dlc else b"", fw)
    if isinstance(first, codec.Request):
        return
    floats = [v for v in vars_of(first) if isinstance(v, float)]
    if any(math.isnan(v) for v in floats):
        return  # NaN != NaN; NaN payloads are covered by the decode-anything property
    try:
        again = codec.decode(arb, codec.encode_data(first, fw), fw)
    except CodecError:  # a float32 NaN/inf or a value the SI scaling pushed past float32
        assert any(not math.isfinite(v / 2 / math.pi) or abs(v) > 3.4e38 for v in floats)
        return
    assert again == first


def vars_of(msg: Any) -> list[Any]:
    return [getattr(msg, n) for n in codec.message_fields(type(msg))]


@PROPERTY
@given(st.integers(-5, 0x2000), st.binary(max_size=64), st.booleans(), st.sampled_from(list(Firmware)))
def test_decode_of_anything_raises_only_codec_error(arb: int, data: bytes, rtr: bool, fw: Firmware) -> None:
    try:
        codec.decode(arb, data, fw, is_remote=rtr)
    except CodecError as exc:
        assert "\n" not in str(exc)


frames = st.builds(
    can.Message,
    arbitration_id=st.one_of(st.integers(0, 0x7FF), st.integers(0x60, 0x7F), st.integers(0, 0x1FFFFFFF)),
    is_extended_id=st.booleans(),
    is_remote_frame=st.booleans(),
    is_error_frame=st.booleans(),
    data=st.binary(max_size=8),
    check=st.just(False),
)


@PROPERTY
@given(st.lists(frames, max_size=30), st.sampled_from(["odrive-0.5", "odrive-0.6"]))
def test_emulator_and_drive_fed_arbitrary_frames_keep_running(batch: list[can.Message], name: str) -> None:
    """Frames arrive for node 3 (ids 0x60-0x7F are its commands), enabled or not."""
    profile = dataclasses.replace(load_profile(name), bus={})
    channel = f"props-{next(_CHANNELS)}"
    host = can.Bus(interface="virtual", channel=channel)
    plant = FakePlant(frozen=True)
    emu = EmulatedODrive(can.Bus(interface="virtual", channel=channel), profile, plant)
    drive_bus = can.Bus(interface="virtual", channel=channel)
    drive = make_drive(drive_bus, profile)
    try:
        for cmd in (codec.ClearErrors(), codec.SetInputTorque(0.0),
                    codec.SetControllerMode(codec.ControlMode.TORQUE_CONTROL, codec.InputMode.PASSTHROUGH),
                    codec.SetAxisState(codec.AxisState.CLOSED_LOOP_CONTROL)):
            host.send(codec.encode(cmd, node_id=3, firmware=emu.firmware))
        for msg in batch:
            host.send(msg)
            emu.handle_pending()
            emu.advance(0.001)
        assert emu.frame_errors == 0, emu.last_frame_error
        assert all(math.isfinite(t) for t in plant.torques)
        assert math.isfinite(emu.input_torque)
        drive.poll(0.0)  # the host side reads every frame the emulator and host sent
    finally:
        drive_bus.shutdown()
        emu.close()
        host.shutdown()


def test_float32_range_edge_is_exact() -> None:
    biggest = struct.unpack("<f", struct.pack("<f", 3.4028234663852886e38))[0]
    frame = codec.encode(codec.SetInputTorque(biggest), node_id=1)
    assert codec.decode_message(frame).torque_nm == biggest
