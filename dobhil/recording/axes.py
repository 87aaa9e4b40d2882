"""Reading the axes of a log: every dobhil log is read as axes, a single-axis log (any
version's: its topics without prefix) as one axis named ``axis``, a several-axis log
(:mod:`dobhil.recording.axeslog`) as the axes its ``axes`` metadata names.

:class:`AxisLog` is one axis read like a single-axis :class:`~dobhil.recording.reader.LogFile`:
its topics by their single-axis names (``/controller``, ``/drive/feedback``, ``/can/rx``, ...;
``/can/*`` are its bus' frames, every axis' on that bus; ``/events`` the run's and the
axis' own), its ``config`` and its ``metadata`` (``config``, ``drive``, ``bus``, ``run`` of
the axis, the run's other records). So replay, report and identify read any axis with the code
that reads a single-axis log.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Any, Final

from dobhil.config.axes import SINGLE_AXIS
from dobhil.errors import LogFileError, exception_line
from dobhil.recording.axeslog import AXES_METADATA, AXIS_PREFIX, BUS_PREFIX, axis_prefix, axis_record, bus_record
from dobhil.recording.reader import LogFile, open_log, recorded_config, unknown_config_keys, unknown_keys_problem

#: The topics of an axis' bus (the rest are the axis' own).
BUS_TOPICS: Final = ("/can/rx", "/can/tx")
#: The run's topic an axis shares (besides its own of the same name).
RUN_TOPICS: Final = ("/events",)
#: An axis' metadata records (``axis/<name>/<record>``).
AXIS_RECORDS: Final = ("config", "drive", "run", "stability_gate")


@dataclass(frozen=True)
class Layout:
    """A log's axes: their names in the loop's order, each axis' bus, each bus' topic prefix
    and the couplings; ``listed`` False for a single-axis log (no prefixes)."""

    names: tuple[str, ...]
    bus_of: Mapping[str, str]
    buses: Mapping[str, str]
    couplings: tuple[Mapping[str, Any], ...] = ()
    listed: bool = True

    def partners(self, name: str) -> tuple[str, ...]:
        """The axes ``name`` is coupled to (``environment.coupling``), sorted."""
        return tuple(sorted({str(c.get("b") if c.get("a") == name else c.get("a"))
                             for c in self.couplings if name in (c.get("a"), c.get("b"))}))


def layout(log: LogFile) -> Layout:
    """The axes of ``log`` (a single-axis log: one axis named ``axis`` on its one bus)."""
    return metadata_layout(log.metadata, log.path)


def metadata_layout(metadata: Mapping[str, Mapping[str, str]], path: str | os.PathLike[str]) -> Layout:
    """:func:`layout` of a log's metadata records (a reader that has no :class:`LogFile`, such
    as python-can's ``can.LogReader`` plugin, dobhil/canio/mcap_reader.py); ``path`` names the
    log in an error."""
    record = metadata.get(AXES_METADATA)
    if record is None:
        bus = str(metadata.get("bus", {}).get("channel", "") or "bus")
        return Layout((SINGLE_AXIS,), {SINGLE_AXIS: bus}, {bus: ""}, (), listed=False)
    try:
        names = json.loads(record["names"])
        bus_of = json.loads(record["bus_of"])
        buses = json.loads(record["buses"])
        couplings = json.loads(record.get("couplings", "[]"))
        ok = (isinstance(names, list) and names and all(isinstance(n, str) for n in names)
              and isinstance(bus_of, dict) and isinstance(buses, dict) and set(names) <= set(bus_of)
              and all(b in buses for b in bus_of.values()) and isinstance(couplings, list))
    except (KeyError, TypeError, ValueError) as exc:
        raise LogFileError(f"{os.fspath(path)}: invalid metadata {AXES_METADATA} ({exception_line(exc)})") from None
    if not ok:
        raise LogFileError(f"{os.fspath(path)}: invalid metadata {AXES_METADATA}: expected names, each axis' bus and "
                           f"each bus' topic prefix, got {dict(record)}")
    return Layout(tuple(names), MappingProxyType(bus_of), MappingProxyType(buses), tuple(couplings))


def axis_names(log: LogFile) -> tuple[str, ...]:
    """The names of the axes of ``log``, in the loop's order."""
    return layout(log).names


