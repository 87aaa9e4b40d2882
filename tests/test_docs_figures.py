r"""The figures the README, drivers/README.md and docs/*.md quote are what their commands give today.

A figure that a deterministic command reproduces (an analysis, a lockstep emulated run, an
identification of such runs, a seeded search or campaign, the paper's claims) carries a check
beside it in the markdown, an HTML comment (invisible on the rendered page)::

    <!-- check: dobhil identify free.mcap contact.mcap --json
      estimates.inertia.value = 0.249955 ± 0.01 %
      residual.whiteness_p = 0.78 ± 0.01
    -->

The first line is the command; each further line a key of the JSON it prints (dots between
names, ``\.`` a dot inside a name, integers index lists) with the value and its tolerance: ``± X %`` relative, ``± X``
absolute, none: exact (a number, ``true``/``false``/``null`` or a JSON string). ``stdout ~ "RE"``
/ ``stderr ~ "RE"`` search the command's text instead, ``exit = N`` its exit code (0 when not
said; ``exit ~ "RE"``: the code's digits match RE, for a command whose deterministic figure
comes with an exit a machine's timing decides, such as ``dobhil check`` of emulated drives).
``<!-- run: COMMAND -->`` runs a command whose files later checks read (a log, an overlay).
``check slow:`` / ``run slow:`` mark a command of minutes: run with DOBHIL_SLOW=1, parsed always.

Every command must also be shown on the page (in a code block or in backticks), with the same
words but for ``--json`` / ``--summary-json``: the figure is reproducible by a reader, not only
by this test. The commands of one page run in order in one temporary directory, from the
package's shipped files (``dobhil`` is ``python -m dobhil`` of the installed package), each
command once, each in a process forked from one that imported dobhil once per test process
(tests/dobhil_forks.py, the ``dobhil_forks`` fixture; a test below checks a forked command
answers as a new process does). A key the JSON does not have fails the check, as does a
figure outside its tolerance.

Figures of timing and of this machine (bench keys, CI and wall times) cannot be asserted: the
pages give each with the command that measures it, and carry no check.

Cost, measured (``pytest -n 0 --durations=5 tests/test_docs_figures.py`` on the 2-core VM
while other test runs shared it): docs/identify.md 176 s (eight lockstep runs of 1.2 to 10 s,
four fits of 5 to 15 s of log), docs/quantisation.md 22 s and README.md 19 s (analyses),
drivers/README.md 1-5 s (a 1.2 s lockstep MIT run), the parser and its own tests 0.3 s. The
slow check (``dobhil tune`` of Fig. 3: 160 s there) runs only with DOBHIL_SLOW=1. The
closed-loop walk-through of docs/identify.md (section 5) adds three lockstep runs of 3 s and
three fits of them: 23 s of wall time, 15 s of CPU, measured under load (load avg 1-2; the
commands timed one by one). The page took 110 s (``pytest -n 0 --durations=5
tests/test_docs_figures.py -k identify``, load avg falling from 5 to 1) and 292 s at load 6.5.
The walk-through's slow part runs only with DOBHIL_SLOW=1: a ``dobhil tune`` on the identified
box (61 s of wall time, 47 s of CPU), a ``dobhil certify`` of up to 200000 refinements (13 s),
five 1.2 s runs, two reports and three compares (13 s), 88 s together at load avg 2-3. With
DOBHIL_SLOW=1 the page took 315 s at load 6.5.

Each command was a new ``python -m dobhil`` process, and importing dobhil, scipy,
python-control and matplotlib was most of a command's CPU: forked from one process that has
imported them (tests/dobhil_forks.py), the file took 42.9 s of CPU instead of 73.9 s (user +
system, ``/usr/bin/time pytest -n 0 -p no:cacheprovider tests/test_docs_figures.py``, the
two versions one after the other, measured under load, load avg 1.4-2.2; the 42.9 s include
the tests of the forking), docs/identify.md 35 s of wall time instead of 53 s, README.md's
eight analyses 3.9 s instead of 12.4 s.
"""

