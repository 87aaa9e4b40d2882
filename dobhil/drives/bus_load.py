"""How many bits a CAN frame takes on the wire: the one formula the preflight's measured
bus load, the run report's bus load and the bus budget all use.

The bus budget (:class:`BusBudget`) is the load a run puts on the bus by design, before
anything is measured: the frames of one loop period (each protocol lists its own through
:meth:`dobhil.drives.preflight.PreflightProbe.cycle_frames`) times their bits on the
wire, against the bit rate. A bus loaded over :data:`MAX_BUDGET` has too little room
left for retransmissions after an error frame, SDO traffic and a second node's frames:
frames then queue behind each other and the feedback arrives late.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

__all__ = ["MAX_BUDGET", "STANDARD_BITRATES", "BusBudget", "CycleFrame", "budget", "fd_frame_bits", "frame_bits",
           "message_bits", "rate_text"]

#: a budget above this fraction of the bit rate is a finding (room for retransmissions,
#: SDO transfers and other nodes' frames: above it one retransmission delays the next cycle)
MAX_BUDGET = 0.7
#: the CiA 301 bit rates a suggestion may name (at most 1 Mbit/s: classic CAN)
STANDARD_BITRATES = (125_000, 250_000, 500_000, 800_000, 1_000_000)


def frame_bits(dlc: int, extended: bool = False) -> int:
    """Bits on the wire of a classic data frame incl. worst-case stuffing (EOF, IFS included)."""
    base, stuffable = (67, 54) if extended else (47, 34)
    return base + 8 * dlc + (stuffable + 8 * dlc - 1) // 4


def fd_frame_bits(length: int, *, extended: bool, data_ratio: float) -> int:
    """Bit times (nominal) of a CAN FD data frame of ``length`` payload bytes with worst-case
    stuffing (ISO 11898-1:2015): the arbitration phase (SOF, id, RRS/SRR, IDE, FDF, res,
    BRS), its stuff bits, CRC delimiter, ACK, EOF and IFS at the nominal rate; ESI, DLC,
    data, stuff count, CRC (17 bits up to 16 bytes, else 21) with its fixed stuff bits and
    the data's dynamic stuff bits at ``data_ratio`` nominal bits each (nominal/data rate,
    1 without the bit rate switch)."""
    arbitration = 1 + 11 + (20 if extended else 0) + 1 + 1 + 1 + 1 + 1
    nominal = arbitration + (arbitration - 1) // 4 + 1 + 2 + 7 + 3
    crc = 17 if length <= 16 else 21
    dynamic = 1 + 4 + 8 * length
    data = dynamic + (dynamic - 1) // 4 + 4 + crc + math.ceil((4 + crc) / 4)
    return math.ceil(nominal + data * data_ratio)


def message_bits(length: int, *, extended: bool, fd: bool = False, brs: bool = False,
                 data_ratio: float | None = None) -> int | None:
    """Bit times (nominal) of one frame as python-can describes it (``Message.dlc``: the
    payload length in bytes, ``is_fd``, ``bitrate_switch``): a classic frame by
    :func:`frame_bits`, a CAN FD frame by :func:`fd_frame_bits`, its data phase at the
    nominal rate without the bit rate switch and at ``data_ratio`` (nominal/data rate) with
    it. None: a frame with the bit rate switch and no ``data_ratio`` (its time on the bus
    depends on a data rate nobody said)."""
    if not fd:
        return frame_bits(length, extended)
    if brs and data_ratio is None:
        return None
    return fd_frame_bits(length, extended=extended, data_ratio=data_ratio if brs and data_ratio is not None else 1.0)


@dataclass(frozen=True)
class CycleFrame:
    """One frame a run puts on the bus: once per loop period (``every`` None), or every
    ``every`` seconds whatever the loop does (a heartbeat, a drive's own stream). ``shared``:
    one such frame serves every drive of its protocol on the bus (a CANopen SYNC), so a bus
    of several axes carries it once, not once per axis. ``or_every``: a frame sent once per
    loop period by one way of running and every ``or_every`` seconds by another, counted at
    the faster of the two (a CANopen SYNC: sent by the loop after each command, or by the
    kernel every SYNC period -- which one runs is known only once the bus is open)."""

    name: str
    dlc: int
    every: float | None = None
    extended: bool = False
    shared: bool = False
    or_every: float | None = None
    #: the setting ``or_every`` comes from, as the advice names it ("the profile's feedback_period")
    or_every_key: str = ""

    @property
    def bits(self) -> int:
        """Bits of one such frame on the wire."""
        return frame_bits(self.dlc, self.extended)

    def bits_at(self, bitrate: float | None) -> int:
        """Bits of one such frame in bit times of the nominal ``bitrate`` (None: unknown). A
        classic frame's do not depend on it; a CAN FD frame's data phase, at a data rate of
        its own, takes fewer of them the slower the nominal rate (a subclass says how)."""
        return self.bits

    def per_cycle(self, period: float) -> float:
        """How many of this frame one loop period carries (a heartbeat's share: < 1)."""
        if self.every is not None:
            return period / self.every
        return 1.0 if self.or_every is None else max(1.0, period / self.or_every)

    def describe(self, period: float, bitrate: float | None = None) -> str:
        share = self.per_cycle(period)
        if math.isclose(share, 1.0, rel_tol=1e-9):
            return f"{self.name} {self.bits_at(bitrate)}"
        return f"{self.name} {self.bits_at(bitrate)} x {share:.3g}"


@dataclass(frozen=True)
class BusBudget:
    """The frames of one loop period against the bit rate (None: unknown)."""

    frames: tuple[CycleFrame, ...]
    period: float
    bitrate: int | None
    #: what "fewer frames" means for this protocol, in the advice ("": no such way)
    fewer: str = "fewer axes on this bus"

    @property
    def bits_per_cycle(self) -> float:
        return sum(f.bits_at(self.bitrate) * f.per_cycle(self.period) for f in self.frames)

    @property
    def load(self) -> float | None:
        """Bits per cycle over the bits one period holds at the bit rate."""
        return self.bits_per_cycle / (self.bitrate * self.period) if self.bitrate else None

    @property
    def over(self) -> bool:
        return self.load is not None and self.load > MAX_BUDGET

    def line(self) -> str:
        """``bus budget: 391 bits per cycle (SYNC 55 + ...) = 39.1 % of 1 Mbit/s at 1 kHz``."""
        head = (f"bus budget: {self.bits_per_cycle:.0f} bits per cycle ("
                + " + ".join(f.describe(self.period, self.bitrate) for f in self.frames) + ")")
        if self.load is None:
            return f"{head} at {rate_text(1.0 / self.period, 'Hz')}; bit rate unknown (set drive.bitrate)"
        return (f"{head} = {self.load * 100:.1f} % of {rate_text(self.bitrate or 0, 'bit/s')} at "
                f"{rate_text(1.0 / self.period, 'Hz')}")

    def advice(self) -> str:
        """What to change when the budget is over :data:`MAX_BUDGET` (empty when it is not)."""
        if not self.over or not self.bitrate:
            return ""
        return (f"bus budget {(self.load or 0.0) * 100:.0f} % of {rate_text(self.bitrate, 'bit/s')} at "
                f"{rate_text(1.0 / self.period, 'Hz')} is over {MAX_BUDGET * 100:.0f} %: use "
                + ", or ".join(self.ways()))

    def ways(self) -> list[str]:
        """The changes that bring the budget within :data:`MAX_BUDGET`: a standard bit rate
        that is enough, the shortest loop period that is, and :attr:`fewer`."""
        if not self.bitrate:
            return [self.fewer] if self.fewer else []
        ways = []
        faster = [b for b in STANDARD_BITRATES if b > self.bitrate and self._load_at(b, self.period) <= MAX_BUDGET]
        if faster:
            ways.append(f"a higher bit rate ({rate_text(faster[0], 'bit/s')} on the drive and the interface: "
                        f"{self._load_at(faster[0], self.period) * 100:.0f} %)")
        slowest = self._shortest_period(self.bitrate)
        keys = sorted({f.or_every_key for f in self.frames if f.every is None and f.or_every is not None})
        if slowest is not None:
            ways.append(f"a slower loop (loop.period >= {slowest * 1e3:.3g} ms)")
        elif keys and (together := self._shortest_period(self.bitrate, following=True)) is not None:
            # the frames that run at their own period whatever the loop hold the bus: slow both
            ways.append(f"a slower loop (loop.period and {' and '.join(keys)} >= {together * 1e3:.3g} ms)")
        if self.fewer:
            ways.append(self.fewer)
        return ways

    def loop_bits(self) -> float:
        """Bits per loop period of the frames the run sends or triggers (the ones it adds to
        a bus on which the drive's own periodic frames already stream)."""
        return sum(f.bits_at(self.bitrate) * f.per_cycle(self.period) for f in self.frames if f.every is None)

    def _load_at(self, bitrate: float, period: float) -> float:
        return sum(f.bits_at(bitrate) * f.per_cycle(period) for f in self.frames) / (bitrate * period)

    def _shortest_period(self, bitrate: float, *, following: bool = False) -> float | None:
        """The shortest loop period whose budget is within MAX_BUDGET at ``bitrate``
        (rounded up to 10 us); None when no period brings it there (the frames that do not
        slow down with the loop exceed it alone). ``following``: the ``or_every`` frames'
        own period set to the loop's too (their :attr:`CycleFrame.or_every_key`).

        The load is ``per_loop / period + per_second``, where an ``or_every`` frame counts per
        loop below its ``or_every`` and per second above it: solved in each stretch between
        those edges, shortest first."""
        def slows(f: CycleFrame, low: float) -> bool:   # sent once per loop period from ``low`` on
            return f.every is None and (following or f.or_every is None or f.or_every > low)
        edges = [] if following else sorted({f.or_every for f in self.frames if f.every is None and f.or_every})
        for low, high in zip([0.0, *edges], [*edges, math.inf]):
            per_loop = sum(f.bits_at(bitrate) for f in self.frames if slows(f, low))
            per_second = sum(f.bits_at(bitrate) / (f.every or f.or_every or math.inf) for f in self.frames
                             if not slows(f, low))
            room = MAX_BUDGET * bitrate - per_second
            if room <= 0 or (per_loop <= 0 and low == 0.0):   # no period helps (or none is needed)
                return None   # the later stretches only move frames from per loop to per second
            period = max(low, per_loop / room)
            if period <= high:
                return math.ceil(period * 1e5 - 1e-9) / 1e5
        return None

    def as_dict(self) -> dict[str, object]:
        return {"bits_per_cycle": self.bits_per_cycle, "load": self.load, "bitrate": self.bitrate,
                "period": self.period, "over": self.over,
                "frames": [{"name": f.name, "bits": f.bits_at(self.bitrate), "per_cycle": f.per_cycle(self.period)}
                           for f in self.frames]}


def budget(frames: Sequence[CycleFrame], period: float, bitrate: int | None, *,
           fewer: str = "fewer axes on this bus") -> BusBudget | None:
    """The budget of ``frames`` (None when the protocol lists none: nothing to say)."""
    return BusBudget(tuple(frames), period, bitrate or None, fewer) if frames else None


def rate_text(value: float, unit: str) -> str:
    """``1 Mbit/s``, ``250 kbit/s``, ``1 kHz``, ``500 Hz``: the way bit and loop rates are said."""
    for scale, prefix in ((1e6, "M"), (1e3, "k")):
        if value >= scale:
            return f"{value / scale:.4g} {prefix}{unit}"
    return f"{value:.4g} {unit}"