class AxisLog:
    """Axis ``name`` of ``log``, read like a single-axis log (see the module docstring)."""

    def __init__(self, log: LogFile, name: str, lay: Layout | None = None) -> None:
        lay = lay or layout(log)
        if name not in lay.names:
            raise LogFileError(f"{log.path}: no axis {name!r}; axes: {', '.join(lay.names)}")
        self.file, self.name, self.path, self.listed = log, name, log.path, lay.listed
        self.bus = lay.bus_of[name]
        self.axes = lay.names
        #: the axes this one is coupled to (none in a single-axis log)
        self.coupled_to = lay.partners(name)
        own, bus = (axis_prefix(name), lay.buses[self.bus]) if lay.listed else ("", "")
        #: topic in the file -> the name this axis reads it by
        self._names: dict[str, str] = {}
        for topic in log.topics():
            if lay.listed and topic.startswith(own + "/"):
                self._names[topic] = topic[len(own):]
            elif lay.listed and topic.startswith(bus + "/") and topic[len(bus):] in BUS_TOPICS:
                self._names[topic] = topic[len(bus):]
            elif not lay.listed or topic in RUN_TOPICS:
                self._names[topic] = topic
        self.metadata = self._metadata(log, lay) if lay.listed else log.metadata
        self.config: Any = self._config() if lay.listed else log.config

    def _metadata(self, log: LogFile, lay: Layout) -> Mapping[str, Mapping[str, str]]:
        """The run's records (not another axis' or bus'), then the axis' own and its bus'."""
        out = {k: v for k, v in log.metadata.items() if not k.startswith(("axis/", "bus/"))}
        for record in AXIS_RECORDS:
            own = log.metadata.get(axis_record(self.name, record))
            if own is not None:
                out[record] = MappingProxyType({**out.get(record, {}), **own})
        bus = log.metadata.get(bus_record(self.bus))
        if bus is not None:
            out["bus"] = bus
        return MappingProxyType(out)

    def _config(self) -> Any:
        record = self.metadata.get("config")
        if not record:
            return None
        unknown = unknown_config_keys(record)
        if unknown:
            raise LogFileError(f"{self.path}: " + unknown_keys_problem(f"axis {self.name}'s recorded config", unknown,
                                                                     self.file.library))
        return recorded_config(self.path, record, self.name)

    @property
    def frame_ids(self) -> frozenset[int] | None:
        """The arbitration ids of this axis' drive's frames on its bus as the run recorded
        them (``axis/<name>/run.frame_ids``); None when not known (a single-axis log: every
        frame of its bus is the drive's)."""
        raw = self.metadata.get("run", {}).get("frame_ids") if self.listed else None
        try:
            ids = json.loads(raw) if raw else None
        except ValueError:
            return None
        return frozenset(ids) if isinstance(ids, list) and all(isinstance(i, int) for i in ids) else None

    def __enter__(self) -> AxisLog:
        return self

    def __exit__(self, *exc: object) -> None:
        pass

    def topics(self) -> tuple[str, ...]:
        return tuple(dict.fromkeys(self._names.values()))

    def require_topic(self, topic: str) -> None:
        if topic not in self.topics():
            where = f"axis {self.name} of " if self.listed else ""
            raise LogFileError(f"{self.path}: {where}no topic {topic!r}; available: "
                               f"{', '.join(self.topics()) or 'none'}")

    def message_count(self, topics: Iterable[str]) -> int:
        """How many messages :meth:`iter_messages` of ``topics`` yields, from the file's
        statistics (0 for a file without them)."""
        wanted = set(topics)
        names = {t for t, n in self._names.items() if n in wanted}
        return sum(count for topic, count in self.file.message_counts().items() if topic in names)

    def iter_payloads(self, topics: Iterable[str] | None = None) -> Iterator[tuple[str, int, bytes]]:
        """(topic as this axis names it, log_time_ns, message bytes) in file order."""
        wanted = None if topics is None else set(topics)
        names = {t: n for t, n in self._names.items() if wanted is None or n in wanted}
        for topic, t, data in self.file.iter_payloads(names):
            yield names[topic], t, data

    def iter_messages(self, topics: Iterable[str] | None = None) -> Iterator[tuple[str, int, dict[str, Any]]]:
        """(topic as this axis names it, log_time_ns, payload dict) in file order."""
        wanted = None if topics is None else set(topics)
        names = {t: n for t, n in self._names.items() if wanted is None or n in wanted}
        for topic, t, payload in self.file.iter_messages(names):
            yield names[topic], t, payload

    def iter_rows(self, fields: Mapping[str, Sequence[str]], defaults: Mapping[str, Any] | None = None
                  ) -> Iterator[tuple[str, int, tuple[Any, ...]]]:
        """:meth:`LogFile.iter_rows` with ``fields`` and the topics as this axis names them."""
        names = {t: n for t, n in self._names.items() if n in fields}
        for topic, t, row in self.file.iter_rows({t: fields[n] for t, n in names.items()}, defaults):
            yield names[topic], t, row


def axis_logs(path: str | os.PathLike[str] | LogFile) -> tuple[AxisLog, ...]:
    """Every axis of the log at ``path`` (checked), in the loop's order."""
    log = path if isinstance(path, LogFile) else open_log(path)
    lay = layout(log)
    return tuple(AxisLog(log, name, lay) for name in lay.names)


def axis_log(path: str | os.PathLike[str] | LogFile, name: str | None = None) -> AxisLog:
    """Axis ``name`` of the log at ``path``; None: its one axis (a several-axis log names its axes)."""
    log = path if isinstance(path, LogFile) else open_log(path)
    lay = layout(log)
    if name is None:
        if len(lay.names) != 1:
            raise LogFileError(f"{log.path}: a log of {len(lay.names)} axes ({', '.join(lay.names)}); "
                               "name one with --axis NAME")
        name = lay.names[0]
    return AxisLog(log, name, lay)


def bus_topics(log: LogFile) -> dict[str, tuple[str, str]]:
    """Bus name -> its (rx, tx) frame topics in the file."""
    lay = layout(log)
    return {bus: (prefix + BUS_TOPICS[0], prefix + BUS_TOPICS[1]) for bus, prefix in lay.buses.items()}


def is_axes_log(path: str | os.PathLike[str] | Path | LogFile) -> bool:
    """True for a several-axis log (its ``axes`` metadata)."""
    log = path if isinstance(path, LogFile) else open_log(path)
    return AXES_METADATA in log.metadata


__all__ = ["AXIS_PREFIX", "AXIS_RECORDS", "BUS_PREFIX", "BUS_TOPICS", "AxisLog", "Layout", "axis_log", "axis_logs",
           "axis_names", "bus_topics", "is_axes_log", "layout",
           "metadata_layout"]
