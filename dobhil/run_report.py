"""The analysis of a recorded run (``dobhil report``): force response, estimation, timing, bus.

:func:`load_run` reads a dobhil MCAP log into per-cycle arrays (:class:`RunData`);
:func:`analyse` computes the summary:

- step metrics of the force response, for steps taken in contact only: reference steps
  are detected in ``tau_ref`` (a jump larger than 5 % of its range, and the start when
  the reference does not start at 0); a step is in contact when the servo touches the
  environment from the step to the next one (:func:`contact_mask`: the emulator's true
  position where the log has it, else the measured position, against the config's
  ``environment.contact_position``). A step that starts in free motion (the demo's first:
  the servo crosses a gap, then hits the environment) is listed without metrics: its
  "overshoot" would be the impact. The estimated interaction torque after each step in
  contact is normalised to the step and measured with
  :func:`dobhil.analysis.metrics.step_metrics`;
- RMS tracking error ``tau_ref - tau_int_hat`` (and against the true torque when emulated);
- a torque-mode run (``loop.mode: torque``, an open-loop excitation for identification)
  has no force loop: its reference is a torque, so no steps, tracking or prediction
  (the keys stay, without values), and the text says so;
- estimation error ``tau_int_hat - tau_int`` against the emulator's ground truth;
- loop timing statistics, overruns;
- CAN frames per second and bus load over the loop's cycles (:func:`_loop_frames`: the
  frames of enabling before the first and of the stop after the last left out): bits per
  frame 47 + 8 DLC plus the worst-case stuff bits ``floor((34 + 8 DLC - 1) / 4)``
  (11-bit identifiers; 29-bit: 67 + 8 DLC and
  ``floor((54 + 8 DLC - 1) / 4)``) at ``drive.bitrate``; a CAN FD frame by ISO 11898-1's
  FD framing, its data phase at the recorded data bit rate when it switched bit rate
  (:func:`dobhil.drives.bus_load.message_bits`);
- command latency: per command frame on ``/can/tx``, the log time since the last frame
  received on ``/can/rx`` (the feedback that triggered the cycle), against the latency the
  sampled analysis assumed (``design.input_delay`` + ``design.delay_samples`` periods): it
  matches when the median and the 99th percentile are both within
  ``LATENCY_TOLERANCE`` periods of it (the analysis models one fixed delay, so a spread
  beyond that is not modelled); in lockstep the log clock is simulated and the latency is
  not measurable. The section says which clock each latency is on (``clock``: always the
  log's; ``sample_clock``: the drive's sample latency of ``loop_timing``, both stamps the
  bus's receive stamps, or the feedback's since the host's send of the frame sampled at,
  as the run recorded it in ``run.sample_clock``);
- records the recorder dropped (``/events`` ``kind=loss``);
- the measured force response against the sampled closed loop of the recorded config
  (``LoopSystems.build(params, sampled=True).system("closed_loop")`` driven by the
  recorded reference with ``control.forced_response``): RMS and max difference, from the
  first step taken in contact on (the loop at rest at the reference before it), over the
  samples in contact: the analysed loop is the loop in contact.

A several-axis log (:mod:`dobhil.recording.axeslog`) is reported axis by axis
(:func:`report_axes`): each axis' summary as above (its bus' load; its command latency from
its own drive's frames), then the loop's shared timing (per cycle the slowest axis'
execution time and period error, an overrun when any axis overran) and each bus' load.
"""

from __future__ import annotations

import json
import os
from array import array
from collections import Counter
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Final

import numpy as np
from numpy.typing import NDArray

from dobhil.config.schema import Config
from dobhil.drives.bus_load import message_bits
from dobhil.drives.timing import with_command_delay
from dobhil.drives.decode import recorded_profile
from dobhil.errors import LogFileError, exception_line
from dobhil.recording.axes import AxisLog, axis_log, axis_logs
from dobhil.recording.codes import ProtocolCodes
from dobhil.recording.reader import LogFile, open_log
from dobhil.recording.schemas import feedback_state

Array = NDArray[np.float64]
ProgressFn = Callable[[int], None]

_CONTROLLER: Final = ("tau_ref", "tau_int_hat", "tau_dis_hat", "tau_per", "u_unsat", "u_sat")
#: A reference jump larger than this fraction of the reference range is a step.
STEP_FRACTION: Final = 0.05
#: Largest command delay [samples] the prediction models (each sample is a state of the model).
MAX_PREDICTION_DELAY: Final = 1000
#: The measured latency matches the analysis' within this many loop periods (median and p99).
LATENCY_TOLERANCE: Final = 0.1
#: ``latency.clock``: the command latency is taken from log times, the recorder's clock
LOG_CLOCK: Final = "log"
#: ``latency.clock_text``: what the log times of the command latency are
LOG_CLOCK_TEXT: Final = "log times: feedback frame read by the loop -> command frame sent"
#: ``latency.sample_clock`` (the run's ``run.sample_clock``, :attr:`dobhil.drives.base.Drive.sample_clock`)
#: -> what the two stamps of the sample latency are (``latency.sample_clock_text``)
SAMPLE_CLOCKS: Final = {
    "bus": "bus receive stamps of both frames: the drive's sample instant and its feedback",
    "sent": "the feedback's bus receive stamp since the host's wall clock just after it sent the "
            "frame the drive sampled at",
}


@dataclass
class RunData:
    """Per-cycle arrays of one recorded run (NaN where a value was not recorded)."""

    path: str
    config: Config | None
    metadata: Mapping[str, Mapping[str, str]]
    t: Array
    signals: dict[str, Array] = field(default_factory=dict)
    frames: dict[str, NDArray[np.int64]] = field(default_factory=dict)   # topic -> DLCs
    #: topic -> how many frames of each (DLC, extended id, CAN FD, bit rate switch)
    frame_kinds: dict[str, Counter[tuple[int, bool, bool, bool]]] = field(default_factory=dict)
    span_s: float = 0.0   # first to last CAN frame, less a recovered log's gaps (:func:`gaps_within`)
    frame_times: dict[str, NDArray[np.int64]] = field(default_factory=dict)  # topic -> log times [ns]
    events: list[dict[str, Any]] = field(default_factory=list)
    #: each change of the drive's state (dobhil's and its own codes, with their names)
    states: list[dict[str, Any]] = field(default_factory=list)
    axis: str = "axis"   # the axis' name ("axis" in a single-axis log)
    bus: str = ""        # the name of the axis' bus
    coupled_to: tuple[str, ...] = ()   # the axes it is coupled to (AxisLog.coupled_to)

    def has(self, name: str) -> bool:
        return name in self.signals and bool(np.any(np.isfinite(self.signals[name])))

    def __getitem__(self, name: str) -> Array:
        return self.signals[name]


