"""One recorded topic to CSV: a ``log_time_ns`` column, then one per schema property.

The columns come from the JSON schema stored in the file, so old recordings export
with the columns they were written with. Lists (CAN ``data``) become space-separated
integers, booleans ``true``/``false``, missing values and ``null`` empty cells.
"""

from __future__ import annotations

import csv
import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from dobhil.errors import LogFileError
from dobhil.recording.reader import open_log

ProgressFn = Callable[[int], None]


def default_output(mcap_path: str | os.PathLike[str], topic: str) -> Path:
    """``run.mcap`` + ``/drive/feedback`` -> ``run.drive_feedback.csv``."""
    slug = topic.strip("/").replace("/", "_") or "topic"
    return Path(mcap_path).with_suffix(f".{slug}.csv")


def cell(value: Any) -> str:
    """One CSV cell of a JSON value."""
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, list):
        return " ".join(cell(v) for v in value)
    return str(value)


def row(log_time_ns: int, payload: Mapping[str, Any], columns: Sequence[str]) -> list[str]:
    """The CSV row of one message."""
    return [str(log_time_ns), *(cell(payload.get(c)) for c in columns)]


def export_csv(
    mcap_path: str | os.PathLike[str],
    topic: str,
    out: str | os.PathLike[str],
    *,
    progress: ProgressFn | None = None,
) -> int:
    """Write ``topic`` of the recording to ``out`` as CSV; the row count."""
    log = open_log(mcap_path)
    columns = log.schema_properties(topic)
    try:
        sink = open(out, "w", newline="", encoding="utf-8")
    except OSError as exc:
        raise LogFileError(f"{os.fspath(out)}: cannot create: {exc.strerror}") from exc
    count = 0
    with sink:
        writer = csv.writer(sink)
        writer.writerow(["log_time_ns", *columns])
        for _, log_time_ns, payload in log.iter_messages([topic]):
            writer.writerow(row(log_time_ns, payload, columns))
            count += 1
            if progress is not None:
                progress(1)
    return count


__all__ = ["cell", "default_output", "export_csv", "row"]
