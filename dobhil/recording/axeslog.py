"""Recording one loop of several axes into one MCAP file: :class:`AxesLog`.

The same records, schemas and writer as a single-axis log (:class:`~dobhil.recording.runlog.RunLog`:
one writer process, the same batches, the same lossy hand-over and counted loss), each
record in a *lane* (:data:`~dobhil.recording.schemas.LANE_STRIDE`) whose topics carry a prefix:

- each axis' cycles, feedback and events under ``/axis/<name>``: ``/axis/<name>/drive/feedback``,
  ``/axis/<name>/drive/command``, ``/axis/<name>/controller``, ``/axis/<name>/loop``,
  ``/axis/<name>/emulator/truth``, ``/axis/<name>/events`` (the topics of a single-axis log and
  their schemas, so a Foxglove layout of one axis reads any axis by its prefix);
- each bus' frames under ``/bus/<bus>``: ``/bus/<bus>/can/rx`` and ``/bus/<bus>/can/tx`` (the
  frames of every axis on that bus, in bus order, as the loop saw them);
- the run's own events (stop, recorder loss) on ``/events``.

The ``axes`` metadata record names the axes in their order, each axis' bus and each bus'
topic prefix (:data:`AXES_METADATA`); each axis' config, profile and limits are the records
``axis/<name>/config``, ``axis/<name>/drive``, ``axis/<name>/run`` and each bus' the record
``bus/<bus>`` (:func:`axis_record`, :func:`bus_record`), written by the caller with the rest
of the run's metadata. :mod:`dobhil.recording.axes` reads them back.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Callable, Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import can

from dobhil.errors import RecorderError
from dobhil.recording.codes import ProtocolCodes
from dobhil.recording.layouts import DEFAULT_LAYOUT
from dobhil.recording.process import WriterProcess
from dobhil.recording.runlog import LaneSink, RunLog
from dobhil.recording.schemas import EventKind, Topic
from dobhil.recording.writer import Lane, LiveView

#: The metadata record that makes a log a several-axis log: ``names`` (JSON list, in the
#: loop's order), ``bus_of`` (JSON: axis -> bus name), ``buses`` (JSON: bus name -> its topic
#: prefix), ``couplings`` (JSON list of ``{a, b, stiffness, damping}``) and ``format``.
AXES_METADATA: Final = "axes"
#: ``axes.format`` of the logs this version writes.
AXES_FORMAT: Final = "1"
#: The prefix of an axis' topics (and of its metadata records, without the slash).
AXIS_PREFIX: Final = "/axis/"
#: The prefix of a bus' frame topics.
BUS_PREFIX: Final = "/bus/"
#: The topics of each kind of lane: the run's, an axis', a bus'.
RUN_LANE: Final = (Topic.EVENTS,)
AXIS_LANE: Final = (Topic.DRIVE_FEEDBACK, Topic.DRIVE_COMMAND, Topic.CONTROLLER, Topic.LOOP, Topic.EMULATOR_TRUTH,
                    Topic.EVENTS)
BUS_LANE: Final = (Topic.CAN_RX, Topic.CAN_TX)
#: What a bus name keeps in its topic (any other character becomes ``_``).
_TOPIC_SAFE: Final = re.compile(r"[^A-Za-z0-9_.-]")


def axis_record(axis: str, record: str) -> str:
    """The name of an axis' metadata record (``axis/left/config``)."""
    return f"axis/{axis}/{record}"


def bus_record(bus: str) -> str:
    """The name of a bus' metadata record (``bus/can0``)."""
    return f"bus/{bus}"


def axis_prefix(axis: str) -> str:
    """``/axis/<name>``: an axis name is a topic path component already
    (:data:`dobhil.config.axes.AXIS_NAME`)."""
    return f"{AXIS_PREFIX}{axis}"


@dataclass(frozen=True)
class AxisDrive:
    """What the log takes from one axis of the run as it begins: its drive (whose
    ``status`` goes to ``/axis/<name>/drive/feedback``), the emulator's truth of its plant
    ``(q, dq, tau_motor, tau_int)`` (None: a real drive), the arbitration ids of its frames
    (None: not known; the rest of its bus' traffic is foreign, shed first in real time),
    the names of its protocol's codes and the name of its bus (as given to :meth:`AxesLog.wrap_bus`)."""

    drive: Any
    bus: str
    truth: Callable[[], tuple[float, float, float, float]] | None = None
    own_ids: Collection[int] | None = None
    codes: ProtocolCodes | None = None