#: the topics of an axis a report reads (:func:`load_axis`)
REPORT_TOPICS = ("/controller", "/drive/feedback", "/emulator/truth", "/loop", "/can/rx", "/can/tx", "/events")
#: messages read between two progress updates
PROGRESS_STEP = 1000


def report_messages(log: LogFile) -> int:
    """The messages a report of ``log`` reads (every axis' topics, its bus' frames once per
    axis on it): the total its progress counts to."""
    return sum(axis.message_count(REPORT_TOPICS) for axis in axis_logs(log))


def load_run(path: str | os.PathLike[str], progress: ProgressFn | None = None, axis: str | None = None) -> RunData:
    """Read a dobhil run log (checked by :class:`~dobhil.recording.reader.LogFile`): its
    one axis, or ``axis`` of a several-axis log."""
    return load_axis(axis_log(open_log(path), axis), progress)


class Columns:
    """One topic's records as typed columns (:mod:`array`: 8 bytes a number), not a tuple of
    Python objects per record (about 40 bytes a number, 180 a CAN frame): a report of a long
    log holds each cycle's numbers once, the way its arrays will."""

    def __init__(self, codes: str) -> None:
        self.columns: list[array[Any]] = [array(code) for code in codes]

    def add(self, *values: float) -> None:
        for column, value in zip(self.columns, values):
            column.append(value)

    def __len__(self) -> int:
        return len(self.columns[0])

    def numpy(self, i: int) -> NDArray[Any]:
        """Column ``i`` as an array on the same memory (no copy: a long log's columns are
        the report's largest objects)."""
        column = self.columns[i]
        return np.frombuffer(column, dtype=column.typecode)


#: the columns each topic's records keep (:func:`_take`): q an integer (cycle, log time), d a float
_COLUMNS: Final = {"controller": "qq" + "d" * len(_CONTROLLER), "feedback": "qdd", "truth": "dddd",
                   "loop": "qdddd", "can": "bqqq"}
#: ``can`` records' topic column
_CAN_TOPICS: Final = ("/can/rx", "/can/tx")


def load_axis(log: AxisLog, progress: ProgressFn | None = None) -> RunData:
    """Read one axis of a checked log. The command latency's frames are the axis' drive's
    own (its ``frame_ids`` as recorded, where another axis shares its bus); the bus load
    counts every frame of the bus."""
    name = os.fspath(log.path)
    own = log.frame_ids
    per: dict[str, Any] = {k: Columns(codes) for k, codes in _COLUMNS.items()}
    per["states"] = []
    frame_times = {topic: array("q") for topic in _CAN_TOPICS}
    events: list[dict[str, Any]] = []
    topics = REPORT_TOPICS
    read = 0
    with log:
        log.require_topic("/controller")
        try:
            for i, (topic, t, p) in enumerate(log.iter_messages(topics)):
                _take(topic, t, p, per, events)
                if topic in frame_times and (own is None or p["arbitration_id"] in own):
                    frame_times[topic].append(t)
                read = i + 1
                if progress is not None and read % PROGRESS_STEP == 0:
                    progress(PROGRESS_STEP)
            if progress is not None and read % PROGRESS_STEP:   # the last ones: the count ends at the total
                progress(read % PROGRESS_STEP)
        except (KeyError, TypeError, ValueError) as exc:
            raise LogFileError(f"{name}: a recorded message does not match its schema "
                               f"({exception_line(exc)})") from None
        run = _assemble(name, log.config, log.metadata, per, events)
        run.states = drive_states(per["states"], _codes(log))
    run.frame_times = {topic: np.frombuffer(times, dtype=np.int64) for topic, times in frame_times.items()}
    run.axis, run.bus, run.coupled_to = log.name, log.bus, log.coupled_to
    return run


def _codes(log: Any) -> ProtocolCodes:
    """The names of the run's drive codes, from its recorded profile (numbers without one)."""
    try:
        return ProtocolCodes(recorded_profile(log.metadata.get("drive"), os.fspath(log.path)))
    except LogFileError:
        return ProtocolCodes()


def drive_states(changes: list[tuple[Any, ...]], codes: ProtocolCodes) -> list[dict[str, Any]]:
    """The drive's state changes, ``(log time, cycle, payload)`` each, as the report gives
    them: the names the log recorded, else (logs before them) ``codes``' names."""
    out = []
    t0 = changes[0][0] if changes else 0
    for t, cycle, p in changes:
        drive_state, state, error = feedback_state(p)
        out.append({"time_s": (t - t0) / 1e9, "cycle": cycle, "drive_state": drive_state, "protocol_state": state,
                    "protocol_state_name": p.get("protocol_state_name") or codes.state_name(state),
                    "protocol_error": error,
                    "protocol_error_text": p.get("protocol_error_text") or codes.error_text(error)})
    return out


def _take(topic: str, t: int, p: dict[str, Any], per: dict[str, Any], events: list[dict[str, Any]]) -> None:
    if topic == "/controller":
        per["controller"].add(p["cycle"], t, *(_f(p[k]) for k in _CONTROLLER))
    elif topic == "/drive/feedback":
        states = per["states"]
        if not states or feedback_state(states[-1][2]) != feedback_state(p):
            states.append((t, p.get("cycle", -1), p))
        if p.get("cycle", 0) >= 0:
            per["feedback"].add(p.get("cycle", len(per["feedback"])), _f(p["position"]), _f(p["velocity"]))
    elif topic == "/emulator/truth":
        per["truth"].add(_f(p["q"]), _f(p["dq"]), _f(p["tau_motor"]), _f(p["tau_int"]))
    elif topic == "/loop":
        per["loop"].add(p["cycle"], _f(p["period_error"]), _f(p["exec_time"]), float(bool(p["overrun"])),
                        _f(p.get("sample_latency")))   # absent in logs before it
    elif topic == "/events":
        events.append({**p, "log_time_ns": t})
    else:   # a frame's kind packed in one number: DLC, then extended id, CAN FD, bit rate switch
        per["can"].add(_CAN_TOPICS.index(topic), t, int(p["dlc"]),
                       bool(p["is_extended_id"]) | bool(p["is_fd"]) << 1 | bool(p["bitrate_switch"]) << 2)


