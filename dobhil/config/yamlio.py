"""YAML as dobhil reads it (configs, ``--set`` values, drive profiles).

PyYAML's safe loader with one change: a key given twice in one mapping is an error
naming the key and both lines (PyYAML keeps the last one silently, so a typo'd copy of
a key would quietly win). Errors are :class:`yaml.YAMLError` with a ``problem_mark``,
like any syntax error, so callers report them the same way.
"""

from __future__ import annotations

from typing import Any

import yaml
from yaml.constructor import ConstructorError
from yaml.nodes import MappingNode

__all__ = ["UniqueKeyLoader", "safe_load", "where"]

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
