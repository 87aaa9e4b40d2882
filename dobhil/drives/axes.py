"""The drives of a loop's axes on their buses: which bus each axis is on, CAN-id clashes
between axes, and the bus budget of all the axes of a bus.

An axis' bus is its ``drive.interface``/``drive.channel`` (its own or the top level's);
failing that the default bus (``--bus``); failing that its drive profile's ``bus:``
section. Axes with none of the three share the one default bus a run is given.

**Clashes.** Two axes on one bus clash when their drives' CAN arbitration ids overlap: each
protocol lists them (:meth:`dobhil.drives.plugin.DriveProtocol.frame_ids`: ODrive node n
uses ``n << 5 | cmd`` for its 32 commands, a CANopen node the COB-IDs of CiA 301's
pre-defined connection set, an MIT motor its node id and its master id, a moteus controller
its command and reply ids), split into a drive's own ids and the ones every drive of its
protocol shares (SYNC and NMT of CANopen, the MIT master id): two drives of one protocol may
share those, a drive of another protocol may not use them. So an ODrive at node 4
(0x080-0x09F) clashes with any CANopen node on the bus (SYNC is 0x080), while ODrive node 1
and CiA 402 node 1 do not. Where a protocol cannot list its ids (its hook gives None) two
axes are compared by node id alone.

**Bus budget.** Per bus, the frames every axis puts on it per loop period (each protocol's
:meth:`~dobhil.drives.preflight.PreflightProbe.cycle_frames`), a frame marked ``shared``
(one SYNC for every CANopen node) counted once per bus, against the bus's bit rate
(:class:`~dobhil.drives.bus_load.BusBudget`). Over 100 % the axes cannot run on that bus:
:func:`axes_budget` refuses (ConfigError, one line), and a single-axis run by the same rule and
line (:func:`drive_budget`: its one axis' budget); over
:data:`~dobhil.drives.bus_load.MAX_BUDGET` (70 %) :meth:`AxesBusBudget.advice` is one line
saying what to change.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from dobhil.config.axes import Axes, Axis
from dobhil.drives.bus_load import MAX_BUDGET, BusBudget, CycleFrame, rate_text
from dobhil.drives.load import load_drive_profile
from dobhil.drives.plugin import FrameIds
from dobhil.drives.preflight import configured_bitrate
from dobhil.drives.profile import DriveProfile
from dobhil.drives.registry import preflight_probe, protocol, protocols
from dobhil.errors import ConfigError

if TYPE_CHECKING:
    from dobhil.drives.preflight import PreflightProbe

__all__ = ["DEFAULT_BUS", "AxesBusBudget", "AxisDrive", "axes_budget", "axis_drives", "bus_budgets",
           "check_clashes", "drive_budget"]

#: the bus of axes that name none (their run's ``--bus``), as the budget and clash lines say it
DEFAULT_BUS = "the default bus"
#: over this share of the bit rate the frames of one period do not fit in the period at all
MAX_LOAD = 1.0


@dataclass(frozen=True)
class AxisDrive:
    """One axis' drive: its profile (``drive.node_id`` applied) and the bus it is on
    (``INTERFACE:CHANNEL``, or :data:`DEFAULT_BUS`) at the bit rate it is opened with."""

    name: str
    profile: DriveProfile
    bus: str
    bitrate: int | None = None

    def describe(self) -> str:
        """``left (odrive node 1)``: the axis as a clash line names it."""
        return f"{self.name} ({self.profile.protocol} node {self.profile.node_id})"


def axis_drives(axes: Axes, config_dir: Path | None, default_bus: str | None = None) -> tuple[AxisDrive, ...]:
    """Each axis' drive, in the axes' order; ConfigError (one line) for a profile its
    protocol refuses, two bit rates on one bus, or two axes whose CAN ids clash
    (:func:`check_clashes`). ``config_dir``: where the config's relative profile paths start."""
    drives = tuple(_axis_drive(axis, config_dir, default_bus) for axis in axes.axes)
    _check_bitrates(drives)
    check_clashes(drives)
    return drives


