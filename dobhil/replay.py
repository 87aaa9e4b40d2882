"""Offline replay: a recorded run's ``/can/rx`` frames decoded by the run's own drive class
(``seq`` counts motion frames as at run time), the controller -- deterministic generated
code -- re-run on the feedback each cycle used (``/drive/feedback``; ``cycle = -1``: the one
``controller.initialize`` used) and the recorded reference. With the recorded config every
output is identical bit for bit (``dobhil replay --verify``); with ``--set`` overrides it
shows what that tuning would have done.

A several-axis log (:mod:`dobhil.recording.axeslog`) replays axis by axis
(:func:`replay_axes`): each axis' controller rebuilt from that axis' recorded config and
profile by the same :func:`~dobhil.runtime.session.build_controller`, fed that axis' feedback
decoded from its bus' frames (its drive class keeps its own node's frames only).
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any, Final

import can
import numpy as np
from numpy.typing import NDArray

from dobhil.config.schema import Config
from dobhil.drives.decode import decode_motion, recorded_profile
from dobhil.drives.profile import DriveProfile
from dobhil.errors import ConfigError, LogFileError, exception_line
from dobhil.recording.axes import AxisLog, axis_log, axis_logs
from dobhil.recording.reader import LogFile, open_log
from dobhil.recording.schemas import CAN_MESSAGE_DEFAULTS, CAN_MESSAGE_FIELDS, can_frame_message_of
from dobhil.runtime.session import build_controller

Array = NDArray[np.float64]

#: Controller outputs in /controller order (and ControlOutput order).
OUTPUTS: Final = ("tau_ref", "tau_int_hat", "tau_dis_hat", "tau_per", "u_unsat", "u_sat")
#: Outputs compared by the verification (tau_ref is an input).
COMPARED: Final = OUTPUTS[1:]
_TOPICS: Final = ("/can/rx", "/drive/feedback", "/controller")
#: The fields replay reads of each topic (read as rows: no payload dict per message).
_FIELDS: Final = {"/controller": ("cycle", *OUTPUTS), "/can/rx": CAN_MESSAGE_FIELDS,
                  "/drive/feedback": ("cycle", "seq")}


@dataclass(frozen=True)
class Recording:
    """What a replay needs from one log."""

    path: str
    profile: DriveProfile
    axis: str                                # the axis' name ("axis" in a single-axis log)
    frames: tuple[can.Message, ...]          # /can/rx in receive order
    initial_seq: int                         # feedback seq controller.initialize used
    cycle: NDArray[np.int64]                 # cycle index per recorded cycle
    seq: NDArray[np.int64]                   # feedback seq each cycle used
    time: Array                              # log time [s] since the first cycle
    recorded: Array                          # (n, 6) recorded OUTPUTS
    #: a recovered log's first gap (:func:`_gap`): the first and last cycle it lost (first >
    #: last: it lost frames, no cycle) and the cycles present after it, not re-run; None: no gap
    missing: tuple[int, int, int] | None = None

    @property
    def cycles(self) -> int:
        return int(self.cycle.size)

    def gap_line(self) -> str | None:
        """One line on a recovered log's missing stretch: which cycles, what was verified."""
        if self.missing is None:
            return None
        first, last, after = self.missing
        lost = (f"cycles {first}..{last} missing" if first <= last
                else f"messages between cycles {first - 1} and {first} missing")
        verified = f"cycles {int(self.cycle[0])}..{first - 1} re-run" if self.cycles else "no cycle re-run"
        return (f"{lost} (recovered log): {verified}, the {after} after the gap not (the controller's state there "
                "is lost with it)")


@dataclass(frozen=True)
class Mismatch:
    """The first cycle where replay and recording differ."""

    cycle: int
    time: float
    signal: str
    recorded: float
    replayed: float

    def line(self) -> str:
        return (f"replay differs at cycle {self.cycle} (t = {self.time:.4f} s): {self.signal} "
                f"recorded {self.recorded!r}, replayed {self.replayed!r}")


