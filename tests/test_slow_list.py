"""``tests/slow-tests.txt``, the tests ``pytest -m "not slow"`` leaves out: every entry names a
test that exists (a renamed test would silently rejoin the edit loop's run), and the matching
marks what it lists and nothing else."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from slow_list import SLOW_LIST, heaviest_first, is_listed, slow_entries, slow_seconds

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


def test_every_listed_figure_is_read() -> None:
    """Each entry's seconds reach the ordering: a figure the pattern misses would run a slow
    file late (only the entries whose comment gives no number are left out)."""
    text = SLOW_LIST.read_text(encoding="utf-8")
    seconds = slow_seconds(text)
    with_figure = [line.split("#", 1)[0].strip() for line in text.splitlines()
                   if not line.startswith("#") and re.search(r"#.*\d s\b", line)]
    assert sorted(seconds) == sorted(with_figure)
    assert seconds["tests/identify/test_cli.py"] == 31.0            # "a module set-up of 31 s"
    assert all(value > 0 for value in seconds.values())


def test_heaviest_files_first_each_file_together_and_in_order() -> None:
    ids = ["tests/a.py::t1", "tests/a.py::t2", "tests/b.py::t1", "tests/c.py::t1", "tests/c.py::t2",
           "tests/d.py::t1"]
    seconds = {"tests/a.py::t2": 1.0, "tests/c.py::t1": 2.0, "tests/c.py::t2[x]": 3.0,
               "tests/d.py": 4.0}
    order = [ids[i] for i in heaviest_first(ids, seconds)]
    # c (5 s) before d (4 s) before a (1 s) before b (none); within a file, collection order
    assert order == ["tests/c.py::t1", "tests/c.py::t2", "tests/d.py::t1", "tests/a.py::t1",
                     "tests/a.py::t2", "tests/b.py::t1"]


def test_this_run_is_in_that_order(request: pytest.FixtureRequest) -> None:
    """The items of this very run (tests/conftest.py's hook): the guest's first, then the
    host's files by listed weight, never heavier after lighter, each file in one piece."""
    ids = [item.nodeid for item in request.session.items]
    host = [nodeid for nodeid in ids if not nodeid.startswith("tests/socketcan/")]
    assert ids[:len(ids) - len(host)] == [n for n in ids if n.startswith("tests/socketcan/")]
    seconds = slow_seconds(SLOW_LIST.read_text(encoding="utf-8"))
    files = [nodeid.split("::", 1)[0] for nodeid in host]
    runs = [f for k, f in enumerate(files) if k == 0 or f != files[k - 1]]
    assert len(runs) == len(set(runs)), "a file split in two"
    weights = [sum(v for e, v in seconds.items() if e.split("::", 1)[0] == f) for f in runs]
    assert weights == sorted(weights, reverse=True)


def test_not_slow_leaves_out_what_the_list_names(tmp_path: Path) -> None:
    """pytest's own ``-m "not slow"`` run, on a file with listed and unlisted tests: it
    collects exactly the unlisted ones (a mark added after pytest's deselection would leave
    the whole suite in the edit loop's run). One collection: the ones kept are pytest's own
    ``--collect-only`` lines, the ones left out what its ``pytest_deselected`` hook is given
    (a plugin of this test's, printing them)."""
    path = "tests/analysis/test_coupled.py"
    entries = slow_entries(SLOW_LIST.read_text(encoding="utf-8"))
    (tmp_path / "print_deselected.py").write_text(
        "def pytest_deselected(items):\n"
        "    for item in items:\n"
        "        print('deselected', item.nodeid)\n", encoding="utf-8")
    done = subprocess.run([sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-p", "no:xdist",
                           "-p", "print_deselected", "--collect-only", "-q", "-m", "not slow", path],
                          capture_output=True, text=True, cwd=ROOT, timeout=300,
                          env={**os.environ, "PYTHONPATH": os.pathsep.join(
                              filter(None, [str(tmp_path), os.environ.get("PYTHONPATH")]))})
    assert done.returncode == 0, done.stdout + done.stderr
    lines = done.stdout.splitlines()
    kept = [line for line in lines if line.startswith(f"{path}::")]
    left_out = [line.removeprefix("deselected ") for line in lines if line.startswith(f"deselected {path}::")]
    assert left_out and kept, done.stdout
    assert left_out == [nodeid for nodeid in left_out if is_listed(nodeid, entries)]
    assert kept == [nodeid for nodeid in kept if not is_listed(nodeid, entries)]
