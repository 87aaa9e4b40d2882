"""YAML as dobhil reads it (configs, ``--set`` values, drive profiles).

PyYAML's safe loader with one change: a key given twice in one mapping is an error
naming the key and both lines (PyYAML keeps the last one silently, so a typo'd copy of
a key would quietly win). Errors are :class:`yaml.YAMLError` with a ``problem_mark``,
like any syntax error, so callers report them the same way.
"""

from __future__ import annotations

import os
import reprlib
import stat
from pathlib import Path
from typing import Any

import yaml
from yaml.constructor import ConstructorError
from yaml.nodes import MappingNode

from dobhil.errors import ConfigError, exception_line

__all__ = ["MAX_TEXT_BYTES", "UniqueKeyLoader", "TextFileError", "load_yaml_file", "read_text_file", "safe_load",
           "show_value", "where"]

#: the largest YAML file dobhil reads (configs and profiles are a few kB; a larger file is
#: not one, and PyYAML would take minutes over it)
MAX_TEXT_BYTES = 1 << 20

_MERGE_TAG = "tag:yaml.org,2002:merge"


class UniqueKeyLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that rejects duplicate keys in a mapping."""

    def construct_mapping(self, node: MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: dict[Any, int] = {}
        for key_node, _ in node.value:
            if key_node.tag == _MERGE_TAG:
                continue
            key = self.construct_object(key_node, deep=True)
            try:
                first = seen.get(key)
            except TypeError:  # an unhashable key: SafeLoader reports it below
                continue
            line = key_node.start_mark.line
            if first is not None:
                raise ConstructorError(None, None, f"duplicate key {key!r} (first at line {first + 1})",
                                       key_node.start_mark)
            seen[key] = line
        return super().construct_mapping(node, deep=deep)


def safe_load(text: str) -> Any:
    """Parse YAML text like ``yaml.safe_load``, rejecting duplicate keys."""
    return yaml.load(text, Loader=UniqueKeyLoader)  # safe: a SafeLoader subclass


def where(exc: yaml.YAMLError) -> str:
    """`` at line L, column C: problem`` of a YAML error, for a one-line message."""
    mark = getattr(exc, "problem_mark", None)
    problem = getattr(exc, "problem", None) or ""
    at = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
    return f"{at}: {problem}" if problem else at


class TextFileError(ValueError):
    """A text file that cannot be read; the message is one line (no path: callers add it)."""


def read_text_file(path: str | os.PathLike[str], *, limit: int = MAX_TEXT_BYTES) -> str:
    """The UTF-8 text of a regular file of at most ``limit`` bytes, or :class:`TextFileError`.

    A FIFO or a device (``/dev/zero``) is refused before it is opened: reading one would
    block or never end. Missing files raise :class:`FileNotFoundError` (callers word it).
    """
    p = Path(path)
    try:
        info = p.stat()
    except FileNotFoundError:
        raise
    except OSError as exc:
        raise TextFileError(f"cannot be read: {exc.strerror or exc.__class__.__name__}") from None
    if stat.S_ISDIR(info.st_mode):
        raise TextFileError("is a directory, not a file")
    if not stat.S_ISREG(info.st_mode):
        raise TextFileError("is not a regular file (a FIFO, socket or device)")
    if info.st_size > limit:
        raise TextFileError(f"is too large ({info.st_size} bytes; at most {limit} allowed)")
    try:
        with p.open("rb") as fh:
            data = fh.read(limit + 1)
    except OSError as exc:
        raise TextFileError(f"cannot be read: {exc.strerror or exc.__class__.__name__}") from None
    if len(data) > limit:  # grew since stat
        raise TextFileError(f"is too large (more than {limit} bytes)")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise TextFileError(f"is not UTF-8 text (byte 0x{data[exc.start]:02x} at offset {exc.start})") from None


def load_yaml_file(path: str | os.PathLike[str], what: str) -> Any:
    """The parsed YAML of a data file (a drive profile, the MIT model table), or a one-line
    ConfigError naming the file and ``what`` it was read as: unreadable, not text, too
    large, or a YAML error with its line and column."""
    try:
        return safe_load(read_text_file(path))
    except TextFileError as exc:
        raise ConfigError(f"{path}: cannot read {what}: it {exc}") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: YAML error in {what}{where(exc)}") from None
    except (OSError, ValueError, RecursionError) as exc:
        raise ConfigError(f"{path}: cannot read {what}: {exception_line(exc, named=False)}") from None


def _short_repr() -> reprlib.Repr:
    r = reprlib.Repr()
    r.maxlevel, r.maxlist, r.maxtuple, r.maxdict, r.maxset = 2, 4, 4, 3, 4
    r.maxstring = r.maxother = 50
    return r


_SHORT = _short_repr()


def show_value(value: Any, width: int = 60) -> str:
    """A value read from YAML, quoted in a one-line error: short whatever its size.

    ``repr`` would take forever on an alias bomb (``&a [..] &b [*a, *a, ..]`` nests 9**9
    references in a few hundred bytes) and fails on an integer of more than 4300 digits;
    :mod:`reprlib` stops at a depth and a length.
    """
    if isinstance(value, int) and not isinstance(value, bool) and value.bit_length() > 64:
        digits = len(str(value)) if value.bit_length() < 14_000 else "thousands of"
        return f"<an integer of {digits} digits>"
    text = " ".join(_SHORT.repr(value).split())
    return text if len(text) <= width else text[: width - 3] + "..."