@dataclass(frozen=True)
class ReplayResult:
    """Recorded and replayed controller outputs over the same measured data."""

    recording: Recording
    config: Config
    overrides: tuple[str, ...]
    position: Array
    velocity: Array
    replayed: Array                          # (n, 6) replayed OUTPUTS

    def column(self, name: str, which: str = "replayed") -> Array:
        return (self.replayed if which == "replayed" else self.recording.recorded)[:, OUTPUTS.index(name)]

    def first_mismatch(self) -> Mismatch | None:
        """The first cycle and signal whose bits differ (NaN equal to NaN), or None."""
        rec, rep = self.recording.recorded[:, 1:], self.replayed[:, 1:]
        differ = (rec.view(np.int64) != rep.view(np.int64)) & ~(np.isnan(rec) & np.isnan(rep))
        rows = np.nonzero(differ.any(axis=1))[0]
        if rows.size == 0:
            return None
        i = int(rows[0])
        j = int(np.nonzero(differ[i])[0][0])
        return Mismatch(int(self.recording.cycle[i]), float(self.recording.time[i]), COMPARED[j],
                        float(rec[i, j]), float(rep[i, j]))

    def summary(self) -> dict[str, Any]:
        """Differences replayed - recorded (max |.|, RMS) per output, and the cycle count."""
        mismatch, diffs = self.first_mismatch(), {}
        for name in COMPARED:
            d = self.column(name) - self.column(name, "recorded")
            d = d[np.isfinite(d)]
            d = d if d.size else np.zeros(1)
            diffs[name] = {"max_abs": float(np.abs(d).max()), "rms": float(np.sqrt(np.mean(d ** 2)))}
        return {"file": self.recording.path, "axis": self.recording.axis, "cycles": self.recording.cycles,
                "overrides": list(self.overrides),
                "identical": mismatch is None, "first_mismatch": None if mismatch is None else mismatch.line(),
                "missing": self.recording.gap_line(), "difference": diffs}

    def rows(self) -> Iterator[list[float]]:
        """CSV rows: cycle, t, q, dq, then recorded and replayed outputs."""
        rec, rep = self.recording.recorded, self.replayed
        for i in range(self.recording.cycles):
            yield [int(self.recording.cycle[i]), float(self.recording.time[i]), self.position[i],
                   self.velocity[i], *rec[i].tolist(), *rep[i, 1:].tolist()]

    @staticmethod
    def header() -> list[str]:
        return ["cycle", "t", "q", "dq", *(f"recorded_{n}" for n in OUTPUTS), *(f"replayed_{n}" for n in COMPARED)]


def recorded_config(log: LogFile | AxisLog, overrides: Sequence[str] = ()) -> Config:
    """The run's config (checked when the log was opened), with ``--set`` overrides on top;
    an axis' config with the overrides of every axis (``section.key``) and its own
    (``axes.NAME.section.key``: NAME one of the log's axes)."""
    from dobhil.config import build_config
    if log.config is None:
        raise LogFileError(f"{log.path}: no 'config' metadata (not a recorded run?)")
    mine = axis_overrides(log, overrides)
    if not mine:
        return log.config
    return build_config({**log.config.flat(), **mine}, source=f"{log.path} config")


#: what a replay re-runs is the recorded controller (dobhil.runtime.session.build_controller) on
#: the recorded feedback: its design, its torque limit and its mode are all ``--set`` can change.
#: The plant, the environment, the sensor, the reference, the drive and the loop's timing are
#: the recording's (its frames, its references, its profile from the log's metadata).
REPLAYED: Final = ("design.", "loop.torque_limit", "loop.mode")


def _replayed(item: str, key: str) -> None:
    """ConfigError unless ``key`` is one a replay applies (:data:`REPLAYED`): another would be
    reported as applied and change nothing."""
    if not key.startswith(REPLAYED):
        raise ConfigError(f"--set {item}: a replay re-runs the recorded controller on the recorded feedback; "
                          "it takes design.* keys, loop.torque_limit and loop.mode (the plant, environment, "
                          "sensor, reference, drive and the loop's timing are the recording's)")


def axis_overrides(log: LogFile | AxisLog, overrides: Sequence[str]) -> dict[str, Any]:
    """The ``--set`` overrides of ``log``'s axis: ``axes.NAME.key`` of this axis as ``key``,
    of another axis of the log left out, of no axis of the log refused; a key the replay does
    not apply (:data:`REPLAYED`) refused for every axis."""
    from dobhil.config import parse_override
    name, axes = (log.name, log.axes) if isinstance(log, AxisLog) else (None, ())
    out: dict[str, Any] = {}
    for item in overrides:
        key, value = parse_override(item)
        if not key.startswith("axes."):
            _replayed(item, key)
            out[key] = value
            continue
        parts = key.split(".")
        if len(parts) != 4 or parts[1] not in axes:
            raise ConfigError(f"--set {item}: expected axes.NAME.section.key=value with NAME one of the log's "
                              f"axes ({', '.join(axes) or 'none: a single-axis log takes section.key=value'})")
        _replayed(item, ".".join(parts[2:]))
        if parts[1] == name:
            out[".".join(parts[2:])] = value
    return out


def _profile(log: LogFile | AxisLog) -> DriveProfile:
    return recorded_profile(log.metadata.get("drive"), os.fspath(log.path))


def _gap(log: LogFile | AxisLog, name: str) -> int | None:
    """The log time a recovered log's first gap starts after (the ``recover`` metadata's
    ``gaps``: :mod:`dobhil.recording.recover`; -1: before any message); None without one (an
    integer: a log time in ns is beyond a float's 53 bits). The controller cannot be
    re-run past it: its state there depends on the cycles lost, and the frames after it are
    counted from a start that lost some (a feedback seq no longer names its frame)."""
    from dobhil.recording.recover import RECOVER_METADATA
    raw = log.metadata.get(RECOVER_METADATA, {}).get("gaps")
    if not raw:
        return None
    try:
        starts = [-1 if g[0] is None else int(g[0]) for g in json.loads(raw)]
    except (ValueError, TypeError, IndexError, KeyError):
        raise LogFileError(f"{name}: invalid metadata {RECOVER_METADATA}.gaps: {raw!r}") from None
    return starts[0] if starts else None


