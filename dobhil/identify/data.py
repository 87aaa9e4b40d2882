"""What an identification fits: the torque sent and the motion measured, one sample per control
cycle (:class:`IdentData`), and the stretches of free motion and of contact in it
(:class:`Segment`).

A dobhil log carries each cycle's loop record: ``/drive/feedback`` (the position and velocity the
controller saw at cycle k) and ``/controller`` (``u_sat``: the torque sent at cycle k, after the
saturation, held until the next). Cycle k is at ``t = k T`` (``loop.period`` of the recorded
config): the loop is clocked by the feedback, so the cycle index is the sample index.

Segments are found from the data alone: a contact adds a restoring spring to the free servo, so
the sampled acceleration ``dq[k+1] - dq[k]`` regressed on the torque (a few samples back, for the
delay), the velocity and a constant gains a ``-(K T/J) q`` term on the side of a position
threshold where the environment is engaged. The threshold that explains the data best is taken
when an F test says the spring term is real and it is restoring; otherwise everything is free.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from types import MappingProxyType
from typing import Any, Final

import numpy as np
from numpy.typing import NDArray

from dobhil.drives.profile import DriveProfile
from dobhil.errors import ConfigError, LogFileError, exception_line

Array = NDArray[np.float64]

FREE: Final = "free"
CONTACT: Final = "contact"
KINDS: Final = (FREE, CONTACT)
#: config sections whose numeric keys an IdentData carries as ``recorded``
RECORDED_SECTIONS: Final = ("plant", "environment", "design")
#: fewest samples of a segment: shorter runs of one kind merge into their neighbour (more than
#: the fit's own minimum, twice its start estimate's smoothing and then some)
MIN_SEGMENT: Final = 25
#: torque lags in the segment regression: covers a whole-sample delay of up to this many periods
_LAGS: Final = 4
#: significance of the contact spring term (F test)
_ALPHA: Final = 1e-3
_TOPICS: Final = ("/drive/feedback", "/controller")


@dataclass(frozen=True)
class IdentData:
    """Uniformly sampled torque and motion of one run (the seam between data and fit)."""

    period: float              # [s]
    t: Array                   # [s] k * period, uniform
    torque: Array              # [Nm] torque sent at t_k (after saturation), held to t_{k+1}
    position: Array            # [rad] measured at t_k, as the controller saw it
    velocity: Array            # [rad/s] measured at t_k
    source: str                # file name ("" when synthetic)
    protocol: str              # the drive profile's protocol
    recorded: Mapping[str, float]   # config keys recorded in the log (plant.*, environment.*, design.*)
    #: a run's log: the cycle of the first sample (its longest run of cycles without a gap)
    first_cycle: int = 0
    #: a run's log: the cycles it recorded (0: not a run's log, or not known)
    cycles: int = 0

    @property
    def samples(self) -> int:
        return int(self.t.size)


@dataclass(frozen=True)
class Segment:
    """Samples ``start`` (inclusive) to ``stop`` (exclusive) of one kind of motion."""

    start: int
    stop: int
    kind: str                  # "free" | "contact"
    # checked where it is used (identify refuses a segment outside the data or of another kind)


# -- reading -------------------------------------------------------------------------------

def read_log(path: str | os.PathLike[str], *, protocol: str | None = None,
             profile: DriveProfile | None = None, period: float | None = None,
             axis: str | None = None) -> IdentData:
    """The :class:`IdentData` of a log: a dobhil run's loop records, or -- a CAN log imported
    with ``dobhil log import``, frames only -- its frames decoded with ``profile`` (required
    then; ``period``: its control period, default the round period the stamps of its motion
    frames scatter around, :func:`dobhil.identify.period.frame_lattice`).
    ``protocol``: the protocol the user expects (their drive profile's); a log of
    another one is refused. A log without motion is refused (nothing to identify).
    LogFileError / ConfigError, one line, otherwise. ``axis``: the axis of a several-axis log
    (its own records and its bus' frames, :func:`~dobhil.recording.axes.axis_log`; a
    several-axis log without it is refused naming its axes)."""
    from dobhil.drives.decode import recorded_profile
    from dobhil.recording.axes import axis_log, is_axes_log
    from dobhil.recording.reader import open_log
    name = os.fspath(path)
    with open_log(path) as whole:
        log: Any = axis_log(whole, axis) if axis is not None or is_axes_log(whole) else whole
        if not all(t in log.topics() for t in _TOPICS):
            data = _from_frames(log, name, profile, period)
        else:
            if log.config is None:
                raise LogFileError(f"{name}: no 'config' metadata (not a recorded run?)")
            if period is not None:
                raise ConfigError(f"--period {period:g}: {name} records its own period "
                                  f"({log.config.loop.period:g} s); --period is for a CAN log without one")
            recorded_drive = recorded_profile(log.metadata.get("drive"), name)
            config = log.config
            cycles = _loop_records(log, name)
            recorded = {k: float(v) for k, v in config.flat().items() if k.split(".")[0] in RECORDED_SECTIONS
                        and isinstance(v, (int, float)) and not isinstance(v, bool)}
            data = _samples(cycles, config.loop.period, name, recorded_drive.protocol, recorded)
            data = replace(data, torque=applied_torque(data.torque, recorded_drive))
    expected = protocol if protocol is not None else (profile.protocol if profile is not None else None)
    if expected is not None and data.protocol != expected:
        raise ConfigError(f"{name}: recorded with a {data.protocol!r} drive, but the profile given is "
                          f"{expected!r}; identify a log with the profile of its own protocol")
    check_motion(data)
    return data


def applied_torque(sent: NDArray[np.float64], profile: DriveProfile) -> NDArray[np.float64]:
    """The torque the drive applies for each command ``sent`` (the loop's ``u_sat``): a
    protocol that sends the torque as an integer code applies the code's value, not the
    command (the codec's model, :class:`~dobhil.drives.plugin.CodecQuantisation`: one step
    on a grid through the torque a zero command applies, truncated in the firmware's sense
    of rotation, or rounded). Fitted to the command instead, a truncating codec's mean
    offset of half a step and its staircase are torque the model does not see: an AK80-9
    free run (12 bits, 8.8 mN m a code) gave an inertia 10 % low and a delay 0.3 periods
    short, the same run's frames imported (decoded as the drive decodes them) the truth
    (tests/identify/test_data.py). A codec of floats returns ``sent`` unchanged."""
    from dobhil.drives.registry import protocol
    codec = protocol(profile.protocol).quantisation(profile)
    if codec is None or not codec.torque > 0.0:
        return sent
    # the float codecs work in single precision: a command on a code boundary stays on its code
    codes = (sent - codec.zero_torque) / codec.torque
    nearest = np.round(codes)
    on_code = np.abs(codes - nearest) <= 1e-6
    if not codec.truncates:
        whole = nearest
    elif codec.direction >= 0:
        whole = np.where(on_code, nearest, np.floor(codes))   # decoded in (true - step, true]
    else:
        whole = np.where(on_code, nearest, np.ceil(codes))    # reversed axis: [true, true + step)
    return np.asarray(codec.zero_torque + whole * codec.torque, dtype=float)


# -- a CAN log imported: frames only --------------------------------------------------------

class _Sink:
    """The bus of the decoding emulator: its replies go nowhere, it reads nothing."""

    channel_info = "identify decoding"

    def send(self, msg: object, timeout: float | None = None) -> None:
        pass

    def recv(self, timeout: float | None = None) -> None:
        return None

    def shutdown(self) -> None:
        pass


def _from_frames(log: object, name: str, profile: DriveProfile | None, period: float | None) -> IdentData:
    """Samples of a frames-only log: the feedback decoded by the profile's drive class (as a
    replay does), the torque by the profile's emulated drive -- the torque its plant would
    receive, protocol state included (an RPDO waits for its SYNC, a disabled axis applies 0).
    A motion frame's sample is the deadline its stamp belongs to; its torque is what the
    frames before the next motion frame left applied. The period is the round period the
    motion frames' stamps scatter around, unless given, and a deadline no motion frame came
    for breaks the samples as a skipped cycle does (:func:`~dobhil.identify.period.frame_lattice`).

    Both decoders get every frame, whichever topic holds it: the recorded direction is the
    recording program's view, not the drive's. A capture by another program on the bus
    (``candump -l``: its log format has no direction, python-can reads every line as received,
    ``can/io/canutils.py``) holds the host's commands on ``/can/rx``; and a command another
    host sent to the drive reached its plant all the same. Each decoder takes only the frames
    of its own direction and node (a drive's feedback is nothing to its emulator, a command
    no motion to the drive class)."""
    import can

    from dobhil.drives.decode import decode_motion
    from dobhil.emulator.plant import Plant
    from dobhil.drives.registry import make_emulated_drive
    from dobhil.recording.schemas import can_frame_message
    if not {"/can/rx", "/can/tx"} & set(log.topics()):  # type: ignore[attr-defined]
        raise LogFileError(f"{name}: neither loop records ({' and '.join(_TOPICS)}) nor CAN frames (/can/rx, "
                           "/can/tx); identify reads a run recorded by dobhil or a CAN log imported with dobhil "
                           "log import")
    if profile is None:
        raise ConfigError(f"{name}: a CAN log without a recorded drive profile; give the drive's profile "
                          "with --drive NAME (a profile name, as dobhil run takes it, or a .yaml path)")
    rx: list[can.Message] = []
    tx: list[can.Message] = []
    try:
        for topic, t, p in log.iter_messages(("/can/rx", "/can/tx")):  # type: ignore[attr-defined]
            (rx if topic == "/can/rx" else tx).append(can_frame_message(p, t))
    except (KeyError, TypeError, ValueError) as exc:
        raise LogFileError(f"{name}: a recorded frame does not match its schema "
                           f"({exception_line(exc)})") from None
    # stable: at one stamp the received frames stay first, as in the lists' order before
    frames = sorted(rx + tx, key=lambda m: m.timestamp)
    motion = decode_motion(profile, frames)
    if len(motion) < 2 * MIN_SEGMENT:
        raise ConfigError(f"{name}: {len(motion)} frames decode as motion feedback of a {profile.protocol!r} drive "
                          f"(node {profile.node_id}); is the log of another protocol or node than profile "
                          f"{profile.name or profile.protocol!r}?")
    from dobhil.identify.period import frame_lattice
    lattice = frame_lattice(np.array([m[0] for m in motion]))
    if period is None:
        period = lattice.period   # the round period the stamps scatter around
    elif math.isfinite(lattice.period) and lattice.period > 0.0 and not lattice.agrees(period):
        # refused, not warned: the samples keep their deadlines whatever the period, so another
        # one only rescales time -- the inertia with its square, the delay and friction with it
        # -- and an overlay carries that to the next run; the stamps tell the period to a host
        # clock's skew (SNAP), a period outside that is a typo or a clock the log cannot vouch for
        raise ConfigError(f"--period {period:g}: {name}'s motion frames come every {lattice.period:g} s "
                          f"(their stamps allow {lattice.slope - lattice.spread:.7g} to "
                          f"{lattice.slope + lattice.spread:.7g} s); leave --period out or give one in that range")
    if not (math.isfinite(period) and period > 0.0):
        raise ConfigError(f"{name}: no control period (the motion frames' timestamps do not increase); "
                          "give it with --period SECONDS")
    emulated = make_emulated_drive(_Sink(), profile, Plant(inertia=1.0))  # type: ignore[arg-type]
    torque, i = [], 0
    for k in range(len(motion)):
        until = motion[k + 1][0] if k + 1 < len(motion) else math.inf
        while i < len(frames) and frames[i].timestamp < until:
            emulated.deliver(frames[i])
            i += 1
        torque.append(emulated.applied_torque)
    # a deadline no motion frame came for (lost, or never sent) is a gap, as a skipped cycle
    rows = {int(k): [p, v, u] for k, (_, p, v), u in zip(lattice.number, motion, torque)}
    return _samples(rows, period, name, profile.protocol, {})


def _loop_records(log: object, name: str) -> dict[int, list[float]]:
    """cycle -> [position, velocity, u_sat] of every cycle that has both records."""
    feedback: dict[int, tuple[float, float]] = {}
    torque: dict[int, float] = {}
    try:
        for topic, _, p in log.iter_messages(_TOPICS):  # type: ignore[attr-defined]
            cycle = int(p["cycle"])
            if cycle < 0:
                continue  # the feedback controller.initialize used, before cycle 0
            if topic == "/controller":
                torque[cycle] = _number(p["u_sat"])
            else:
                feedback[cycle] = (_number(p["position"]), _number(p["velocity"]))
    except (KeyError, TypeError, ValueError) as exc:
        raise LogFileError(f"{name}: a recorded message does not match its schema "
                           f"({exception_line(exc)})") from None
    return {c: [*feedback[c], torque[c]] for c in sorted(torque) if c in feedback}


def _number(value: object) -> float:
    return math.nan if value is None else float(value)  # type: ignore[arg-type]


def _samples(cycles: Mapping[int, list[float]], period: float, name: str, protocol: str,
             recorded: Mapping[str, float]) -> IdentData:
    """The longest run of consecutive, finite cycles (the first of equally long ones). A
    late real-time cycle skips the frames that came meanwhile, and their cycle numbers with
    them (dobhil/runtime/loop.py), so a gap breaks the uniform sampling the fit needs; the
    safe stop's zero command is no cycle."""
    first, length = _longest_run(cycles)
    if length < 2 * MIN_SEGMENT:
        raise LogFileError(f"{name}: {length} consecutive usable control cycles at most (of {len(cycles)}: the "
                           f"loop skipped cycles); identify needs at least {2 * MIN_SEGMENT}")
    a = np.asarray([cycles[k] for k in range(first, first + length)], dtype=float)
    return IdentData(period=period, t=np.arange(a.shape[0], dtype=float) * period, torque=a[:, 2], position=a[:, 0],
                     velocity=a[:, 1], source=os.path.basename(name), protocol=protocol,
                     recorded=MappingProxyType(dict(recorded)), first_cycle=first, cycles=len(cycles))


def _longest_run(cycles: Mapping[int, list[float]]) -> tuple[int, int]:
    """(first cycle, length) of the longest run of consecutive cycles with finite values."""
    best = (0, 0)
    start, last = 0, -2
    for k in sorted(cycles):
        if not all(math.isfinite(v) for v in cycles[k]):
            last = -2
            continue
        if k != last + 1:
            start = k
        last = k
        if last - start + 1 > best[1]:
            best = (start, last - start + 1)
    return best


def check_motion(data: IdentData) -> None:
    """ConfigError when the log cannot excite anything: the position never changed, or the
    torque never did (one line naming the log and what a useful log needs)."""
    what = data.source or "data"
    if np.ptp(data.position) == 0.0:
        raise ConfigError(f"{what}: the position never changes (no motion); identify needs a run that "
                          "moves the servo (e.g. configs identify-free.yaml)")
    if np.ptp(data.torque) == 0.0:
        raise ConfigError(f"{what}: the torque never changes; identify needs an excitation "
                          "(a chirp, prbs or multisine reference)")


# -- segments ------------------------------------------------------------------------------

def parse_segment(text: str, data: IdentData) -> Segment:
    """``T0:T1`` or ``T0:T1:free|contact`` (seconds from the first cycle) -> a Segment; the
    kind, when not given, is the kind :func:`find_segments` finds for most of its samples."""
    parts = text.split(":")
    if len(parts) not in (2, 3):
        raise ConfigError(f"--segment {text!r}: expected T0:T1 or T0:T1:free|contact (seconds)")
    try:
        t0, t1 = float(parts[0]), float(parts[1])
    except ValueError:
        raise ConfigError(f"--segment {text!r}: T0 and T1 must be numbers of seconds") from None
    end = data.samples * data.period
    if not (math.isfinite(t0) and math.isfinite(t1)):
        raise ConfigError(f"--segment {text!r}: T0 and T1 must be finite numbers of seconds "
                          f"(0 <= T0 < T1 <= {end:g} s)")
    if not t0 < t1:  # said apart from a range outside the log: the order is the mistake, not the times
        raise ConfigError(f"--segment {text!r}: T0 must be below T1 (the segment runs from T0 to T1 seconds; "
                          f"0 <= T0 < T1 <= {end:g} s)")
    if not (0.0 <= t0 and t1 <= end + 0.5 * data.period):
        raise ConfigError(f"--segment {text!r}: outside the log; expected 0 <= T0 < T1 <= {end:g} s")
    start, stop = int(round(t0 / data.period)), min(int(round(t1 / data.period)), data.samples)
    if stop - start < MIN_SEGMENT:
        raise ConfigError(f"--segment {text!r}: {stop - start} samples; a segment needs at least "
                          f"{MIN_SEGMENT} ({MIN_SEGMENT * data.period:g} s)")
    if len(parts) == 3:
        if parts[2] not in KINDS:
            raise ConfigError(f"--segment {text!r}: kind {parts[2]!r}; expected one of {', '.join(KINDS)}")
        return Segment(start, stop, parts[2])
    contact = contact_mask(data)[start:stop]
    return Segment(start, stop, CONTACT if 2 * int(contact.sum()) > contact.size else FREE)


def find_segments(data: IdentData) -> tuple[Segment, ...]:
    """The free-motion and contact segments of the whole log, found from the data."""
    return segments_of(contact_mask(data))


def segments_of(contact: NDArray[np.bool_]) -> tuple[Segment, ...]:
    """Maximal runs of one kind; a run shorter than :data:`MIN_SEGMENT` joins the one before
    (a contact bouncing open for a few samples is not a free-motion experiment), and free runs
    between two contact runs join them: the servo left the environment and came back, one
    contact experiment that the model (which switches in and out of contact itself) follows
    through -- cut into pieces, each would have to start from a state the fit does not know."""
    edges = np.flatnonzero(np.diff(contact.astype(np.int8))) + 1
    bounds = [0, *edges.tolist(), int(contact.size)]
    runs: list[list[int]] = []
    for a, b in zip(bounds[:-1], bounds[1:]):
        kind = int(contact[a])
        if runs and (b - a < MIN_SEGMENT or runs[-1][2] == kind):
            runs[-1][1] = b
        elif runs and runs[-1][1] - runs[-1][0] < MIN_SEGMENT:
            runs[-1][1], runs[-1][2] = b, kind
        else:
            runs.append([a, b, kind])
    touching = [i for i, r in enumerate(runs) if r[2]]
    if touching:
        first, last = touching[0], touching[-1]
        runs[first:last + 1] = [[runs[first][0], runs[last][1], 1]]
    return tuple(Segment(a, b, CONTACT if k else FREE) for a, b, k in runs)


def contact_mask(data: IdentData) -> NDArray[np.bool_]:
    """Per sample, whether the environment is engaged: ``q >= threshold`` for the threshold
    that best explains the sampled acceleration with a restoring spring (all False when no
    spring term passes the F test)."""
    q, n = data.position, data.samples
    y = np.diff(data.velocity)                        # dq[k+1] - dq[k], k = LAGS .. n-2
    rows = np.arange(_LAGS, n - 1)
    base = np.column_stack([*(data.torque[rows - j] for j in range(_LAGS)), data.velocity[rows],
                            np.ones(rows.size)])
    target, qk = y[rows], q[rows]
    # each candidate adds one column z = max(q - threshold, 0) to the free model: its residual
    # sum of squares follows from z's part orthogonal to the free model's columns (one QR for all)
    basis, _ = np.linalg.qr(base)
    r = target - basis @ (basis.T @ target)
    rss_free = float(r @ r)
    best: tuple[float, float, float] | None = None    # (rss, threshold, spring coefficient)
    candidates = _thresholds(qk)
    for chunk in np.array_split(candidates, max(1, candidates.size // 25)):
        z = np.maximum(qk[:, None] - chunk[None, :], 0.0)
        zp = z - basis @ (basis.T @ z)
        denom, num = np.einsum("ij,ij->j", zp, zp), zp.T @ r
        engaged = (qk[:, None] >= chunk[None, :]).sum(axis=0)
        for j in np.flatnonzero((denom > 0.0) & (engaged >= MIN_SEGMENT)):
            coef = num[j] / denom[j]
            rss = rss_free - coef * num[j]
            if best is None or rss < best[0]:
                best = (float(rss), float(chunk[j]), float(coef))
    if best is None or best[2] >= 0.0 or not _significant(rss_free, best[0], target.size, base.shape[1] + 2):
        return np.zeros(n, dtype=bool)
    return q >= best[1]


def _thresholds(q: Array) -> Array:
    """Candidate contact positions: quantiles of the measured positions, plus one below them
    all (a run in contact throughout)."""
    levels = np.unique(np.quantile(q, np.linspace(0.0, 0.95, 100)))
    return np.concatenate([[q.min() - 1.0], levels])


def _significant(rss0: float, rss1: float, n: int, params: int) -> bool:
    """F test of the spring (and threshold) against the free model."""
    from scipy.special import fdtrc  # the F distribution's survival function (scipy.stats imports seconds)
    if rss1 <= 0.0:
        return rss0 > 0.0
    stat = ((rss0 - rss1) / 2.0) / (rss1 / max(n - params, 1))
    return bool(fdtrc(2, max(n - params, 1), stat) < _ALPHA)


# -- several logs fitted together ------------------------------------------------------------

#: zero-torque samples between two logs joined for one fit: more than any delay the fit
#: searches and the start estimate's smoothing reach, so no torque of one log acts in the next
#: (each log starts at rest, every command before its cycle 0 being 0)
JOIN_GAP: Final = 32


@dataclass(frozen=True)
class Part:
    """Where one log's samples are in a joined :class:`IdentData`: ``offset`` .. ``offset +
    samples``, and the segments found in (or given for) it, in the joined sample numbering."""

    source: str
    offset: int
    samples: int
    segments: tuple[Segment, ...]

    def local(self, segment: Segment, period: float) -> tuple[float, float]:
        """The segment's times [s] from this log's first cycle."""
        return (segment.start - self.offset) * period, (segment.stop - self.offset) * period


def join(parts: Sequence[tuple[IdentData, Sequence[Segment]]]) -> tuple[IdentData, tuple[Part, ...]]:
    """Several logs of the same drive as one record, so one fit shares the plant between them
    (a free run's friction with a contact run's environment: a contact-only record cannot tell
    the servo's viscous friction from the environment's damping). The logs follow each other
    with :data:`JOIN_GAP` samples of zero torque between them, which no segment covers; the
    segments shift with their log. ConfigError (one line) when the logs differ in period or
    protocol."""
    if not parts:
        raise ValueError("join: no log")
    first = parts[0][0]
    if len(parts) == 1:
        return first, (Part(first.source, 0, first.samples, tuple(parts[0][1])),)
    pieces: dict[str, list[Array]] = {"torque": [], "position": [], "velocity": []}
    placed: list[Part] = []
    offset = 0
    for data, segments in parts:
        if not math.isclose(data.period, first.period, rel_tol=1e-9):
            raise ConfigError(f"{data.source}: period {data.period:g} s, but {first.source} has {first.period:g} s; "
                              "logs identified together need the same period")
        if data.protocol != first.protocol:
            raise ConfigError(f"{data.source}: recorded with a {data.protocol!r} drive, but {first.source} with "
                              f"a {first.protocol!r} one; logs identified together need the same drive")
        if offset:
            # the gap holds the next log's first sample: at rest there, no torque
            pieces["torque"].append(np.zeros(JOIN_GAP))
            pieces["position"].append(np.full(JOIN_GAP, data.position[0]))
            pieces["velocity"].append(np.zeros(JOIN_GAP))
            offset += JOIN_GAP
        pieces["torque"].append(data.torque)
        pieces["position"].append(data.position)
        pieces["velocity"].append(data.velocity)
        placed.append(Part(data.source, offset, data.samples,
                           tuple(Segment(s.start + offset, s.stop + offset, s.kind) for s in segments)))
        offset += data.samples
    # the recorded config keys the logs agree on (the free run's environment is not the contact run's)
    recorded = {k: v for k, v in first.recorded.items() if all(d.recorded.get(k) == v for d, _ in parts)}
    joined = IdentData(period=first.period, t=np.arange(offset, dtype=float) * first.period,
                       torque=np.concatenate(pieces["torque"]), position=np.concatenate(pieces["position"]),
                       velocity=np.concatenate(pieces["velocity"]),
                       source="+".join(data.source for data, _ in parts), protocol=first.protocol,
                       recorded=MappingProxyType(recorded))
    return joined, tuple(placed)


__all__ = ["CONTACT", "FREE", "JOIN_GAP", "KINDS", "MIN_SEGMENT", "IdentData", "Part", "Segment", "check_motion",
           "contact_mask", "find_segments", "join", "parse_segment", "read_log", "segments_of"]