def _f(v: Any) -> float:
    return float("nan") if v is None else float(v)


def _by_cycle(records: Columns, cycles: NDArray[np.int64]) -> Array:
    """The records' values (every column after the first, their cycle) on the rows of
    ``cycles`` (sorted; a cycle recorded twice: its last row), NaN where a cycle has none; of
    a cycle recorded more than once, the last record."""
    width = len(records.columns) - 1
    out = np.full((cycles.size, width), np.nan)
    keys = records.numpy(0)
    row = np.searchsorted(cycles, keys, side="right") - 1
    known = row >= 0
    known[known] = cycles[row[known]] == keys[known]
    rows = row[known]
    if not rows.size:
        return out
    # the last record of each row, as the log has them in order (a later record wins)
    _, first_from_end = np.unique(rows[::-1], return_index=True)
    last = rows.size - 1 - first_from_end
    values = np.column_stack([records.numpy(i)[known] for i in range(1, width + 1)])
    out[rows[last]] = values[last]
    return out


def gaps_within(name: str, meta: Mapping[str, Mapping[str, str]], start: int, end: int) -> int:
    """The log time [ns] from ``start`` to ``end`` that a log ``dobhil log recover`` saved
    with gaps lost: each gap of its ``recover`` metadata (the log times copied just before
    and after a stretch of lost messages, :mod:`dobhil.recording.recover`) clipped to them.
    The frames of those stretches are lost too, so a rate over the whole span would read low
    by the time lost (a bus load of 22 % for 26 %)."""
    from dobhil.recording.recover import RECOVER_METADATA
    raw = meta.get(RECOVER_METADATA, {}).get("gaps")
    if not raw:
        return 0
    try:
        gaps = [(start if g[0] is None else int(g[0]), int(g[1])) for g in json.loads(raw)]
    except (ValueError, TypeError, IndexError, KeyError):
        raise LogFileError(f"{name}: invalid metadata {RECOVER_METADATA}.gaps: {raw!r}") from None
    return sum(max(0, min(b, end) - max(a, start)) for a, b in gaps)