def _read(log: LogFile | AxisLog, name: str) -> Recording:
    frames: list[can.Message] = []
    seqs: dict[int, int] = {}
    initial: int | None = None
    controller: list[tuple[int, int, list[float]]] = []
    gap, after = _gap(log, name), set()
    try:
        for topic, t, row in log.iter_rows(_FIELDS, CAN_MESSAGE_DEFAULTS):
            if gap is not None and t > gap:   # past a recovered log's gap: not re-run, its cycles counted
                if topic == "/controller":
                    after.add(int(row[0]))
                continue
            if topic == "/controller":
                controller.append((int(row[0]), t, [float("nan") if v is None else float(v) for v in row[1:]]))
            elif topic == "/can/rx":
                frames.append(can_frame_message_of(row, t))
            elif row[0] < 0:
                initial = int(row[1])
            else:
                seqs[int(row[0])] = int(row[1])
    except (KeyError, TypeError, ValueError) as exc:
        raise LogFileError(f"{name}: a recorded message does not match its schema "
                           f"({exception_line(exc)})") from None
    if initial is None:
        lost = " (lost with the start of this recovered log)" if gap is not None else ""
        raise LogFileError(f"{name}: no initial feedback record (cycle -1) on /drive/feedback{lost}")
    controller.sort(key=lambda c: c[0])
    missing = None
    if after:
        first = controller[-1][0] + 1 if controller else 0
        missing = (first, min(after) - 1, len(after))
    unfed = [c for c, _, _ in controller if c not in seqs]
    if unfed:
        raise LogFileError(f"{name}: cycle {unfed[0]} has /controller but no /drive/feedback record")
    cycle = np.array([c for c, _, _ in controller], dtype=np.int64)
    times = np.array([t for _, t, _ in controller], dtype=np.int64)
    return Recording(name, _profile(log), getattr(log, "name", "axis"), tuple(frames), initial, cycle,
                     np.array([seqs[int(c)] for c in cycle], dtype=np.int64),
                     (times - (times[0] if times.size else 0)) / 1e9,
                     np.array([v for _, _, v in controller], dtype=float).reshape(-1, len(OUTPUTS)), missing)


def replay(path: str | os.PathLike[str], overrides: Sequence[str] = (), axis: str | None = None) -> ReplayResult:
    """Re-run the controller of ``path`` (with ``overrides``) on its recorded feedback frames:
    of ``axis`` (None: the log's one axis; a several-axis log needs the name)."""
    return replay_axis(axis_log(open_log(path), axis), overrides)


def replay_axes(path: str | os.PathLike[str], overrides: Sequence[str] = ()) -> tuple[ReplayResult, ...]:
    """Every axis of ``path`` replayed (:func:`replay_axis`), in the loop's order."""
    return tuple(replay_axis(axis, overrides) for axis in axis_logs(path))


def replay_axis(log: AxisLog, overrides: Sequence[str] = ()) -> ReplayResult:
    """Re-run the controller of one axis of a log on its recorded feedback frames."""
    for topic in _TOPICS:
        log.require_topic(topic)
    config = recorded_config(log, overrides)
    recording = _read(log, os.fspath(log.path))
    pos, vel = _decode_feedback(recording)
    n_fb, seq = len(pos) - 1, recording.seq
    if recording.initial_seq > n_fb or (seq.size and int(seq.max()) > n_fb) or recording.initial_seq < 1:
        raise LogFileError(f"{recording.path}: feedback seq beyond the {n_fb} motion frames on /can/rx")
    ctrl = build_controller(config, recording.profile)
    ctrl.initialize(pos[recording.initial_seq], vel[recording.initial_seq])
    step, refs = ctrl.step, recording.recorded[:, 0].tolist()
    q = [pos[s] for s in seq.tolist()]
    dq = [vel[s] for s in seq.tolist()]
    measured = dq if ctrl.measures_velocity else [None] * len(q)
    out = [step(a, b, r) for a, b, r in zip(q, measured, refs)]
    return ReplayResult(recording, config, tuple(overrides), np.array(q), np.array(dq),
                        np.array(out, dtype=float).reshape(-1, len(OUTPUTS)))


def _decode_feedback(recording: Recording) -> tuple[list[float], list[float]]:
    """(position, velocity) indexed by feedback seq (index 0 unused), decoded by the run's own
    drive class, so ``seq`` counts motion frames exactly as at run time."""
    motion = decode_motion(recording.profile, recording.frames)
    return [float("nan"), *(p for _, p, _ in motion)], [float("nan"), *(v for _, _, v in motion)]


__all__ = ["COMPARED", "OUTPUTS", "Mismatch", "Recording", "ReplayResult", "axis_overrides", "recorded_config",
           "replay", "replay_axes", "replay_axis"]
