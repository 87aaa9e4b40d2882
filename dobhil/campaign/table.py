"""The campaign's table on disk: ``runs.csv`` (always available) or ``runs.parquet``
(pyarrow, an optional dependency), written atomically (:func:`dobhil.files.atomic_path`).

Parquet columns are typed from the rows: integers (run, seeds, cycles, overruns, integer
keys), booleans (retried, settled), strings (stop reason, error), float64 for the rest, with
null for a metric a run does not have. CSV leaves such a cell empty.
"""

from __future__ import annotations

import csv
import importlib.util
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
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


#: rows a parquet table takes at a time (one row group each): bounded memory for any length
ROW_GROUP = 10_000


def write_table(rows: Iterable[dict[str, Any]], columns: Sequence[str], path: Path, fmt: str,
                integer_keys: Sequence[str] = ()) -> Path:
    with table_writer(columns, path, fmt, integer_keys) as write:
        for row in rows:
            write(row)
    return path


@contextmanager
def table_writer(columns: Sequence[str], path: Path, fmt: str,
                 integer_keys: Sequence[str] = ()) -> Iterator[Any]:
    """``write(row)`` for each row as it comes: CSV a line each, parquet a row group per
    :data:`ROW_GROUP` rows, so no table of a campaign is ever held whole. The file appears
    at ``path`` when the block ends normally (:func:`dobhil.files.atomic_path`)."""
    from dobhil.files import atomic_path
    with atomic_path(path) as tmp:
        if fmt == "parquet":
            with _parquet_writer(columns, tmp, (*INTEGER, *integer_keys)) as write:
                yield write
        else:
            with tmp.open("w", newline="") as fh:
                writer = csv.DictWriter(fh, fieldnames=list(columns))
                writer.writeheader()
                yield lambda row: writer.writerow({c: ("" if row[c] is None else row[c]) for c in columns})


def _arrow_type(column: str, integers: Sequence[str]) -> Any:
    import pyarrow as pa
    if column in TEXT:
        return pa.string()
    if column in BOOLEAN:
        return pa.bool_()
    return pa.int64() if column in integers else pa.float64()


@contextmanager
def _parquet_writer(columns: Sequence[str], path: Path, integers: Sequence[str]) -> Iterator[Any]:
    import pyarrow as pa
    import pyarrow.parquet as pq
    schema = pa.schema([(c, _arrow_type(c, integers)) for c in columns])
    batch: list[dict[str, Any]] = []

    def flush() -> None:
        writer.write_table(pa.Table.from_pylist(batch, schema=schema))
        batch.clear()

    def write(row: dict[str, Any]) -> None:
        batch.append({c: row[c] for c in columns})
        if len(batch) >= ROW_GROUP:
            flush()
    with pq.ParquetWriter(path, schema) as writer:
        yield write
        if batch:
            flush()


def read_table(path: Path) -> list[dict[str, Any]]:
    """The rows of a ``runs.parquet`` (for checks and tests): column -> Python value."""
    import pyarrow.parquet as pq
    return list(pq.read_table(path).to_pylist())


__all__ = ["FORMATS", "check_format", "read_table", "table_name", "table_writer", "write_table"]