def _loop_frames(can: Columns, stamps: NDArray[np.int64], period: float | None
                 ) -> tuple[dict[str, NDArray[np.int64]], dict[str, Counter[tuple[int, bool, bool, bool]]], list[Any]]:
    """The CAN frames of the loop's cycles: DLCs and kinds per topic, and the window's
    bounds [ns]. From the first cycle's record to the last's (excluded): as many periods as
    cycles less one, each with one cycle's feedback and command whatever their phase
    (received before a record, sent after it, or all at its time in lockstep). The frames
    of enabling before the loop and of its stop after (the drive's heartbeats while the stop
    waits out its watchdog, 0.1 s on the demo) are no cycle's: counted in, they made a
    3-cycle run's 1 kHz commands read 120 frames/s and its load 15 % for the 27 % of the bus
    budget (``dobhil check``). Without a recorded config, every frame, from the first to
    the last."""
    topic, times, dlc, kind = (can.numpy(i) for i in range(4))
    bounds: list[Any]
    if period is not None:   # one cycle: an empty window, no rate rather than one of enabling and stop
        lo, hi = int(stamps[0]), int(stamps[-1])
        inside = (times >= lo) & (times < hi)
        bounds = [lo, hi]
    else:
        inside = np.ones(times.size, dtype=bool)
        bounds = [int(times.min()), int(times.max())] if times.size else [None, None]
    frames: dict[str, NDArray[np.int64]] = {}
    ext: dict[str, Counter[tuple[int, bool, bool, bool]]] = {}
    for code, name in enumerate(_CAN_TOPICS):
        frames[name] = dlc[inside & (topic == code)]
        kinds, counts = np.unique(frames[name] * 8 + kind[inside & (topic == code)], return_counts=True)
        ext[name] = Counter({(int(k) // 8, bool(k & 1), bool(k & 2), bool(k & 4)): int(c)
                             for k, c in zip(kinds, counts)})
    return frames, ext, bounds


def _assemble(name: str, config: Config | None, meta: Mapping[str, Mapping[str, str]],
              per: dict[str, Any], events: list[dict[str, Any]]) -> RunData:
    records: Columns = per["controller"]
    if not len(records):
        raise LogFileError(f"{name}: no /controller records (the run stopped before its first cycle)")
    cycle, stamp = records.numpy(0), records.numpy(1)
    order = np.lexsort((stamp, cycle))   # by cycle, then log time
    cycles, stamps = cycle[order], stamp[order]
    n = cycles.size
    frames, ext, bounds = _loop_frames(per["can"], stamps, None if config is None else config.loop.period)
    # time from cycle 0: a log recovered without its start (its first chunk damaged) begins
    # at a later cycle, which is that many periods into the run, not at 0 s
    first = int(cycles[0])
    origin = int(stamps[0]) - (round(first * config.loop.period * 1e9) if config is not None and first > 0 else 0)
    data = RunData(path=name, config=config, metadata=meta, t=(stamps - origin) / 1e9,
                   frames=frames, frame_kinds=ext, events=events,
                   span_s=0.0 if bounds[0] is None else
                   (bounds[1] - bounds[0] - gaps_within(name, meta, bounds[0], bounds[1])) / 1e9)
    data.signals.update({k: records.numpy(i + 2)[order] for i, k in enumerate(_CONTROLLER)})
    data.signals["cycle"] = cycles.astype(float)
    fb = _by_cycle(per["feedback"], cycles)
    data.signals.update(q=fb[:, 0], dq=fb[:, 1])
    loop = _by_cycle(per["loop"], cycles)
    data.signals.update(period_error=loop[:, 0], exec_time=loop[:, 1], overrun=loop[:, 2],
                        sample_latency=loop[:, 3])
    truth = np.full((n, 4), np.nan)
    recorded = min(len(per["truth"]), n)   # in the log's order, one a cycle
    for i in range(4):
        truth[:recorded, i] = per["truth"].numpy(i)[:recorded]
    data.signals.update(q_true=truth[:, 0], dq_true=truth[:, 1], tau_motor=truth[:, 2], tau_int_true=truth[:, 3])
    return data


# -- analysis ------------------------------------------------------------------


@dataclass(frozen=True)
class StepInfo:
    """One detected reference step and the force response's metrics after it (None: not
    taken in contact, ``why`` says what the servo did instead)."""

    time: float
    start: float
    end: float
    metrics: dict[str, float | None] | None
    in_contact: bool | None = None  # None: contact not known (no config)
    why: str = ""


@dataclass(frozen=True)
class Contact:
    """Where the servo touched the environment: ``mask[i]`` per cycle (None: not known)."""

    mask: NDArray[np.bool_] | None
    source: str  # in words, for the report

    def throughout(self, start: int, end: int) -> bool | None:
        return None if self.mask is None else bool(self.mask[start:end].all()) and end > start


def contact_mask(data: RunData) -> Contact:
    """In contact where the position is at or beyond ``environment.contact_position``: the
    emulator's true position when recorded (exact), else the measured one (within one
    encoder count, ``sensor.encoder_resolution``)."""
    if data.config is None:
        return Contact(None, "not known (no recorded config)")
    q_c = data.config.environment.contact_position
    if data.has("q_true"):
        q = data["q_true"]
        return Contact(np.nan_to_num(q, nan=-np.inf) >= q_c,
                       f"emulator truth: true position >= environment.contact_position ({q_c:g} rad)")
    if data.has("q"):
        counts = data.config.sensor.encoder_resolution
        quantum = 2 * np.pi / counts if counts else 0.0
        return Contact(np.nan_to_num(data["q"], nan=-np.inf) >= q_c - quantum,
                       f"measured position >= environment.contact_position ({q_c:g} rad) from the config"
                       + (f", within one encoder count ({quantum:.3g} rad)" if quantum else ""))
    return Contact(None, "not known (no position recorded)")


def detect_steps(t: Array, ref: Array, from_start: bool = True) -> list[tuple[int, float, float]]:
    """(index, value before, value after) of every reference step; ``from_start``: the first
    sample is the run's first cycle, so a reference away from 0 there is a step from 0 (not
    so in a log recovered without its start: the reference had its value before)."""
    finite = ref[np.isfinite(ref)]
    if finite.size == 0:
        return []
    span = max(float(np.ptp(np.concatenate([finite, [0.0]]))), 1e-12)
    steps: list[tuple[int, float, float]] = []
    if from_start and abs(ref[0]) > STEP_FRACTION * span:
        steps.append((0, 0.0, float(ref[0])))
    jumps = np.nonzero(np.abs(np.diff(ref)) > STEP_FRACTION * span)[0] + 1
    steps.extend((int(i), float(ref[i - 1]), float(ref[i])) for i in jumps)
    return steps


def step_infos(data: RunData, contact: Contact | None = None) -> list[StepInfo]:
    """Every reference step; metrics for those taken in contact (all when contact is not known)."""
    from dobhil.analysis.metrics import step_metrics
    t, ref, y = data.t, data["tau_ref"], data["tau_int_hat"]
    contact = contact or contact_mask(data)
    cycles = data.signals.get("cycle")
    steps = detect_steps(t, ref, from_start=cycles is None or cycles.size == 0 or cycles[0] <= 0)
    out = []
    for j, (i, a, b) in enumerate(steps):
        end = steps[j + 1][0] if j + 1 < len(steps) else t.size
        touching = contact.throughout(i, end)
        if i > 0 and cycles is not None and cycles[i] - cycles[i - 1] > 1:
            # a recovered log's gap: the reference stepped somewhere in the cycles lost, and
            # the response to it is lost with them (its first sample kept is no step's start)
            out.append(StepInfo(float(t[i]), a, b, None, touching,
                                f"it fell in cycles {int(cycles[i - 1]) + 1}..{int(cycles[i]) - 1}, lost from "
                                "this recovered log, with its response"))
            continue
        if touching is False:
            out.append(StepInfo(float(t[i]), a, b, None, False, _not_in_contact(contact, t, i, end)))
            continue
        seg_t, seg_y = t[i:end] - t[i], (y[i:end] - a) / (b - a)
        m = step_metrics(seg_t, seg_y, target=1.0).as_dict()
        out.append(StepInfo(float(t[i]), a, b, _scale(m, b - a), touching))
    return out


def _not_in_contact(contact: Contact, t: Array, start: int, end: int) -> str:
    """Why a step has no metrics: when the servo touched (or left) the environment."""
    assert contact.mask is not None
    segment = contact.mask[start:end]
    if not segment[0]:
        touched = np.nonzero(segment)[0]
        return ("in free motion at the step; did not touch the environment before the next step or the end"
                if not touched.size
                else f"in free motion at the step; touched the environment at {t[start + touched[0]]:.3f} s")
    return f"lost contact at {t[start + int(np.argmin(segment))]:.3f} s"


def _scale(m: dict[str, float | None], height: float) -> dict[str, float | None]:
    """Metrics of the normalised response back in N m where they are torques."""
    out = dict(m)
    for key in ("steady_state_error", "final_value", "peak"):
        if out.get(key) is not None:
            out[f"{key}_nm"] = float(out[key]) * height  # type: ignore[arg-type]
    return out


def _rms(x: Array) -> float | None:
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x ** 2))) if x.size else None


def _amax(x: Array) -> float | None:
    x = x[np.isfinite(x)]
    return float(np.abs(x).max()) if x.size else None


def _pct(x: Array, q: float) -> float | None:
    x = x[np.isfinite(x)]
    return float(np.percentile(x, q)) if x.size else None


