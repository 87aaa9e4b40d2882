"""``tests/slow-tests.txt``, the tests ``pytest -m "not slow"`` leaves out: every entry names a
test that exists (a renamed test would silently rejoin the edit loop's run), and the matching
marks what it lists and nothing else."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from slow_list import SLOW_LIST, is_listed, slow_entries

ROOT = Path(__file__).resolve().parents[1]


def test_every_entry_names_a_test_that_exists() -> None:
    entries = slow_entries(SLOW_LIST.read_text(encoding="utf-8"))
    assert entries, "an empty list: -m 'not slow' would run everything"
    missing = []
    for entry in sorted(entries):
        path, *names = entry.split("[", 1)[0].split("::")
        source = ROOT / path
        if not source.is_file():
            missing.append(entry)
            continue
        text = source.read_text(encoding="utf-8")
        defined = [re.search(rf"^\s*(def|class) {re.escape(name)}\b", text, re.M) for name in names]
        missing += [entry] if not all(defined) else []
    assert not missing, f"slow-tests.txt names tests that do not exist: {missing}"


@pytest.mark.parametrize(("nodeid", "listed"), [
    ("tests/a.py::test_x", True),                 # the entry itself
    ("tests/a.py::test_x[lockstep-odrive]", True),  # a parametrization of it
    ("tests/a.py::test_xy", False),               # a longer name is another test
    ("tests/a.py::test_y[p]", True),              # this parametrization only
    ("tests/a.py::test_y[q]", False),
    ("tests/b.py::test_anything", True),          # a whole file
    ("tests/c.py::TestK::test_m", True),          # a whole class
    ("tests/c.py::TestL::test_m", False),
    ("tests/bb.py::test_anything", False),
])
def test_entries_match_their_tests_only(nodeid: str, listed: bool) -> None:
    entries = slow_entries("# a comment\ntests/a.py::test_x  # 3 s\ntests/a.py::test_y[p]\n\ntests/b.py\n"
                           "tests/c.py::TestK\n")
    assert is_listed(nodeid, entries) is listed