from __future__ import annotations

import json
import math
import os
import re
import shlex
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from dobhil_forks import DobhilForks

REPO = Path(__file__).resolve().parents[1]
PAGES = sorted([REPO / "README.md", REPO / "drivers" / "README.md", *(REPO / "docs").glob("*.md")])
SLOW = bool(os.environ.get("DOBHIL_SLOW"))
#: seconds one command of a page may take (the slowest, a lockstep 10 s identify run or a fit,
#: takes a few seconds idle)
COMMAND_TIMEOUT = 900

_BLOCK = re.compile(r"<!--\s*(check|run)(\s+slow)?:(.*?)-->", re.S)
_EXPECT = re.compile(r"^(?P<key>[\w.\-\\]+)\s*(?P<op>=|~)\s*(?P<value>.+?)"
                     r"(?:\s*±\s*(?P<tol>[0-9.eE+\-]+)\s*(?P<pct>%)?)?$")
_QUIET = {"--json", "--summary-json"}


class CheckError(AssertionError):
    """A check that does not hold, or cannot be read; its message says which and why."""


@dataclass(frozen=True)
class Expect:
    """One line of a check: a key, how it is compared, and within what."""

    key: str
    op: str            # "=" (value) or "~" (regex on stdout/stderr)
    value: Any
    tol: float = 0.0
    relative: bool = False

    def holds(self, found: Any) -> bool:
        if isinstance(self.value, bool) or self.value is None or isinstance(self.value, str):
            return bool(found == self.value and type(found) is type(self.value))
        if isinstance(found, bool) or not isinstance(found, (int, float)):
            return False
        bound = self.tol * abs(self.value) if self.relative else self.tol
        return math.isfinite(found) and abs(found - self.value) <= bound

    def said(self) -> str:
        tol = (f" ± {self.tol * 100:g} %" if self.relative else f" ± {self.tol:g}") if self.tol else ""
        return f"{self.key} {self.op} {json.dumps(self.value)}{tol}"


@dataclass(frozen=True)
class Check:
    """A command of a page and what its output must say (nothing: a ``run``)."""

    page: str
    line: int
    command: str
    expects: tuple[Expect, ...]
    slow: bool

    def args(self) -> list[str]:
        """The command's arguments after ``dobhil``."""
        words = shlex.split(self.command)
        if words[:1] != ["dobhil"]:
            raise CheckError(f"{self.where}: a check runs dobhil only, got {self.command!r}")
        return words[1:]

    def argv(self) -> list[str]:
        return [sys.executable, "-m", "dobhil", *self.args()]

    @property
    def where(self) -> str:
        return f"{self.page}:{self.line}"


def parse_expect(text: str, where: str) -> Expect:
    m = _EXPECT.match(text.strip())
    if m is None:
        raise CheckError(f"{where}: {text.strip()!r}: expected KEY = VALUE [± TOL [%]] or stdout|stderr ~ \"RE\"")
    key, op, raw, tol = m["key"], m["op"], m["value"].strip(), m["tol"]
    try:
        value = json.loads(raw)
    except json.JSONDecodeError:
        raise CheckError(f"{where}: {raw!r} is not a number, true, false, null or a \"string\"") from None
    if op == "~" and (key not in ("stdout", "stderr", "exit") or not isinstance(value, str) or tol):
        raise CheckError(f"{where}: ~ takes stdout, stderr or exit and a \"regex\", got {text.strip()!r}")
    if tol is not None and not isinstance(value, (int, float)):
        raise CheckError(f"{where}: a tolerance needs a number, got {raw!r}")
    return Expect(key, op, value, float(tol or 0.0) / (100.0 if m["pct"] else 1.0), bool(m["pct"]))