def bus_stats(data: RunData) -> dict[str, Any]:
    """Frames per second and the bus load: each frame's bit times at the nominal rate
    (:func:`dobhil.drives.bus_load.message_bits`: a CAN FD frame's data phase at the
    recorded ``bus.data_bitrate`` when it switched bit rate) over the log's span. A log with
    frames that switched bit rate and no data bit rate has no load (``bus_load_why``)."""
    bus = data.metadata.get("bus", {})
    bitrate = float(bus.get("bitrate", 0) or 0)
    if not bitrate and data.config is not None:
        bitrate = float(data.config.drive.bitrate)
    data_rate = float(bus.get("data_bitrate", 0) or 0)
    ratio = bitrate / data_rate if bitrate and data_rate else None
    span = data.span_s or (float(data.t[-1]) if data.t.size else 0.0)
    out: dict[str, Any] = {"bitrate": bitrate or None, "duration_s": span}
    if data_rate:
        out["data_bitrate"] = data_rate
    bits: int | None = 0
    for topic, dlcs in data.frames.items():
        key = topic.rsplit("/", 1)[-1]
        out[f"{key}_frames"] = len(dlcs)
        out[f"{key}_frames_per_s"] = len(dlcs) / span if span > 0 else None
        for (dlc, extended, fd, brs), count in data.frame_kinds.get(topic, Counter()).items():
            each = message_bits(dlc, extended=extended, fd=fd, brs=brs, data_ratio=ratio)
            bits = None if bits is None or each is None else bits + each * count
    out["bits_per_s"] = bits / span if span > 0 and bits is not None else None
    out["bus_load"] = (bits / span / bitrate) if span > 0 and bitrate and bits is not None else None
    if bits is None:
        out["bus_load_why"] = "CAN FD frames switched bit rate and the log does not record the data bit rate"
    elif span <= 0:
        out["bus_load_why"] = "one cycle: no time between the loop's cycles to measure it over"
    return out


def command_delay_periods(data: RunData) -> int | None:
    """The recorded drive profile's ``command_delay_periods`` (None: not set, or a log
    recorded before it existed)."""
    raw = data.metadata.get("drive", {}).get("command_delay_periods")
    try:
        value = json.loads(raw) if raw else None
    except ValueError:
        return None
    return value if isinstance(value, int) and not isinstance(value, bool) else None


def design_config(data: RunData) -> Config | None:
    """The recorded config as the run used it: with the drive protocol's command delay
    (:func:`dobhil.drives.timing.with_command_delay`, as the run's controller had it)."""
    if data.config is None:
        return None
    return with_command_delay(data.config, command_delay_periods(data))[0]


def latency_stats(data: RunData) -> dict[str, Any]:
    """Measured command latency (feedback frame received -> command frame sent, log clock)
    against the one the sampled analysis assumed. A drive whose protocol applies commands
    a fixed number of periods after their sample (at the next SYNC, say) makes the
    assumed delay itself: the command must only be in time for it (within a period)."""
    out: dict[str, Any] = {"assumed_s": None, "measured": False, **latency_clocks(data)}
    period = None
    config = design_config(data)
    latched = command_delay_periods(data)
    if config is not None:
        design, period = config.design, config.loop.period
        out["assumed_s"] = design.input_delay + design.delay_samples * period
        if latched is not None:
            out["protocol_delay_periods"] = latched
    if data.metadata.get("run", {}).get("log_clock") == "simulated":
        out["why"] = "lockstep: the log clock is simulated (the emulator applies the assumed delay)"
        return out
    rx = np.asarray(data.frame_times.get("/can/rx", []), dtype=np.int64)
    tx = np.asarray(data.frame_times.get("/can/tx", []), dtype=np.int64)
    if rx.size == 0 or tx.size == 0:
        out["why"] = "no frames in both directions"
        return out
    rx = np.sort(rx)   # a copy: the run's frame times stay in the log's order
    last = np.searchsorted(rx, tx, side="right") - 1
    lat = (tx[last >= 0] - rx[last[last >= 0]]) / 1e9
    if period is not None:   # a command long after any feedback is not a cycle's answer
        lat = lat[lat < period]
    if lat.size == 0:
        out["why"] = "no command within a period of a received frame"
        return out
    p50, p99 = float(np.percentile(lat, 50)), float(np.percentile(lat, 99))
    out.update(measured=True, p50_s=p50, p99_s=p99, max_s=float(lat.max()), commands=int(lat.size))
    if latched is not None and period is not None:
        # the protocol's latch makes the assumed delay: a command in time for it is exact
        out["matches"] = bool(p99 < period)
    elif out["assumed_s"] is not None and period is not None:
        # the analysis models one fixed delay: the median must sit on it and the spread
        # (p99) stay within the same tolerance, else the analysis is of another loop
        tolerance = LATENCY_TOLERANCE * period
        out.update(tolerance_s=tolerance, p50_minus_assumed_s=p50 - out["assumed_s"],
                   p99_minus_assumed_s=p99 - out["assumed_s"])
        out["matches"] = bool(abs(p50 - out["assumed_s"]) <= tolerance and abs(p99 - out["assumed_s"]) <= tolerance)
    return out


def latency_clocks(data: RunData) -> dict[str, str]:
    """Which clock each latency of the report is on: ``clock`` (the command latency: log
    times) and, where the run measured the drive's sample latency, ``sample_clock`` as the
    run recorded it (``run.sample_clock``; "not recorded" in a log from before it), with a
    line each saying what that is (the bus's stamps named by their interface)."""
    out = {"clock": LOG_CLOCK, "clock_text": LOG_CLOCK_TEXT}
    if not data.has("sample_latency"):
        return out
    sample = str(data.metadata.get("run", {}).get("sample_clock") or "")
    interface = str(data.metadata.get("bus", {}).get("interface") or "")
    text = SAMPLE_CLOCKS.get(sample, "not recorded in this log")
    if sample in SAMPLE_CLOCKS and interface:
        text += f" (interface {interface})"
    out.update(sample_clock=sample if sample in SAMPLE_CLOCKS else "not recorded", sample_clock_text=text)
    return out