def _axis_drive(axis: Axis, config_dir: Path | None, default_bus: str | None) -> AxisDrive:
    try:
        profile = load_drive_profile(axis.config, config_dir)
    except ConfigError as exc:
        raise ConfigError(f"axis {axis.name}: {exc}") from None
    drive = axis.config.drive
    if drive.interface:
        bus = f"{drive.interface}:{drive.channel}"
    elif default_bus:
        bus = default_bus
    else:
        own = profile.bus_kwargs()
        bus = f"{own['interface']}:{own.get('channel', '')}" if "interface" in own else DEFAULT_BUS
    return AxisDrive(axis.name, profile, bus, configured_bitrate(drive.bitrate, profile))


def _check_bitrates(drives: Sequence[AxisDrive]) -> None:
    """One bus runs at one bit rate: two axes of one bus asking for two are refused."""
    first: dict[str, AxisDrive] = {}
    for d in drives:
        other = first.setdefault(d.bus, d)
        if other.bitrate and d.bitrate and other.bitrate != d.bitrate:
            raise ConfigError(f"axes {other.name} and {d.name} are both on {d.bus} but at "
                              f"{rate_text(other.bitrate, 'bit/s')} and {rate_text(d.bitrate, 'bit/s')}: "
                              "one bus has one bit rate; set the same drive.bitrate on both")


# -- clashes ------------------------------------------------------------------------------------


def check_clashes(drives: Sequence[AxisDrive],
                  ids_of: Callable[[DriveProfile], FrameIds | None] | None = None) -> None:
    """ConfigError naming both axes and the id when two axes on one bus use one CAN id (see
    the module docstring); ``ids_of``: a profile's ids (default: its protocol's hook)."""
    lookup = ids_of or (lambda p: protocol(p.protocol).frame_ids(p))
    ids = [lookup(d.profile) for d in drives]
    for i, a in enumerate(drives):
        for j in range(i):
            b = drives[j]
            if a.bus == b.bus:
                _check_pair(b, ids[j], a, ids[i])


def _check_pair(a: AxisDrive, ids_a: FrameIds | None, b: AxisDrive, ids_b: FrameIds | None) -> None:
    if ids_a is None or ids_b is None:
        if a.profile.node_id == b.profile.node_id:
            raise ConfigError(f"axes {a.describe()} and {b.describe()} on {a.bus} have one node id; "
                              "give each axis its own drive.node_id")
        return
    common = _common_ids(ids_a, ids_b, a.profile.protocol == b.profile.protocol)
    if common:
        raise ConfigError(f"axes {a.describe()} and {b.describe()} on {a.bus} both use CAN id "
                          f"{_id_text(min(common))}{_more(common)}; give one of them another drive.node_id "
                          "(or move it to another bus)")


def _common_ids(a: FrameIds, b: FrameIds, same_protocol: bool) -> frozenset[int]:
    """The ids both drives use that they may not share: any of one's own ids the other uses;
    a shared id of one protocol that another protocol's drive uses too."""
    clash = (a.own & (b.own | b.shared)) | (a.shared & b.own)
    return clash if same_protocol else clash | (a.shared & b.shared)


def _id_text(can_id: int) -> str:
    return f"0x{can_id:08X}" if can_id > 0x7FF else f"0x{can_id:03X}"


def _more(ids: frozenset[int]) -> str:
    return f" (and {len(ids) - 1} more)" if len(ids) > 1 else ""