def parse_page(path: Path) -> list[Check]:
    """Every check and run of one page, in order."""
    return parse_text(path.read_text(encoding="utf-8"), path.relative_to(REPO).as_posix())


def parse_text(text: str, name: str) -> list[Check]:
    """Every check and run of the page ``name`` whose markdown is ``text``."""
    checks = []
    for m in _BLOCK.finditer(text):
        line = text.count("\n", 0, m.start()) + 1
        lines = [ln for ln in m[3].strip().splitlines() if ln.strip()]
        if not lines:
            raise CheckError(f"{name}:{line}: an empty {m[1]}")
        expects = tuple(parse_expect(ln, f"{name}:{line}") for ln in lines[1:])
        if m[1] == "run" and expects:
            raise CheckError(f"{name}:{line}: a run has no expectations; use check")
        if m[1] == "check" and not expects:
            raise CheckError(f"{name}:{line}: a check without a figure; use run")
        checks.append(Check(name, line, " ".join(lines[0].split()), expects, bool(m[2])))
    return checks


def _words(command: str) -> str:
    return " ".join(w for w in command.split() if w not in _QUIET)


def shown(page_text: str, command: str) -> bool:
    """``command`` (but for --json / --summary-json) is on the page outside the checks: in a
    code block (continuation lines joined) or in backticks."""
    visible = _BLOCK.sub(" ", page_text).replace("\\\n", " ")
    visible = re.sub(r"\s+", " ", visible.replace("`", " ` "))
    return f" {_words(command)} " in f" {_words(visible)} "


def lookup(data: Any, key: str) -> Any:
    """``data`` at the dotted ``key``; CheckError naming the first part that is missing."""
    node = data
    parts = [part.replace("\\.", ".") for part in re.split(r"(?<!\\)\.", key)]
    for i, part in enumerate(parts):
        if isinstance(node, list) and re.fullmatch(r"-?\d+", part) and -len(node) <= int(part) < len(node):
            node = node[int(part)]
        elif isinstance(node, dict) and part in node:
            node = node[part]
        else:
            there = ".".join(parts[:i]) or "the output"
            have = sorted(node)[:20] if isinstance(node, dict) else type(node).__name__
            raise CheckError(f"key {key!r}: no {part!r} in {there} (it has {have})")
    return node


@dataclass(frozen=True)
class Ran:
    code: int
    stdout: str
    stderr: str
    seconds: float


def verify(check: Check, ran: Ran) -> None:
    """Every expectation of ``check`` against what its command gave; one CheckError listing
    all that failed."""
    failed = []
    exit_code = next((e for e in check.expects if e.key == "exit"), Expect("exit", "=", 0))
    if not (re.fullmatch(exit_code.value, str(ran.code)) if exit_code.op == "~" else ran.code == exit_code.value):
        failed.append(f"exit {ran.code}, expected {exit_code.value}: {ran.stderr.strip()[-500:]}")
    data: Any = None
    for e in check.expects:
        if e.key == "exit":
            continue
        if e.op == "~":
            text = ran.stdout if e.key == "stdout" else ran.stderr
            if not re.search(e.value, text, re.M):
                failed.append(f"{e.said()}: not in {text.strip()[-400:]!r}")
            continue
        if data is None:
            try:
                data = json.loads(ran.stdout)
            except json.JSONDecodeError:
                raise CheckError(f"{check.where}: {check.command}: stdout is not JSON: {ran.stdout[:200]!r}") from None
        try:
            found = lookup(data, e.key)
        except CheckError as exc:
            failed.append(str(exc))
            continue
        if not e.holds(found):
            failed.append(f"{e.said()}: found {json.dumps(found)}")
    if failed:
        raise CheckError(f"{check.where}: {check.command}:\n  " + "\n  ".join(failed))


#: the environment of every command: a wide terminal, so that no text is wrapped
ENV = {**os.environ, "COLUMNS": "200"}