def prediction(data: RunData, contact: Contact | None = None,
               steps: list[StepInfo] | None = None) -> tuple[Array | None, dict[str, Any]]:
    """The sampled closed loop of the recorded config driven by the recorded reference, from
    the first step taken in contact on (NaN before it), the loop at rest at the reference
    before that step: the analysed loop is the loop in contact."""
    config = design_config(data)
    if config is None:
        return None, {"available": False, "why": "no recorded config"}
    partners = data.coupled_to
    if partners:   # its loop is the coupled one: one axis' model alone would predict another run
        return None, {"available": False, "coupled": list(partners),
                      "why": f"axis {data.axis} is coupled to {', '.join(partners)} (environment.coupling): "
                             "its loop is the coupled loop, which `dobhil analyze` of the axes config analyses"}
    if config.design.delay_samples > MAX_PREDICTION_DELAY:
        return None, {"available": False, "why": f"design.delay_samples = {config.design.delay_samples} "
                                                  f"is above {MAX_PREDICTION_DELAY} (the model would be too large)"}
    import control

    from dobhil.analysis.transfer import LoopSystems
    from dobhil.synthesis.params import params_from_config
    sys_ = LoopSystems.build(params_from_config(config), sampled=True).system("closed_loop")
    radius = float(np.max(np.abs(sys_.poles()), initial=0.0))
    if not radius < 1.0:   # the recorded loop diverges: its response says nothing about the run
        return None, {"available": False, "unstable": True,
                      "why": f"the recorded design's sampled closed loop is unstable (largest |pole| "
                             f"{radius:.6g}; dobhil analyze gives its max stable C_f): no bounded prediction"}
    contact = contact or contact_mask(data)
    steps = step_infos(data, contact) if steps is None else steps
    start = _prediction_start(data, contact, steps)
    if start is None:
        lost = any(s.metrics is None and s.in_contact is not False for s in steps)
        what = ("each reference step in contact fell in cycles lost from this recovered log" if lost
                else "no reference step taken in contact" if steps else "no reference step, and contact not all along")
        return None, {"available": False, "why": f"{what} (the analysis is of the loop in contact)"}
    index, before = start
    # up to a recovered log's next gap: the model runs cycle by cycle, and the reference of
    # the cycles lost is not known
    cycles = data.signals.get("cycle")
    jumps = np.nonzero(np.diff(cycles[index:]) != 1)[0] if cycles is not None else np.array([], dtype=int)
    stop = index + int(jumps[0]) + 1 if jumps.size else data.t.size
    if stop - index < 2:   # python-control's forced_response needs two instants
        return None, {"available": False, "why": "the run ended within a cycle of its first step in contact "
                                                  "(nothing to compare)"}
    ref = np.nan_to_num(data["tau_ref"][index:stop]) - before   # at rest at `before`: a step from 0
    t = np.arange(ref.size) * float(sys_.dt)
    y = np.full(data.t.size, np.nan)
    y[index:stop] = before * float(np.real(control.dcgain(sys_))) + np.asarray(
        control.forced_response(sys_, T=t, U=ref).outputs).reshape(-1)
    diff = data["tau_int_hat"] - y
    if contact.mask is not None:
        diff = np.where(contact.mask, diff, np.nan)
    return y, {"available": True, "rms_difference": _rms(diff), "max_difference": _amax(diff),
               "from_s": float(data.t[index]),
               "system": "LoopSystems(sampled=True).closed_loop: tau_ref -> tau_int_hat, in contact"}


def _prediction_start(data: RunData, contact: Contact, steps: list[StepInfo]) -> tuple[int, float] | None:
    """(index, reference before) where the prediction starts: the first step in contact;
    the start of the run when there is no step and the servo is in contact all along (or
    contact is not known)."""
    for s in steps:
        if s.in_contact is not False and s.metrics is not None:   # None: a step lost in a recovered log's gap
            return int(np.searchsorted(data.t, s.time)), s.start
    if not steps and (contact.mask is None or bool(contact.mask.all())):
        return 0, 0.0
    return None


def torque_mode(data: RunData) -> bool:
    """A ``loop.mode: torque`` run: open loop, tau_ref is the torque command (identification)."""
    return data.config is not None and data.config.loop.mode == "torque"


def analyse(data: RunData) -> tuple[dict[str, Any], Array | None]:
    """The report summary (JSON-ready) and the predicted tau_int_hat. A torque-mode run
    has no force loop: no force steps, tracking or prediction (same keys, no values)."""
    contact = contact_mask(data)
    ref, est, true = data["tau_ref"], data["tau_int_hat"], data["tau_int_true"]
    if torque_mode(data):
        steps: list[StepInfo] = []
        predicted: Array | None = None
        pred_info: dict[str, Any] = {"available": False, "why": "loop.mode = torque: an open-loop "
                                     "excitation run, no force loop to predict"}
        ref = np.full_like(ref, np.nan)   # the reference is a torque: nothing tracks it
    else:
        steps = step_infos(data, contact)
        predicted, pred_info = prediction(data, contact, steps)
    summary: dict[str, Any] = {
        "file": data.path, "cycles": int(data.t.size), "duration_s": run_duration(data),
        "run": dict(data.metadata.get("run", {})),
        "stop": next((e["reason"] for e in reversed(data.events) if e.get("kind") == "stop"), None),
        "contact": {"source": contact.source,
                    "first_s": _first_contact(data.t, contact)},
        "steps": [s.__dict__ for s in steps],
        "tracking": {"rms_error_estimated": _rms(ref - est), "max_error_estimated": _amax(ref - est),
                     "rms_error_true": _rms(ref - true) if data.has("tau_int_true") else None},
        "estimation": ({"rms_error": _rms(est - true), "max_error": _amax(est - true)}
                       if data.has("tau_int_true") else None),
        "loop_timing": _timing(data),
        "bus": bus_stats(data),
        "latency": latency_stats(data),
        "dropped": int(sum(int(e.get("count", 0)) for e in data.events if e.get("kind") == "loss")),
        "prediction": pred_info,
        "stability_gate": stability_gate(data),
        "drive_states": data.states,
    }
    return summary, predicted


def run_duration(data: RunData) -> float:
    """How long the run lasted [s]: its last cycle's time plus that cycle's period (N cycles
    at period T are N T, as the run's stop line says: "ran 3 s" for 3000 cycles of 1 ms, not
    the 2.999 s the last cycle starts at); without a recorded config, the last cycle's time."""
    if not data.t.size:
        return 0.0
    period = data.config.loop.period if data.config is not None else 0.0
    return float(data.t[-1]) + period


def stability_gate(data: RunData) -> dict[str, Any] | None:
    """The stability gate's verdict the run recorded before it started (the
    ``stability_gate`` metadata of ``dobhil run``/``demo``: status, max stable C_f, margins,
    whether ``--allow-unstable`` overrode a refusal); None for a log without it."""
    raw = data.metadata.get("stability_gate")
    if not raw:
        return None
    out: dict[str, Any] = {}
    for key, value in raw.items():
        try:
            out[key] = json.loads(value)
        except ValueError:
            out[key] = value
    return out


def _first_contact(t: Array, contact: Contact) -> float | None:
    if contact.mask is None or not contact.mask.any():
        return None
    return float(t[int(np.argmax(contact.mask))])