class AxesLog:
    """Records one several-axis run through ``writer``: a sink per axis (:meth:`sink`, the
    loop's ``CycleSink`` of that axis) and a tap per bus (:meth:`wrap_bus`, the session's
    ``bus_wrapper``), all in one :class:`~dobhil.recording.runlog.RunLog`'s batches. Buses are
    wrapped before :meth:`begin`; records wait until it (a preflight talks on the buses)."""

    def __init__(self, writer: WriterProcess, axes: Iterable[str], *, live: LiveView | None = None) -> None:
        names = tuple(axes)
        if not names or len(set(names)) != len(names):
            raise ValueError(f"expected distinct axis names, got {names!r}")
        self.log = RunLog(writer, live=live)
        self.names = names
        self._sinks = {name: LaneSink(self.log, lane) for lane, name in enumerate(names, start=1)}
        self._buses: dict[str, tuple[int, str]] = {}   # bus name -> (lane, topic prefix)

    @classmethod
    def open(cls, path: str | os.PathLike[str], axes: Iterable[str], *, live: LiveView | None = None,
             fsync: bool = True, layout: str = DEFAULT_LAYOUT) -> AxesLog:
        """A log of the axes named ``axes`` (in the loop's order) to the new file ``path``
        (created now; its writer process started, not yet open)."""
        names = tuple(axes)
        return cls(WriterProcess(Path(path), fsync=fsync, layout=layout), names, live=live)

    @property
    def path(self) -> Path:
        return self.log.path

    @property
    def writer(self) -> WriterProcess:
        return self.log.writer

    @property
    def writer_pid(self) -> int | None:
        return self.log.writer_pid

    @property
    def live(self) -> LiveView | None:
        return self.log.live

    @property
    def live_port(self) -> int | None:
        return self.log.live_port

    @property
    def buses(self) -> Mapping[str, str]:
        """Bus name -> the prefix of its frame topics, in the order the buses were wrapped."""
        return {name: prefix for name, (_, prefix) in self._buses.items()}

    def sink(self, axis: str) -> LaneSink:
        """The ``CycleSink`` of axis ``axis``."""
        try:
            return self._sinks[axis]
        except KeyError:
            raise KeyError(f"no axis {axis!r} in this log; axes: {', '.join(self.names)}") from None

    def wrap_bus(self, bus: can.BusABC, bus_name: str) -> can.BusABC:
        """The session's ``bus_wrapper``: every frame of ``bus`` on ``/bus/<bus_name>/can/rx``
        and ``.../can/tx``. A bus wrapped twice (two sessions' taps of one bus) shares its topics."""
        if self.log.writer.opened:
            raise RecorderError(f"{self.path}: bus {bus_name!r} wrapped after the log began; "
                                "wrap every bus before begin()")
        if bus_name not in self._buses:
            taken = {prefix for _, prefix in self._buses.values()}
            stem = BUS_PREFIX + (_TOPIC_SAFE.sub("_", bus_name) or "_")
            prefix, n = stem, 2
            while prefix in taken:
                prefix, n = f"{stem}-{n}", n + 1
            self._buses[bus_name] = (1 + len(self.names) + len(self._buses), prefix)
        return self.log.wrap_bus(bus, self._buses[bus_name][0])

    def lanes(self, drives: Mapping[str, AxisDrive]) -> tuple[Lane, ...]:
        """The writer's lanes: the run's (no prefix: its events), each axis' (its own topics),
        each bus' (its frames)."""
        return (Lane("", None, RUN_LANE), *(Lane(axis_prefix(n), drives[n].codes, AXIS_LANE) for n in self.names),
                *(Lane(prefix, None, BUS_LANE) for _, prefix in self._buses.values()))

    def begin(self, *, metadata: Mapping[str, Mapping[str, Any]], attachments: Sequence[tuple[str, str, bytes]],
              lossy: bool, drives: Mapping[str, AxisDrive], clock_ns: Callable[[], int] | None = None,
              couplings: Sequence[Mapping[str, Any]] = (), cancel: Callable[[], str] | None = None) -> None:
        """Header, ``metadata`` (the run's, each axis' and bus' records) with the ``axes``
        record, attachments; each axis' drive, truth and codes (``drives``, one per axis);
        the log clock (simulated time in lockstep), lossy in real time; ``cancel``: the run's
        stop request, which ends a lockstep hand-over's wait (:meth:`RunLog.begin`)."""
        missing = [n for n in self.names if n not in drives]
        unknown = sorted({d.bus for d in drives.values()} - set(self._buses))
        if missing or unknown:
            raise RecorderError(f"{self.path}: " + (f"no drive for axis {missing[0]!r}" if missing else
                                                    f"bus {unknown[0]!r} of an axis was never wrapped"))
        layout = {"names": json.dumps(list(self.names)), "format": AXES_FORMAT,
                  "bus_of": json.dumps({n: drives[n].bus for n in self.names}),
                  "buses": json.dumps(dict(self.buses)), "couplings": json.dumps(list(map(dict, couplings)))}
        own: dict[int, set[int]] = {}
        known = True
        for n in self.names:
            ids = drives[n].own_ids
            if ids is None:
                known = False   # a drive of unknown ids: nothing on the buses is foreign
            own.setdefault(self._buses[drives[n].bus][0], set()).update(ids or ())
        self.log.begin(metadata={**metadata, AXES_METADATA: layout}, attachments=attachments, lossy=lossy,
                       clock_ns=clock_ns, lanes=self.lanes(drives), own=own if known else None, cancel=cancel)
        for n in self.names:
            sink = self._sinks[n]
            sink.drive, sink.truth = drives[n].drive, drives[n].truth

    def event(self, kind: EventKind, reason: str, detail: str = "") -> None:
        """An event of the whole run on ``/events``."""
        self.log.event(kind, reason, detail)

    @property
    def end_failure(self) -> str:
        """Why the log's end failed (:meth:`end` raised it), "" while it did not."""
        return self.log.end_failure

    def end(self, stop_reason: str | None, detail: str = "", cancel: Callable[[], str] | None = None) -> None:
        """The last records, the stop event, summary and footer; waits for the writer, for a
        bounded time (:meth:`RunLog.end`). Raises :class:`~dobhil.errors.RecorderError` if
        the writer failed (once)."""
        self.log.end(stop_reason, detail, cancel)


__all__ = ["AXES_FORMAT", "AXES_METADATA", "AXIS_PREFIX", "BUS_PREFIX", "AxesLog", "AxisDrive", "axis_prefix",
           "axis_record", "bus_record"]