def run(check: Check, cwd: Path, forks: DobhilForks) -> Ran:
    """``check``'s command as ``python -m dobhil`` in ``cwd``, forked from ``forks``' server."""
    start = time.perf_counter()
    done = forks.run(check.args(), cwd, timeout=COMMAND_TIMEOUT, env=ENV)
    return Ran(done.returncode, done.stdout, done.stderr, time.perf_counter() - start)


def run_process(check: Check, cwd: Path) -> Ran:
    """``check``'s command in a new ``python -m dobhil`` process."""
    start = time.perf_counter()
    proc = subprocess.run(check.argv(), cwd=cwd, capture_output=True, text=True, env=ENV,
                          timeout=COMMAND_TIMEOUT, check=False)
    return Ran(proc.returncode, proc.stdout, proc.stderr, time.perf_counter() - start)


CHECKED = [p for p in PAGES if _BLOCK.search(p.read_text(encoding="utf-8"))]


def test_every_check_parses_and_its_command_is_on_the_page() -> None:
    """Cheap, always: the syntax of every check, and the reader can see each command."""
    assert CHECKED, "no page carries a check"
    for page in PAGES:
        text = page.read_text(encoding="utf-8")
        for check in parse_page(page):
            check.argv()
            assert shown(text, check.command), f"{check.where}: {check.command!r} is not shown on the page"


@pytest.mark.timeout(3 * COMMAND_TIMEOUT)
@pytest.mark.parametrize("page", CHECKED, ids=lambda p: p.relative_to(REPO).as_posix())
def test_the_figures_of_a_page_are_what_its_commands_give(page: Path, tmp_path: Path,
                                                          dobhil_forks: DobhilForks) -> None:
    checks = [c for c in parse_page(page) if SLOW or not c.slow]
    if not checks:
        pytest.skip("only slow checks on this page: set DOBHIL_SLOW=1")
    done: dict[str, Ran] = {}
    failures = []
    for check in checks:
        if check.command not in done:
            done[check.command] = run(check, tmp_path, dobhil_forks)
        try:
            verify(check, done[check.command])
        except CheckError as exc:
            failures.append(str(exc))
    times = ", ".join(f"{c.split()[1]} {r.seconds:.1f} s" for c, r in done.items())
    assert not failures, "\n".join(failures) + f"\n(commands: {times})"


# -- the mechanism itself ---------------------------------------------------------


@pytest.mark.parametrize("command", ["dobhil analyze demo --json", "dobhil analyze no-such-config --json"])
def test_a_forked_command_answers_as_a_new_process(command: str, tmp_path: Path,
                                                   dobhil_forks: DobhilForks) -> None:
    """The pages' commands run forked from one server (tests/dobhil_forks.py): the same exit
    code, output and error text as a new ``python -m dobhil`` process gives."""
    check = Check("x.md", 1, command, (), False)
    forked = run(check, tmp_path, dobhil_forks)
    alone = run_process(check, tmp_path)
    assert (forked.code, forked.stdout, forked.stderr) == (alone.code, alone.stdout, alone.stderr)
    assert forked.stdout or forked.stderr


def test_a_command_past_its_time_out_is_killed_and_the_next_one_runs(tmp_path: Path) -> None:
    """A time-out kills the server and the command it forked; the next command starts a new
    server (the session's fixture outlives a page that hung). A time-out of 0 s: no command
    answers before the reply is first looked for."""
    with DobhilForks() as forks:
        with pytest.raises(TimeoutError, match="no exit in 0 s"):
            forks.run(["run", "demo", "--emulate", "--lockstep", "--duration", "600"], tmp_path, timeout=0)
        done = forks.run(["--version"], tmp_path, timeout=COMMAND_TIMEOUT)
    assert done.returncode == 0 and done.stdout.startswith("dobhil "), done


def _check(body: str) -> Check:
    found = parse_text(f"<!-- check: {body} -->", "x.md")
    assert len(found) == 1
    return found[0]