def _timing(data: RunData) -> dict[str, Any]:
    ex, pe = data["exec_time"], np.abs(data["period_error"])
    out = {"exec_time_p50": _pct(ex, 50), "exec_time_p99": _pct(ex, 99), "exec_time_max": _amax(ex),
           "period_error_p50": _pct(pe, 50), "period_error_p99": _pct(pe, 99), "period_error_max": _amax(pe),
           "overruns": int(np.nansum(data["overrun"]))}
    sl = data.signals.get("sample_latency")
    if sl is not None and np.isfinite(sl).any():   # only where the drive's sample instant was known
        out.update(sample_latency_p50=_pct(sl, 50), sample_latency_p99=_pct(sl, 99), sample_latency_max=_amax(sl))
    return out


def summary_text(s: Mapping[str, Any]) -> str:
    """The short text version of the summary."""
    def us(v: float | None) -> str:
        return "-" if v is None else f"{v * 1e6:.0f} us"

    def nm(v: float | None) -> str:
        return "-" if v is None else f"{v:.4g} N m"

    lines = [f"run: {s['file']}", f"cycles: {s['cycles']} ({s['duration_s']:.3f} s), stop: {s['stop'] or '-'}"]
    gate = s.get("stability_gate")
    if gate:
        overridden = "OVERRIDDEN by --allow-unstable: " if gate.get("overridden") else ""
        lines.append(f"stability gate: {overridden}{gate.get('line') or gate.get('status')}")
    if not s["prediction"].get("available") and "loop.mode = torque" in s["prediction"].get("why", ""):
        lines.append("mode: torque (open loop, the reference is the torque command): no force tracking")
    contact = s.get("contact") or {}
    if s["steps"] and contact:
        first = contact.get("first_s")
        lines.append(f"contact: {contact['source']}; first at "
                     f"{'-' if first is None else f'{first:.3f} s'}; step metrics only for steps taken in contact")
    for st in s["steps"]:
        lines.append(_step_line(st))
    tr = s["tracking"]
    lines.append(f"tracking: RMS(tau_ref - tau_int^) {nm(tr['rms_error_estimated'])}"
                 + (f", RMS(tau_ref - tau_int) {nm(tr['rms_error_true'])}" if tr["rms_error_true"] is not None else ""))
    if s["estimation"]:
        lines.append(f"estimation: RMS(tau_int^ - tau_int) {nm(s['estimation']['rms_error'])}, "
                     f"max {nm(s['estimation']['max_error'])}")
    p = s["prediction"]
    if p.get("unstable") or p.get("coupled"):
        lines.append(f"analysis prediction: none ({p['why']})")
    if p.get("available"):
        lines.append(f"analysis prediction vs measured tau_int^: RMS {nm(p['rms_difference'])}, "
                     f"max {nm(p['max_difference'])}")
    lt = s["loop_timing"]
    lines.append(f"loop: exec p50 {us(lt['exec_time_p50'])}, p99 {us(lt['exec_time_p99'])}, "
                 f"max {us(lt['exec_time_max'])}; |period error| p99 {us(lt['period_error_p99'])}; "
                 f"overruns {lt['overruns']}")
    la = s.get("latency") or {}
    if lt.get("sample_latency_p99") is not None:
        clock = f"; {la['sample_clock_text']}" if la.get("sample_clock_text") else ""
        lines.append(f"sample latency (drive sample -> feedback received{clock}): p50 {us(lt['sample_latency_p50'])}, "
                     f"p99 {us(lt['sample_latency_p99'])}, max {us(lt['sample_latency_max'])}")
    if la.get("measured"):
        assumed = "-" if la.get("assumed_s") is None else us(la["assumed_s"])
        clock = f" ({la['clock_text']})" if la.get("clock_text") else ""
        lines.append(f"command latency{clock}: p50 {us(la['p50_s'])}, p99 {us(la['p99_s'])}, max {us(la['max_s'])}; "
                     f"assumed by the analysis {assumed}{_latency_verdict(la)}")
    elif la:
        lines.append(f"command latency: not measured ({la.get('why', '-')})")
    b = s["bus"]
    load = (f"- ({b['bus_load_why']})" if b.get("bus_load_why") else "-") if b["bus_load"] is None \
        else f"{b['bus_load'] * 100:.1f} %"
    fps = "-" if b.get("rx_frames_per_s") is None else f"{b['rx_frames_per_s']:.0f} rx + {b['tx_frames_per_s']:.0f} tx"
    rate = "?" if not b["bitrate"] else f"{b['bitrate']:.0f}"
    lines.append(f"bus: {fps} frames/s, load {load} at {rate} bit/s; dropped records {s['dropped']}")
    lines += _state_lines(s.get("drive_states") or [])
    return "\n".join(lines) + "\n"


#: state changes the text summary lists (the JSON summary has them all)
STATE_LINES: Final = 10


def _state_lines(states: list[Mapping[str, Any]]) -> list[str]:
    """One line per change of the drive's state: dobhil's state, the drive's own state and
    error code with the protocol's names for them."""
    lines = [f"drive state at {st['time_s']:.3f} s (cycle {st['cycle']}): {st['drive_state']}; "
             f"the drive's state {st['protocol_state']} ({st['protocol_state_name']}), "
             f"error {st['protocol_error_text']}" for st in states[:STATE_LINES]]
    if len(states) > STATE_LINES:
        lines.append(f"... {len(states) - STATE_LINES} more drive state changes (report --json lists them)")
    return lines


def _step_line(st: Mapping[str, Any]) -> str:
    head = f"step at {st['time']:.3f} s ({st['start']:.3g} -> {st['end']:.3g} N m): "
    m = st["metrics"]
    if m is None and st.get("in_contact") is not False:   # not taken where the log kept it
        return head + f"{st.get('why') or '-'}: no step metrics"
    if m is None:
        return head + f"not taken in contact ({st.get('why') or '-'}): no step metrics"

    def fmt(k: str, scale: float = 1.0, unit: str = "") -> str:
        return "-" if m.get(k) is None else f"{m[k] * scale:.3g}{unit}"
    return head + (f"overshoot {fmt('overshoot_pct', 1, ' %')}, rise {fmt('rise_time', 1e3, ' ms')}, "
                   f"settling {fmt('settling_time', 1e3, ' ms')}, "
                   f"steady-state error {fmt('steady_state_error_nm', 1, ' N m')}")


