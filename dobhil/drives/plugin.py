"""A drive protocol as one object: everything dobhil knows of a protocol, behind one base class.

As python-can has one ``BusABC`` subclass per interface, found by one entry point of the
group ``can.interface``, dobhil has one :class:`DriveProtocol` subclass per protocol, found
by one entry point of the group ``dobhil.drives`` (name: the protocol, the key of its
profiles' ``protocol:``; value: ``module:Class``). The built-in protocols register through the
same entry points (``pyproject.toml``) and are also listed in the registry
(:mod:`dobhil.drives.registry`) so a source tree that was never installed works.

A protocol lives in one subpackage, ``dobhil/drives/<name>/`` (codec, drive, emulated drive,
preflight, profile rules, this object in ``plugin.py``); generic code (runtime, analysis,
recording, the emulator's process, cli, tune, campaign, identify) only ever holds a
:class:`DriveProtocol` and calls its hooks, so a new protocol is a new subpackage plus its
entry point, not an edit everywhere.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

import can

from dobhil.drives.base import Drive
from dobhil.drives.profile import DriveProfile, ProtocolRules
from dobhil.drives.waits import Cancel
from dobhil.errors import ConfigError

if TYPE_CHECKING:
    from dobhil.drives.emulated import EmulatedDrive
    from dobhil.drives.preflight import PreflightProbe

__all__ = ["CodecQuantisation", "DriveProtocol", "FeedbackField", "FrameIds", "HostWatchSetting", "PeriodicSend",
           "ZeroResult", "classic_bus", "require_fd_bus"]

_EMPTY: Mapping[str, Any] = MappingProxyType({})


def classic_bus(bus: can.BusABC) -> bool:
    """True when the bus says it runs classic CAN (python-can's ``BusABC.protocol``)."""
    return getattr(bus, "protocol", None) is can.CanProtocol.CAN_20


def require_fd_bus(bus: can.BusABC, profile: DriveProfile) -> None:
    """The one-line refusal of a bus opened as classic CAN for a protocol whose frames are
    CAN FD: its frames could not be sent, and a drive never answering would say nothing
    of why (``dobhil run``, ``check``, ``emulate`` alike)."""
    if classic_bus(bus):
        raise ConfigError(f"drive profile {profile.name or profile.protocol!r}: protocol {profile.protocol} needs a "
                          f"CAN FD bus, but {bus.channel_info} was opened as classic CAN (open it with fd=True; "
                          "SocketCAN: ip link set ... fd on)")


@dataclass(frozen=True)
class CodecQuantisation:
    """What a protocol's codec does to the loop's signals, for the analysis
    (:mod:`dobhil.analysis.quantisation`): one step per channel in SI units, the sense in
    which the codec truncates, and the torque a zero command decodes to."""

    position: float            # [rad] one code of the position the host reads
    velocity: float            # [rad/s] one code of the velocity the host reads
    torque: float              # [N m] one code of the torque the drive applies
    direction: int = 1         # +1: the decoded value lies in (true - step, true]; -1: reversed axis
    truncates: bool = True     # False: the codec rounds to nearest (error in [-step/2, step/2))
    zero_torque: float = 0.0   # [N m] what a zero command applies (a truncating codec's bias)
    source: Mapping[str, Any] = field(default_factory=lambda: _EMPTY)   # what the steps come from, for the report


@dataclass(frozen=True)
class FeedbackField:
    """Where a feedback value sits in the protocol's motion frame, for fault injection
    (:mod:`dobhil.emulator.faults`): the frame's id, the value's byte offset and its
    ``struct`` format (little-endian float, say ``"<f"``)."""

    arbitration_id: int
    offset: int
    fmt: str


@dataclass(frozen=True)
class FrameIds:
    """The CAN arbitration ids a drive uses on its bus (an id above 0x7FF is a 29-bit
    extended one, as python-can's ``is_extended_id`` is set by the drives): ``own``, the
    ids of this one drive; ``shared``, ids every drive of the same protocol on the bus uses
    together (a CANopen SYNC and NMT, an MIT master id all replies come on), which two such
    drives share without clashing, but which no drive of another protocol may use."""

    own: frozenset[int]
    shared: frozenset[int] = frozenset()


@dataclass(frozen=True)
class HostWatchSetting:
    """A drive's timeout on the host's frames as a profile sets it, before any bus opens
    (the drive's live watch, with how the host feeds it, is
    :attr:`~dobhil.drives.base.Drive.host_watch`): the drive stops following torque when
    the frame that feeds it (``fed_by``, sent every loop period) stops for ``timeout`` s.
    One rule holds every protocol's to the loop period
    (:func:`dobhil.runtime.session.check_host_watch`); the fields word its refusal."""

    what: str         # the drive's name for it: "command watchdog", "heartbeat consumer (0x1016)"
    key: str          # the setting that holds it: "watchdog_timeout", "cia402.consumer_heartbeat"
    timeout: float    # [s] > 0
    fed_by: str = "command"   # what the host sends every period that feeds it
    where: str = ""   # where ``key`` is set when not in the profile itself ("" : the profile)
    #: what else allows a longer period ("" : a longer ``key``, on the drive too)
    remedy: str = ""


@dataclass(frozen=True)
class PeriodicSend:
    """A frame the host's drive sends by itself at a fixed period, with python-can's
    ``send_periodic``, on a bus that sends periodic frames natively
    (:func:`~dobhil.drives.periodic.native_periodic`: SocketCAN's broadcast manager, the
    lockstep bus, the emulator's process), as a profile sets it, before any bus opens.
    The lockstep bus sends one only every whole number of its steps (one step per loop
    period): :func:`dobhil.runtime.session.check_lockstep` holds every one to that."""

    what: str        # the protocol's name of the frame: "SYNC", "host heartbeat"
    period: float    # [s] > 0
    key: str         # the setting it follows: "feedback_period", "cia402.consumer_heartbeat"


class ZeroResult(Protocol):
    """What a drive's set zero left (:meth:`DriveProtocol.set_zero`): its first reply after
    zeroing, as ``dobhil check --set-zero`` prints it (``line()``) and writes it (--json)."""

    @property
    def node(self) -> int: ...

    @property
    def position(self) -> float: ...   # [rad] the reading after zeroing (near 0 when it took)

    @property
    def silence(self) -> float: ...    # [s] how long the host waited before asking

    def line(self) -> str: ...


class DriveProtocol(ABC):
    """One drive protocol. Subclasses set :attr:`name` and implement the hooks; the defaults
    are what a protocol without that feature gives (no emulator, no quantisation, ...)."""

    #: the key of ``protocol:`` in a profile and the entry point's name
    name: ClassVar[str] = ""
    #: one line for humans: "ODrive CANSimple", "CANopen CiA 402", ...
    title: ClassVar[str] = ""
    #: True when the protocol's frames are CAN FD (the bus must be opened with ``fd=True``)
    fd: ClassVar[bool] = False
    #: True when the drive makes its present position its zero on command
    #: (:meth:`set_zero`; ``dobhil check --set-zero`` refuses other protocols before a bus opens)
    sets_zero: ClassVar[bool] = False
    #: True when the drive sends its motion feedback on its own, every ``feedback_period``,
    #: where the bus sends periodic frames natively (the lockstep bus: a CiA 402 SYNC);
    #: False when it answers each command with one reply (the drive's
    #: :attr:`~dobhil.drives.base.Drive.feedback_streams`, known before a bus opens)
    feedback_streams: ClassVar[bool] = True

    def check_bus(self, bus: can.BusABC, profile: DriveProfile) -> None:
        """Refuse, in one line, a bus this protocol's frames cannot travel on, before
        anything is sent: a CAN FD protocol (:attr:`fd`) on a bus opened as classic CAN."""
        if self.fd:
            require_fd_bus(bus, profile)

    @property
    @abstractmethod
    def drive_class(self) -> type[Drive]:
        """The :class:`~dobhil.drives.base.Drive` subclass that speaks the protocol."""

    @property
    def emulator_class(self) -> type[EmulatedDrive] | None:
        """The emulated drive (:class:`~dobhil.drives.emulated.EmulatedDrive`), or None."""
        return None

    @property
    def rules(self) -> ProtocolRules:
        """The profile section rules, given to the one profile validator."""
        return self.drive_class.profile_rules

    def preflight_probe(self, profile: DriveProfile) -> PreflightProbe | None:
        """What ``dobhil check`` reads of a drive of this protocol (None: nothing yet)."""
        return self.drive_class.preflight_probe(profile)

    def check_files(self, profile: DriveProfile) -> None:
        """Read and check the files ``profile`` names (CiA 402: its EDS) as its drive will,
        so that a command that opens no bus (``dobhil analyze``) refuses what ``dobhil run``
        would: ConfigError, one line. Default: the profile names no file."""
        return None

    def drive_identity(self, profile: DriveProfile) -> str:
        """What tells ``profile``'s drive apart from another of this protocol whose frames
        decode, scale or delay otherwise, in words (``firmware '0.6'``): logs of two
        identities are not one drive (``dobhil identify``). Default: the firmware."""
        return f"firmware {profile.firmware!r}"

    def state_name(self, profile: DriveProfile, code: int) -> str:
        """The drive's own state code (``DriveStatus.state``, the log's ``protocol_state``)
        in the protocol's words for ``profile``'s drive; ``str(code)`` when it names none."""
        return str(code)

    def error_text(self, profile: DriveProfile, code: int) -> str:
        """The drive's own error code (the log's ``protocol_error``) in the protocol's words."""
        return f"0x{code:X}" if code else "none"

    def quantisation(self, profile: DriveProfile) -> CodecQuantisation | None:
        """What the codec of ``profile``'s drive quantises (None: floats, nothing to model)."""
        return None

    def feedback_field(self, profile: DriveProfile, name: str) -> FeedbackField | None:
        """Where ``name`` (``"position"`` or ``"velocity"``) is in the motion frame of
        ``profile``'s drive (None: the protocol offers no such injection)."""
        return None

    def frame_ids(self, profile: DriveProfile) -> FrameIds | None:
        """The arbitration ids ``profile``'s drive uses (the ones its drive's
        :attr:`~dobhil.drives.base.Drive.frame_ids` lists), split into its own and the ones
        it shares with drives of its protocol; None: not known (two axes are then compared
        by node id)."""
        return None

    def host_watch(self, profile: DriveProfile) -> HostWatchSetting | None:
        """The timeout ``profile``'s drive keeps on the host's frames, which a run relies on
        to stop the drive when the host stops (None: none set). Default: the profile's
        ``watchdog_timeout``, the drive-side command watchdog (0: off)."""
        timeout = profile.watchdog_timeout
        return HostWatchSetting("command watchdog", "watchdog_timeout", timeout) if timeout > 0 else None

    def periodic_sends(self, profile: DriveProfile) -> tuple[PeriodicSend, ...]:
        """The frames ``profile``'s drive sends with ``send_periodic`` where the bus sends
        them natively (a CANopen SYNC); default: none (the drive sends each frame itself)."""
        return ()

    def set_zero(self, bus: can.BusABC, profile: DriveProfile, *, clock: Callable[[], float],
                 cancel: Cancel | None = None) -> ZeroResult:
        """Make the present position the drive's zero and read it back (only where
        :attr:`sets_zero`); ConfigError for a protocol that cannot."""
        raise ConfigError(f"protocol {self.name!r} cannot set its zero on command")

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.name!r}>"