def test_a_check_naming_a_key_the_output_lacks_fails_naming_it() -> None:
    check = _check("dobhil analyze demo --json\n sampled.max_stable_force_gain = 8.72 ± 1 %")
    out = json.dumps({"sampled": {"stable": True}, "continuous": {}})
    with pytest.raises(CheckError, match=r"key 'sampled.max_stable_force_gain': no 'max_stable_force_gain' in "
                                         r"sampled \(it has \['stable'\]\)"):
        verify(check, Ran(0, out, "", 0.0))


@pytest.mark.parametrize(("found", "holds"), [(8.72, True), (8.8, True), (8.81, False), (8.64, True), (8.63, False),
                                              ("8.72", False), (True, False), (float("nan"), False)])
def test_a_figure_holds_within_its_relative_tolerance_only(found: Any, holds: bool) -> None:
    check = _check("dobhil analyze demo --json\n a.b = 8.72 ± 1 %")
    ran = Ran(0, json.dumps({"a": {"b": found}}), "", 0.0)
    if holds:
        verify(check, ran)
    else:
        with pytest.raises(CheckError, match=r"a.b = 8.72 ± 1 %: found"):
            verify(check, ran)


def test_a_dot_inside_a_name_is_escaped() -> None:
    check = _check("dobhil tune x --json\n design.design\\.force_gain = 0.623 ± 0.0005")
    verify(check, Ran(0, json.dumps({"design": {"design.force_gain": 0.6231}}), "", 0.0))
    with pytest.raises(CheckError, match="no 'design' in the output"):
        verify(check, Ran(0, json.dumps({"design.design.force_gain": 0.6231}), "", 0.0))


def test_exact_values_exit_codes_and_text() -> None:
    check = _check('dobhil run x --json\n exit = 1\n a.0 = "done"\n a.1 = null\n stderr ~ "^NOTE: node \\\\d"\n b = 3')
    verify(check, Ran(1, json.dumps({"a": ["done", None], "b": 3}), "x\nNOTE: node 1 ...", 0.0))
    with pytest.raises(CheckError, match="exit 0, expected 1"):
        verify(check, Ran(0, json.dumps({"a": ["done", None], "b": 3}), "NOTE: node 1", 0.0))
    with pytest.raises(CheckError, match=r"b = 3: found 3.5"):
        verify(check, Ran(1, json.dumps({"a": ["done", None], "b": 3.5}), "NOTE: node 1", 0.0))
    with pytest.raises(CheckError, match=r"stderr ~"):
        verify(check, Ran(1, json.dumps({"a": ["done", None], "b": 3}), "WARNING: x", 0.0))


def test_an_exit_code_by_pattern() -> None:
    check = _check('dobhil check x\n exit ~ "[01]"\n stdout ~ "gate"')
    for code in (0, 1):
        verify(check, Ran(code, "a gate line", "", 0.0))
    for code in (2, 10):
        with pytest.raises(CheckError, match=f"exit {code}, expected"):
            verify(check, Ran(code, "a gate line", "", 0.0))


@pytest.mark.parametrize("body", ["dobhil analyze demo --json\n a.b 8.72", "dobhil analyze demo\n a = x",
                                  "dobhil x\n stdout = \"a\" ± 2", "dobhil x\n a ~ \"b\"", "dobhil x"])
def test_a_malformed_check_is_refused(body: str) -> None:
    with pytest.raises(CheckError):
        _check(body)


def test_a_command_must_be_shown_without_its_json_flag() -> None:
    page = ("Run\n\n```\ndobhil analyze demo \\\n  --set a=1\n```\n"
            "<!-- check: dobhil analyze demo --set a=1 --json\n x = 1 -->")
    assert shown(page, "dobhil analyze demo --set a=1 --json")
    assert not shown(page, "dobhil analyze demo --set a=2 --json")
    assert not shown("<!-- run: dobhil run demo -->", "dobhil run demo")   # the check itself does not count