def _latency_verdict(la: Mapping[str, Any]) -> str:
    """Matches or not, with the tolerance, and what is off (older summaries: no verdict)."""
    if "protocol_delay_periods" in la and "matches" in la:
        n = la["protocol_delay_periods"]
        return (f"; the drive applies each command {n} period{'' if n == 1 else 's'} after its sample "
                + ("(every command in time for it)" if la["matches"] else
                   "but p99 is above a period: some commands miss the drive's latch"))
    if "matches" not in la or "tolerance_s" not in la:
        return ""
    tol = f"+-{la['tolerance_s'] * 1e6:.0f} us ({LATENCY_TOLERANCE:g} T)"
    if la["matches"]:
        return f"; p50 and p99 within {tol} of it: matches the analysis"
    off = [f"{k} off by {la[f'{k}_minus_assumed_s'] * 1e6:+.0f} us" for k in ("p50", "p99")
           if abs(la[f"{k}_minus_assumed_s"]) > la["tolerance_s"]]
    advice = (f"; set design.input_delay = {la['p50_s']:.6f} for the median" if abs(la["p50_minus_assumed_s"])
              > la["tolerance_s"] else "; the spread is not in the analysis (a fixed delay)")
    return f"; does not match the analysis (tolerance {tol}): {', '.join(off)}{advice}"


def report(path: str | os.PathLike[str], progress: ProgressFn | None = None) -> tuple[RunData, dict[str, Any],
                                                                                  Array | None]:
    """The run's data, its summary and the predicted tau_int_hat (the CLI draws and writes them)."""
    data = load_run(path, progress)
    summary, predicted = analyse(data)
    return data, summary, predicted


AxisReport = tuple[RunData, dict[str, Any], "Array | None"]


def report_axes(path: str | os.PathLike[str], progress: ProgressFn | None = None
                ) -> tuple[dict[str, AxisReport], dict[str, Any]]:
    """Each axis' data, summary and prediction (by name, in the loop's order), and the
    summary of the run: ``axes`` (each axis' summary, its ``bus`` the load of its bus),
    ``loop_timing`` shared by the axes, ``buses`` (each bus' load and the axes on it)."""
    log = open_log(path)
    per: dict[str, AxisReport] = {}
    for axis in axis_logs(log):
        data = load_axis(axis, progress)
        summary, predicted = analyse(data)
        summary["bus"] = {"name": data.bus, **summary["bus"]}
        per[axis.name] = (data, summary, predicted)
    datas = [d for d, _, _ in per.values()]
    buses: dict[str, dict[str, Any]] = {}
    for data, summary, _ in per.values():
        entry = buses.setdefault(data.bus, {**summary["bus"], "axes": []})
        entry["axes"].append(data.axis)
    first = datas[0]
    return per, {"file": os.fspath(path), "axes": {n: s for n, (_, s, _) in per.items()},
                 "run": dict(first.metadata.get("run", {})),
                 "stop": next((e["reason"] for e in reversed(first.events) if e.get("kind") == "stop"), None),
                 "dropped": int(sum(int(e.get("count", 0)) for e in first.events if e.get("kind") == "loss")),
                 "loop_timing": shared_timing(datas), "buses": buses}


def shared_timing(datas: list[RunData]) -> dict[str, Any]:
    """The loop's timing over its axes: per cycle the largest execution time and |period
    error| any axis recorded, an overrun when any axis' cycle overran."""
    # on arrays, a cycle's axes gathered by their cycle number: a long log's cycles are not
    # each a Python object (a list of floats per cycle took 300 bytes a cycle of two axes)
    cycles, where = np.unique(np.concatenate([data["cycle"] for data in datas]), return_inverse=True)
    ex, pe, over = (np.full(cycles.size, np.nan), np.full(cycles.size, np.nan), np.zeros(cycles.size))
    np.fmax.at(ex, where, np.concatenate([data["exec_time"] for data in datas]))
    np.fmax.at(pe, where, np.abs(np.concatenate([data["period_error"] for data in datas])))
    np.maximum.at(over, where, np.nan_to_num(np.concatenate([data["overrun"] for data in datas]), nan=0.0))
    return {"cycles": int(cycles.size), "exec_time_p50": _pct(ex, 50), "exec_time_p99": _pct(ex, 99),
            "exec_time_max": _amax(ex), "period_error_p50": _pct(pe, 50), "period_error_p99": _pct(pe, 99),
            "period_error_max": _amax(pe), "overruns": int(over.sum())}


def axes_summary_text(s: Mapping[str, Any]) -> str:
    """The text of a several-axis summary: each axis' (as :func:`summary_text`, indented),
    the shared timing, each bus' load."""
    def us(v: float | None) -> str:
        return "-" if v is None else f"{v * 1e6:.0f} us"

    lines = [f"run: {s['file']}", f"axes: {', '.join(s['axes'])}; stop: {s['stop'] or '-'}; "
             f"dropped records {s['dropped']}"]
    for name, summary in s["axes"].items():
        lines.append(f"axis {name}:")
        lines += ["  " + line for line in summary_text(summary).splitlines()[1:]]
    lt = s["loop_timing"]
    lines.append(f"loop (all axes, {lt['cycles']} cycles): exec p50 {us(lt['exec_time_p50'])}, "
                 f"p99 {us(lt['exec_time_p99'])}, max {us(lt['exec_time_max'])}; |period error| p99 "
                 f"{us(lt['period_error_p99'])}; overruns {lt['overruns']}")
    for name, b in s["buses"].items():
        load = (f"- ({b['bus_load_why']})" if b.get("bus_load_why") else "-") if b["bus_load"] is None \
            else f"{b['bus_load'] * 100:.1f} %"
        rate = "?" if not b["bitrate"] else f"{b['bitrate']:.0f}"
        fps = ("-" if b.get("rx_frames_per_s") is None
               else f"{b['rx_frames_per_s']:.0f} rx + {b['tx_frames_per_s']:.0f} tx")
        lines.append(f"bus {name} (axes {', '.join(b['axes'])}): {fps} frames/s, load {load} at {rate} bit/s")
    return "\n".join(lines) + "\n"


__all__ = ["LATENCY_TOLERANCE", "LOG_CLOCK", "SAMPLE_CLOCKS", "AxisReport", "Contact", "RunData", "StepInfo",
           "analyse", "axes_summary_text", "bus_stats", "contact_mask", "detect_steps", "gaps_within",
           "latency_clocks", "latency_stats", "load_axis", "load_run", "prediction", "report", "report_axes",
           "run_duration", "shared_timing", "step_infos", "summary_text", "torque_mode"]
