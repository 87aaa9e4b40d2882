"""The list of slow tests (``tests/slow-tests.txt``) that ``tests/conftest.py`` marks ``slow``."""

from __future__ import annotations

from pathlib import Path

#: node ids (or a file, or a test without its parameters) of the tests ``-m "not slow"`` leaves
#: out, each with the seconds it took; a list kept apart so the tests themselves stay unmarked
SLOW_LIST = Path(__file__).with_name("slow-tests.txt")


def slow_entries(text: str) -> frozenset[str]:
    """The entries of ``tests/slow-tests.txt``: one a line, ``#`` starts a comment."""
    return frozenset(line.split("#", 1)[0].strip() for line in text.splitlines()) - {""}


def is_listed(nodeid: str, entries: frozenset[str]) -> bool:
    """``nodeid`` is an entry, a parametrization of one (``test_x[a]`` of ``test_x``) or a
    test of a listed file or class."""
    if nodeid in entries:
        return True
    base = nodeid.split("[", 1)[0]
    parts = base.split("::")
    return any("::".join(parts[:n]) in entries for n in range(1, len(parts) + 1))