# -- bus budget ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class AxesBusBudget:
    """The frames of every axis on one bus per loop period against its bit rate:
    ``per_axis`` (name, bits per cycle of its own frames), ``shared`` the bits of frames the
    bus carries once for all (a SYNC), ``unknown`` the axes whose protocol lists no frames."""

    bus: str
    budget: BusBudget
    per_axis: tuple[tuple[str, float], ...]
    shared: float = 0.0
    unknown: tuple[str, ...] = ()
    fd_protocols: tuple[str, ...] = ()
    #: who needs the bits, in :meth:`refusal` (empty: ``axes a, b`` / ``axis a``; a single-axis
    #: run names its drive, :func:`drive_budget`)
    subject: str = ""

    @property
    def axes(self) -> tuple[str, ...]:
        return tuple(name for name, _ in self.per_axis) + self.unknown

    @property
    def load(self) -> float | None:
        return self.budget.load

    @property
    def over(self) -> bool:
        """Above :data:`~dobhil.drives.bus_load.MAX_BUDGET`: worth changing."""
        return self.budget.over

    @property
    def refused(self) -> bool:
        """Above 100 %: the frames of one period do not fit in it."""
        return self.load is not None and self.load > MAX_LOAD

    def line(self) -> str:
        """``bus budget socketcan:can0: 543 bits per cycle (left 271 + right 271) = 54.3 % of
        1 Mbit/s at 1 kHz``."""
        parts = [f"{name} {bits:.0f}" for name, bits in self.per_axis]
        if self.shared:
            parts.append(f"shared {self.shared:.0f}")
        head = f"bus budget {self.bus}: {self.budget.bits_per_cycle:.0f} bits per cycle ({' + '.join(parts)})"
        rate = rate_text(1.0 / self.budget.period, "Hz")
        tail = f"; frames of {', '.join(self.unknown)} unknown" if self.unknown else ""
        if self.load is None or not self.budget.bitrate:
            return f"{head} at {rate}; bit rate unknown (set drive.bitrate){tail}"
        return f"{head} = {self.load * 100:.1f} % of {rate_text(self.budget.bitrate, 'bit/s')} at {rate}{tail}"

    def advice(self) -> str:
        """Over 70 %: one line saying what to change (empty when within it)."""
        if not self.over:
            return ""
        return (f"bus {self.bus} (axes {', '.join(self.axes)}): {self._load_text()} is over "
                f"{MAX_BUDGET * 100:.0f} %: use " + ", or ".join(self._ways()))

    def refusal(self) -> str:
        """Over 100 %: the one line :func:`axes_budget` refuses with (empty when within it)."""
        if not self.refused:
            return ""
        who = self.subject or (f"axis {self.axes[0]}" if len(self.axes) == 1 else f"axes {', '.join(self.axes)}")
        need = "need" if not self.subject and len(self.axes) > 1 else "needs"
        return (f"bus {self.bus}: {who} {need} {self.budget.bits_per_cycle:.0f} bits per "
                f"cycle, {self._load_text()}: more than the bus carries in one period; use "
                + ", or ".join(self._ways()))

    def _load_text(self) -> str:
        return (f"{(self.load or 0.0) * 100:.0f} % of {rate_text(self.budget.bitrate or 0, 'bit/s')} at "
                f"{rate_text(1.0 / self.budget.period, 'Hz')}")

    def _ways(self) -> list[str]:
        ways = self.budget.ways()
        if self.fd_protocols:
            ways.append(f"drives on CAN FD (protocol {', '.join(self.fd_protocols)})")
        return ways

    def as_dict(self) -> dict[str, object]:
        return {"bus": self.bus, **self.budget.as_dict(), "axes": dict(self.per_axis), "shared_bits": self.shared,
                "unknown": list(self.unknown), "refused": self.refused}


def bus_budgets(drives: Sequence[AxisDrive], period: float,
                probe: Callable[[DriveProfile], PreflightProbe | None] = preflight_probe) -> tuple[AxesBusBudget, ...]:
    """The budget of each bus the axes are on, in the order the buses first appear."""
    buses = list(dict.fromkeys(d.bus for d in drives))
    return tuple(_bus_budget(bus, [d for d in drives if d.bus == bus], period, probe) for bus in buses)


def axes_budget(drives: Sequence[AxisDrive], period: float,
                probe: Callable[[DriveProfile], PreflightProbe | None] = preflight_probe) -> tuple[AxesBusBudget, ...]:
    """:func:`bus_budgets`, refused (ConfigError, one line) when a bus is over 100 % or when
    its axes ask for a frame of the bus (:attr:`CycleFrame.shared`) at two periods."""
    _check_shared_periods(drives, period, probe)
    budgets = bus_budgets(drives, period, probe)
    for b in budgets:
        if b.refused:
            raise ConfigError(b.refusal())
    return budgets


