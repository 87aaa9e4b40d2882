"""The CANopen CiA 402 protocol as one object (:class:`~dobhil.drives.plugin.DriveProtocol`),
registered as the entry point ``cia402`` of the group ``dobhil.drives`` (``pyproject.toml``)."""

from __future__ import annotations

from collections.abc import Sequence

from dobhil.drives.cia402 import codec
from dobhil.drives.cia402.codec import Cob, Mapped, PowerState
from dobhil.drives.cia402.drive import CiA402Drive, emcy_text
from dobhil.drives.cia402.eds import load_od
from dobhil.drives.cia402.emulator import EmulatedCiA402
from dobhil.drives.plugin import DriveProtocol, FeedbackField, FrameIds, HostWatchSetting, PeriodicSend
from dobhil.drives.profile import DriveProfile

#: the feedback values a fault may corrupt -> (object index, which of the two TPDOs)
_FEEDBACK_OBJECTS = {"position": (0x6064, 0), "velocity": (0x606C, 1)}

__all__ = ["CiA402Protocol"]


class CiA402Protocol(DriveProtocol):
    name = "cia402"
    title = "CANopen CiA 402"

    @property
    def drive_class(self) -> type[CiA402Drive]:
        return CiA402Drive

    @property
    def emulator_class(self) -> type[EmulatedCiA402]:
        return EmulatedCiA402

    def state_name(self, profile: DriveProfile, code: int) -> str:
        """The power state the statusword reports (``operation enabled``)."""
        return PowerState(code).text if code in {m.value for m in PowerState} else super().state_name(profile, code)

    def error_text(self, profile: DriveProfile, code: int) -> str:
        """The last EMCY's error code with canopen's description of its CiA 301 class."""
        return f"EMCY 0x{code:04X} ({emcy_text(code)})" if code else "none"

    def feedback_field(self, profile: DriveProfile, name: str) -> FeedbackField | None:
        """``position`` (0x6064) in the status TPDO, ``velocity`` (0x606C) in the motion
        TPDO after it (``cia402.tpdo``, the codec's standard mappings): integers in the
        drive's units."""
        found = _FEEDBACK_OBJECTS.get(name)
        if found is None:
            return None
        index, which = found
        layout = (codec.TPDO_STATUS, codec.TPDO_MOTION)[which]
        cob = Cob.tpdo(int(profile.options["tpdo"]) + which, profile.node_id)
        return _field(cob, layout, index)

    def frame_ids(self, profile: DriveProfile) -> FrameIds:
        """The node's COB-IDs of the pre-defined connection set (CiA 301: EMCY 0x080,
        TPDO/RPDO 1-4 0x180-0x500, SDO 0x580/0x600, heartbeat 0x700, each + node id); NMT,
        SYNC and the host's heartbeat (when the node watches it) every CANopen node on the
        bus shares."""
        node = profile.node_id
        own: set[int] = {Cob.emcy(node), Cob.SDO_TX + node, Cob.SDO_RX + node, Cob.HEARTBEAT + node}
        own |= {Cob.tpdo(n, node) for n in range(1, 5)} | {Cob.rpdo(n, node) for n in range(1, 5)}
        shared: set[int] = {Cob.NMT, Cob.SYNC}
        if float(profile.options.get("consumer_heartbeat", 0.0)) > 0:
            shared.add(Cob.HEARTBEAT + int(profile.options.get("host_node_id", 127)))
        return FrameIds(frozenset(own), frozenset(shared))

    def host_watch(self, profile: DriveProfile) -> HostWatchSetting | None:
        """The node's heartbeat consumer time (0x1016, ``cia402.consumer_heartbeat``; 0:
        off): the node faults when the host's heartbeat, sent every loop period at the
        shortest (a whole number of SYNC periods, :func:`codec.host_heartbeat_interval
        <dobhil.drives.cia402.codec.host_heartbeat_interval>`), stops for it.
        Off: the profile's ``watchdog_timeout``, as for any protocol."""
        consumer = float(profile.options.get("consumer_heartbeat", 0.0))
        if consumer <= 0:
            return super().host_watch(profile)
        return HostWatchSetting("heartbeat consumer (0x1016)", "cia402.consumer_heartbeat", consumer,
                                fed_by="host heartbeat")

    def periodic_sends(self, profile: DriveProfile) -> tuple[PeriodicSend, ...]:
        """SYNC every ``feedback_period`` (the node's 0x1006 / 0x60C2, :meth:`CiA402Drive._start_sync
        <dobhil.drives.cia402.drive.CiA402Drive._start_sync>`), and the host's heartbeat when the
        node watches it (``cia402.consumer_heartbeat`` > 0), every whole number of SYNC periods
        (:func:`~dobhil.drives.cia402.codec.host_heartbeat_interval`)."""
        sync = profile.feedback_period
        if sync is None or not sync > 0:   # the rules require it; nothing to say without it
            return ()
        sends = [PeriodicSend("SYNC", sync, "feedback_period")]
        consumer = float(profile.options.get("consumer_heartbeat", 0.0))
        if consumer > 0:
            sends.append(PeriodicSend("host heartbeat", codec.host_heartbeat_interval(consumer, sync),
                                      "cia402.consumer_heartbeat"))
        return tuple(sends)

    def check_files(self, profile: DriveProfile) -> None:
        load_od(profile)   # the drive's own reading and check of the EDS


def _field(cob: int, layout: Sequence[Mapped], index: int) -> FeedbackField:
    """Where object ``index`` sits in a PDO mapping ``layout`` (byte-aligned, in order)."""
    types = [m.data_type for m in layout]
    at = [m.index for m in layout].index(index)
    fmt = codec.layout_struct(types[at:at + 1]).format
    return FeedbackField(arbitration_id=cob, offset=codec.layout_struct(types[:at]).size, fmt=fmt)
