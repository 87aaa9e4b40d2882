"""The MIT mode protocol as one object (:class:`~dobhil.drives.plugin.DriveProtocol`),
registered as the entry point ``mit`` of the group ``dobhil.drives`` (``pyproject.toml``)."""

from __future__ import annotations

from collections.abc import Callable
from types import MappingProxyType

import can

from dobhil.drives.mit.codec import MitModel, TorqueFrame, unpack_command
from dobhil.drives.mit.drive import MitDrive
from dobhil.drives.mit.emulator import EmulatedMit
from dobhil.drives.mit.preflight import ZeroResult
from dobhil.drives.mit.preflight import set_zero as send_set_zero
from dobhil.drives.mit.replies import DAMIAO_ENABLED, MitFault
from dobhil.drives.mit.rules import model_of
from dobhil.drives.plugin import CodecQuantisation, DriveProtocol, FrameIds, HostWatchSetting
from dobhil.drives.profile import DriveProfile
from dobhil.drives.waits import Cancel

__all__ = ["MitProtocol", "model_quantisation", "zero_command_torque"]


class MitProtocol(DriveProtocol):
    name = "mit"
    title = "MIT mode"
    sets_zero = True
    feedback_streams = False   # one reply per command

    @property
    def drive_class(self) -> type[MitDrive]:
        return MitDrive

    @property
    def emulator_class(self) -> type[EmulatedMit]:
        return EmulatedMit

    def state_name(self, profile: DriveProfile, code: int) -> str:
        """A Damiao reply's state nibble in its model's words; CubeMars and Mini-Cheetah
        replies carry no state (-1)."""
        if code < 0:
            return "none (the reply carries no mode)"
        named = {0: "disabled", DAMIAO_ENABLED: "enabled", **model_of(profile).layout.states}
        return named.get(code, f"state 0x{code:X}")

    def error_text(self, profile: DriveProfile, code: int) -> str:
        """The reply's error byte (or Damiao fault nibble) in its model's words, or what
        dobhil read from the reply's values (:class:`~dobhil.drives.mit.replies.MitFault`)."""
        if code in {m.value for m in MitFault}:
            return MitFault(code).name.lower().replace("_", " ")
        layout = model_of(profile).layout
        text = layout.errors.get(code) if "error" in layout.extra else layout.states.get(code)
        return text if code and text else super().error_text(profile, code)

    def frame_ids(self, profile: DriveProfile) -> FrameIds:
        """Commands go to the node id; replies come on ``mit.reply_id`` (the firmware's
        master id) with the node in byte 0, so every MIT motor on the bus may share it."""
        return FrameIds(frozenset({profile.node_id}), frozenset({int(profile.options.get("reply_id", 0))}))

    def host_watch(self, profile: DriveProfile) -> HostWatchSetting | None:
        """The motor's command timeout, the ``command_timeout`` of the profile's model row:
        without a command for it, a Mini-Cheetah zeroes its command (``CAN_TIMEOUT``, 25 ms)
        and a Damiao with its TIMEOUT register set leaves motor mode. None where the row has
        none (a CubeMars AK documents none; a Damiao's register is 0 from the factory, so its
        shipped rows say null): then the profile's ``watchdog_timeout``, as for any protocol."""
        model = model_of(profile)
        if not model.command_timeout:
            return super().host_watch(profile)
        row = f"{model.vendor} {model.model} (firmware {model.firmware!r})"
        return HostWatchSetting("command timeout", "command_timeout", model.command_timeout,
                                where=f"the model table's row {row}",
                                remedy="a motor set to a longer one, with a row of its own (mit.models)")

    def drive_identity(self, profile: DriveProfile) -> str:
        """The model row (vendor, model, firmware): one firmware name serves many models
        whose codec ranges differ (every Damiao row is firmware "factory")."""
        opts = profile.options
        return f"{opts.get('vendor')} {opts.get('model')} (firmware {profile.firmware!r})"

    def set_zero(self, bus: can.BusABC, profile: DriveProfile, *, clock: Callable[[], float],
                 cancel: Cancel | None = None) -> ZeroResult:
        """Set zero (0xFE), wait ``mit.zero_silence``, read the position back
        (:func:`dobhil.drives.mit.preflight.set_zero`)."""
        return send_set_zero(bus, profile, clock=clock, cancel=cancel)

    def quantisation(self, profile: DriveProfile) -> CodecQuantisation:
        """The codec of the profile's model row (``mit.vendor``/``mit.model``, see
        :mod:`dobhil.drives.mit.rules`): 16-bit position, 12-bit velocity and torque over the
        model's ranges (``MitModel.quanta``), truncated as the firmware's ``float_to_uint``
        does, in the firmware's sense of rotation (``axis_direction``). ConfigError (one
        line) when the model table has no such row."""
        return model_quantisation(model_of(profile))


def model_quantisation(model: MitModel) -> CodecQuantisation:
    """What the codec of one row of the model table quantises (see
    :meth:`MitProtocol.quantisation`); the report names the row (``source``)."""
    steps = model.quanta
    return CodecQuantisation(
        position=float(steps.position), velocity=float(steps.velocity), torque=float(steps.torque),
        direction=model.axis_direction, truncates=True, zero_torque=zero_command_torque(model),
        source=MappingProxyType({"vendor": model.vendor, "model": model.model, "firmware": model.firmware}))


def zero_command_torque(model: MitModel) -> float:
    """The torque a zero command applies, found by the codec itself: the drive's
    preallocated torque frame filled with 0 N m, decoded as the firmware decodes it (in the
    host's sense of rotation). Code ``2^11 - 1`` of 12 bits: -step/2, -4.4 mN m on an AK80-9."""
    frame = TorqueFrame(model)
    data = bytearray(frame.template)
    frame.fill(data, 0.0)
    return float(unpack_command(model, bytes(data)).torque)
