"""The list of slow tests (``tests/slow-tests.txt``) that ``tests/conftest.py`` marks ``slow``."""

from __future__ import annotations

import re
from collections.abc import Mapping
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


#: the seconds an entry's comment gives: the first number followed by "s" (``# 4 s``,
#: ``# ~60 s (...)``, ``# a module set-up of 2 s, ...``)
_SECONDS = re.compile(r"#\D*?~?(\d+(?:\.\d+)?) s\b")


def slow_seconds(text: str) -> dict[str, float]:
    """Each entry of ``tests/slow-tests.txt`` with the seconds its comment gives (entries
    without a figure are left out)."""
    out: dict[str, float] = {}
    for line in text.splitlines():
        entry = line.split("#", 1)[0].strip()
        found = _SECONDS.search(line)
        if entry and found:
            out[entry] = float(found.group(1))
    return out


def heaviest_first(nodeids: list[str], seconds: Mapping[str, float]) -> list[int]:
    """The order (indices into ``nodeids``) that runs the files with the most listed seconds
    first, each file's tests together and in their own order (module-scoped set-ups stay
    paid once per worker), files of equal weight in their given order.

    Why: pytest-xdist's ``load`` scheduler hands tests out in collection order, a chunk to
    each worker and then one or a few at a time; a file of 40 s collected last starts when the
    other worker has nothing left and ends the run alone. Longest first is Graham's rule
    (R. L. Graham, "Bounds on multiprocessing timing anomalies", SIAM J. Appl. Math. 17,
    1969): the run ends within a third of the optimum, the longest job at worst at the
    start, not the end."""
    weight: dict[str, float] = {}
    for entry, value in seconds.items():
        path = entry.split("::", 1)[0]
        weight[path] = weight.get(path, 0.0) + value
    files = [nodeid.split("::", 1)[0] for nodeid in nodeids]
    return sorted(range(len(nodeids)), key=lambda i: -weight.get(files[i], 0.0))
