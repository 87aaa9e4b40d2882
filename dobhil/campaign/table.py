"""The campaign's table on disk: ``runs.csv`` (always available) or ``runs.parquet``
(pyarrow, an optional dependency), written atomically (:func:`dobhil.files.atomic_path`).

Parquet columns are typed from the rows: integers (run, seeds, cycles, overruns, integer
keys), booleans (retried, settled), strings (stop reason, error), float64 for the rest, with
null for a metric a run does not have. CSV leaves such a cell empty.
"""

from __future__ import annotations

import csv
import importlib.util
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from dobhil.errors import ConfigError

FORMATS = ("csv", "parquet")

#: columns that are always text, booleans (null: not known) or always whole numbers (the rest: floats)
TEXT = ("stop_reason", "error")
BOOLEAN = ("retried", "settled")
INTEGER = ("run", "seed", "sensor_seed", "cycles", "overruns")


def check_format(fmt: str) -> None:
    """Before a campaign starts: parquet needs pyarrow (not a core dependency)."""
    if fmt == "parquet" and importlib.util.find_spec("pyarrow") is None:
        raise ConfigError("--format parquet needs pyarrow, which is not installed: pip install pyarrow "
                          "(or use --format csv)")


def table_name(fmt: str) -> str:
    return f"runs.{fmt}"


def write_table(rows: Sequence[dict[str, Any]], columns: Sequence[str], path: Path, fmt: str,
                integer_keys: Sequence[str] = ()) -> Path:
    if fmt == "parquet":
        return _write_parquet(rows, columns, path, (*INTEGER, *integer_keys))
    return _write_csv(rows, columns, path)


def _write_csv(rows: Sequence[dict[str, Any]], columns: Sequence[str], path: Path) -> Path:
    from dobhil.files import atomic_path
    with atomic_path(path) as tmp, tmp.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(columns))
        writer.writeheader()
        for row in rows:
            writer.writerow({c: ("" if row[c] is None else row[c]) for c in columns})
    return path


def _arrow_type(column: str, integers: Sequence[str]) -> Any:
    import pyarrow as pa
    if column in TEXT:
        return pa.string()
    if column in BOOLEAN:
        return pa.bool_()
    return pa.int64() if column in integers else pa.float64()


def _write_parquet(rows: Sequence[dict[str, Any]], columns: Sequence[str], path: Path,
                   integers: Sequence[str]) -> Path:
    import pyarrow as pa
    import pyarrow.parquet as pq
    from dobhil.files import atomic_path
    schema = pa.schema([(c, _arrow_type(c, integers)) for c in columns])
    table = pa.Table.from_pylist([{c: row[c] for c in columns} for row in rows], schema=schema)
    with atomic_path(path) as tmp:
        pq.write_table(table, tmp)
    return path


def read_table(path: Path) -> list[dict[str, Any]]:
    """The rows of a ``runs.parquet`` (for checks and tests): column -> Python value."""
    import pyarrow.parquet as pq
    return list(pq.read_table(path).to_pylist())


__all__ = ["FORMATS", "check_format", "read_table", "table_name", "write_table"]
