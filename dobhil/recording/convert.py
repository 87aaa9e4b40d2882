"""A topic of a recording as CSV (``dobhil log export --topic``): ``log_time_ns``, then one
column per property of the schema stored in the file; lists space-separated, booleans
``true``/``false``, ``null`` empty. Checked first, written under a temporary name. (CAN logs
in python-can's formats: :mod:`dobhil.canio.canlog`.)
"""

from __future__ import annotations

import csv
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from dobhil.files import atomic_path, check_output
from dobhil.recording.reader import open_log

ProgressFn = Callable[[int], None]


def default_csv_output(mcap_path: str | os.PathLike[str], topic: str) -> Path:
    """``run.mcap`` + ``/drive/feedback`` -> ``run.drive_feedback.csv``."""
    return Path(mcap_path).with_suffix(f".{topic.strip('/').replace('/', '_') or 'topic'}.csv")


def cell(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, list):
        return " ".join(map(cell, value))
    return "" if value is None else str(value)


def export_csv(mcap_path: str | os.PathLike[str], topic: str, out: str | os.PathLike[str], *,
               progress: ProgressFn | None = None) -> int:
    """``topic`` of the recording to ``out`` as CSV; the row count."""
    check_output(out, inputs=[mcap_path], what="output", suffix=".csv")
    count = 0
    # describe: a copy of what was recorded never applies the config, so a newer dobhil's log is exported too
    log = open_log(mcap_path, describe=True)
    with atomic_path(out) as tmp, open(tmp, "w", newline="", encoding="utf-8") as sink:
        columns, writer = log.schema_properties(topic), csv.writer(sink)
        writer.writerow(["log_time_ns", *columns])
        for _, t, payload in log.iter_messages([topic]):
            writer.writerow([str(t), *(cell(payload.get(c)) for c in columns)])
            count += 1
            if progress is not None:
                progress(1)
    return count


__all__ = ["cell", "default_csv_output", "export_csv"]