def _check_shared_periods(drives: Sequence[AxisDrive], period: float,
                          probe: Callable[[DriveProfile], PreflightProbe | None]) -> None:
    """A frame one bus carries once for every drive of a protocol (a CANopen SYNC: a network
    has one SYNC producer, CiA 301) is one frame at one period: two axes of a bus whose
    profiles ask for it at two periods would put two producers on the bus, and each node
    answers every one of them. Refused in one line naming both axes and the setting."""
    seen: dict[tuple[str, str, object, object], tuple[str, CycleFrame]] = {}
    for d in drives:
        found = probe(d.profile)
        for f in (found.cycle_frames(period) if found is not None else ()):
            if not f.shared:
                continue
            first = seen.setdefault((d.bus, f.name, f.dlc, f.extended), (d.name, f))
            other_name, other = first
            if (other.every, other.or_every) != (f.every, f.or_every):
                key = f.or_every_key or other.or_every_key or "the drive profile's period of it"
                raise ConfigError(
                    f"axes {other_name} and {d.name} on {d.bus} ask for one {f.name} of the bus every "
                    f"{_every_text(other, period)} and every {_every_text(f, period)} ({key}): a bus carries "
                    f"one {f.name}, at one period; give both drives the same (or put one on another bus: "
                    "its drive.interface/drive.channel)")


def _every_text(frame: CycleFrame, period: float) -> str:
    """The period a frame of the bus is asked for at: its own, else its ``or_every`` (the
    period a bus that sends it by itself keeps, e.g. SocketCAN's broadcast manager), else
    the loop's."""
    every = frame.every if frame.every is not None else (frame.or_every or period)
    return f"{every * 1e3:g} ms"


def drive_budget(axis: Axis, config_dir: Path | None, default_bus: str | None = None,
                 probe: Callable[[DriveProfile], PreflightProbe | None] = preflight_probe) -> AxesBusBudget:
    """The bus budget of a single-axis run (``dobhil run``/``check`` of one drive): the
    budget of :func:`axes_budget` for its one axis -- its bus and bit rate found as an axis'
    are, the same frames, refused (ConfigError, the same line) over 100 % -- naming the drive
    and, as a way out, what "fewer frames" means for its protocol (there are no other axes)."""
    (drive,) = axis_drives(Axes((axis,), listed=False), config_dir, default_bus)
    found = probe(drive.profile)
    fewer = found.budget_fewer if found is not None else None
    subject = f"drive profile {drive.profile.name or drive.profile.protocol!r} (node {drive.profile.node_id})"
    b = dataclasses.replace(_bus_budget(drive.bus, [drive], axis.config.loop.period, probe, fewer), subject=subject)
    if b.refused:
        raise ConfigError(b.refusal())
    return b


def _bus_budget(bus: str, drives: Sequence[AxisDrive], period: float,
                probe: Callable[[DriveProfile], PreflightProbe | None], fewer: str | None = None) -> AxesBusBudget:
    frames: list[CycleFrame] = []
    shared: dict[tuple[object, ...], CycleFrame] = {}
    per_axis: list[tuple[str, float]] = []
    unknown: list[str] = []
    bitrates = [d.bitrate for d in drives if d.bitrate]
    bitrate = bitrates[0] if bitrates else None
    for d in drives:
        found = probe(d.profile)
        own = list(found.cycle_frames(period)) if found is not None else []
        if not own:
            unknown.append(d.name)
            continue
        mine = [f for f in own if not f.shared]
        for f in own:
            if f.shared:   # one per bus: the first axis' stands for all
                shared.setdefault((f.name, f.dlc, f.every, f.extended, f.or_every), f)
        # replace(), not a new CycleFrame: a protocol's subclass (CAN FD's bits) stays itself
        frames += [dataclasses.replace(f, name=f"{d.name}: {f.name}") for f in mine]
        per_axis.append((d.name, sum(f.bits_at(bitrate) * f.per_cycle(period) for f in mine)))
    frames += shared.values()
    if fewer is None:
        fewer = "fewer axes on this bus (another bus for one: its drive.interface/drive.channel)"
    budget = BusBudget(tuple(frames), period, bitrate, fewer)
    shared_bits = sum(f.bits_at(bitrate) * f.per_cycle(period) for f in shared.values())
    return AxesBusBudget(bus, budget, tuple(per_axis), shared_bits, tuple(unknown), _fd_instead(drives))


def _fd_instead(drives: Sequence[AxisDrive]) -> tuple[str, ...]:
    """The CAN FD protocols dobhil speaks, when some axis on the bus is classic CAN (an FD
    frame carries up to 64 bytes at a faster data phase: far fewer bits per value)."""
    if all(protocol(d.profile.protocol).fd for d in drives):
        return ()
    fd = []
    for name in protocols():
        try:
            if protocol(name).fd:
                fd.append(name)
        except ConfigError:   # a protocol that fails to load is left out here
            continue
    return tuple(fd)
