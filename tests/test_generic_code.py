"""Generic code names no protocol: the loop, the analysis, the recording, the report, the
emulator's process, pipe, plant and faults, the command line, tune, campaign, identify,
replay and the live view hold a :class:`~dobhil.drives.plugin.DriveProtocol` and call its
hooks, so a protocol from another package takes part in all of them.

Every module of those packages is read as Python reads it (``tokenize``: identifiers,
string literals, comments -- docstrings are string literals) and fails on a protocol's
name, taken from the registry's built-in table plus the names and spellings of the
protocols dobhil knows of, or on an import of a protocol's module, written as an import
statement or as a string (a registry imports by name)."""

from __future__ import annotations

import ast
import io
import re
import tokenize
from collections.abc import Iterator
from pathlib import Path

import pytest

from dobhil.drives.registry import PROTOCOL_CLASSES

PACKAGE = Path(__file__).resolve().parents[1] / "dobhil"

#: the generic packages and modules (relative to ``dobhil/``)
GENERIC = ("runtime", "analysis", "recording", "run_report.py", "emulator", "cli", "tune", "campaign",
           "identify", "replay.py", "live")

#: names and spellings of protocols beyond the registry's keys (``cia402`` is also written
#: "CiA 402"; ``odrive``'s protocol is CANSimple; CiA 402 runs on CANopen; moteus is the
#: mjbots protocol)
SPELLINGS = ("cia 402", "cia-402", "canopen", "cansimple", "can simple", "moteus")


def protocol_words() -> tuple[str, ...]:
    return tuple(sorted({*PROTOCOL_CLASSES, *SPELLINGS}))


#: where a CamelCase identifier's words meet: ``MitModel``, ``EmulatedODrive``
#: (``CiA402`` stays one word); and, tried besides, after an acronym: ``MITMode``
CAMEL = re.compile(r"(?<=[a-z0-9])(?=[A-Z][a-z])|(?<=[a-z])(?=[A-Z]{2})")
ACRONYM = re.compile(r"(?<=[A-Z])(?=[A-Z][a-z])")


def spellings(text: str) -> tuple[str, ...]:
    """``text`` with its CamelCase words apart, with and without acronyms split off
    (``ODriveDrive`` must stay ``ODrive Drive``, ``MITMode`` become ``MIT Mode``)."""
    camel = CAMEL.sub(" ", text)
    return (camel, ACRONYM.sub(" ", camel))


def word_pattern(words: tuple[str, ...]) -> re.Pattern[str]:
    """A protocol's name as a word: not inside a longer word (``submit`` is no ``mit``), but
    an underscore or a dot separates words (``mit_model``, ``drives.odrive``); a space in a
    spelling matches any run of spaces, dashes or underscores."""
    alternatives = "|".join(re.escape(w).replace(r"\ ", r"[\s_-]*").replace(r"\-", r"[\s_-]*") for w in words)
    return re.compile(rf"(?<![a-z0-9])(?:{alternatives})(?![a-z0-9])", re.IGNORECASE)


#: a protocol's module: ``dobhil.drives.<protocol>`` (and below); set from the registry
def module_pattern(names: tuple[str, ...]) -> re.Pattern[str]:
    return re.compile(rf"\bdobhil\.drives\.(?:{'|'.join(map(re.escape, names))})\b")


def generic_modules() -> Iterator[Path]:
    for entry in GENERIC:
        path = PACKAGE / entry
        yield from sorted(path.rglob("*.py")) if path.is_dir() else (path,)


def leaks(source: str, where: str) -> list[str]:
    """``where:line: ...`` for each protocol name among ``source``'s identifiers, string
    literals and comments, and each import of a protocol module (statement or string)."""
    words = word_pattern(protocol_words())
    modules = module_pattern(tuple(PROTOCOL_CLASSES))
    found: list[str] = []
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type in (tokenize.NAME, tokenize.STRING, tokenize.COMMENT) or \
                tok.type == getattr(tokenize, "FSTRING_MIDDLE", -1):
            hit = next((m for text in spellings(tok.string) for m in (words.search(text), modules.search(text))
                        if m), None)
            if hit:
                found.append(f"{where}:{tok.start[0]}: protocol name {hit.group(0)!r} in {tok.string.strip()[:80]!r}")
    for node in ast.walk(ast.parse(source)):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module:
            names = [node.module, *(f"{node.module}.{alias.name}" for alias in node.names)]
        if any(modules.search(name) for name in names):
            found.append(f"{where}:{node.lineno}: imports a protocol module: {', '.join(names)}")
    return found


def test_generic_code_names_no_protocol() -> None:
    problems = [problem for path in generic_modules()
                for problem in leaks(path.read_text(encoding="utf-8"), str(path.relative_to(PACKAGE.parent)))]
    assert problems == [], "protocol names in generic code:\n" + "\n".join(problems)


def test_every_generic_package_is_read() -> None:
    """A package renamed or moved must not leave the test reading nothing."""
    read = {p.relative_to(PACKAGE).parts[0] for p in generic_modules()}
    assert read == set(GENERIC) and len(list(generic_modules())) > 40


@pytest.mark.parametrize(("source", "expected"), [
    # names, in each place Python keeps words
    ('if profile.protocol == "mit":\n    pass\n', ["1: protocol name 'mit'"]),
    ("from dobhil.drives.mit.codec import MitModel\n",
     ["1: protocol name 'mit'", "1: protocol name 'Mit'", "1: imports a protocol module"]),
    ("import dobhil.drives.odrive.codec as c\n", ["1: protocol name 'odrive'", "1: imports a protocol module"]),
    ("x = 1  # an ODrive's encoder rate\n", ["1: protocol name 'ODrive'"]),
    ('"""On a CiA 402 drive."""\n', ["1: protocol name 'CiA 402'"]),
    ('"""On a CANopen node."""\n', ["1: protocol name 'CANopen'"]),
    ("def cia402_frame() -> None: ...\n", ["1: protocol name 'cia402'"]),
    ("CANSIMPLE_ID = 9\n", ["1: protocol name 'CANSIMPLE'"]),
    ("m = moteus_query\n", ["1: protocol name 'moteus'"]),
    ("class EmulatedODrive: ...\n", ["1: protocol name 'ODrive'"]),
    ("model: MitModel\nd = CiA402Drive\nMITMode = 1\n",
     ["1: protocol name 'Mit'", "2: protocol name 'CiA402'", "3: protocol name 'MIT'"]),
    ('MOD = "dobhil.drives.cia402.emulator"\n', ["1: protocol name 'cia402'"]),
    ('x = f"{a} on an MIT motor"\n', ["1: protocol name 'MIT'"]),
    # not a protocol: inside a longer word, or a generic word
    ("def submit(limit: int) -> None:\n    emit = limit  # transmit, commit\n", []),
    ('"""The drive\'s feedback_period; the registry\'s protocol(name)."""\n', []),
])
def test_the_check_finds_what_it_should(source: str, expected: list[str]) -> None:
    assert [_short(problem) for problem in leaks(source, "m.py")] == expected


def _short(problem: str) -> str:
    """``m.py:1: protocol name 'mit' in '...'`` -> ``1: protocol name 'mit'``."""
    line, _, rest = problem.removeprefix("m.py:").partition(": ")
    return f"{line}: {rest.split(' in ')[0].split(': ')[0]}"


#: one protocol's words for the drive's state, which generic code once used for dobhil's own
#: state: allowed only where a log of that time is read (the record names of an old log)
#: and in the deprecated properties that warn and name the new ones
OLD_STATE_WORDS = re.compile(r"\baxis_(?:state|error)\b", re.IGNORECASE)
OLD_LOG_READERS = {("recording/schemas.py", "feedback_state"), ("emulator/process.py", "axis_state"),
                   ("emulator/process.py", "axis_error")}


def old_state_words(source: str, where: str) -> list[str]:
    """``where:line`` of each ``axis_state``/``axis_error`` outside :data:`OLD_LOG_READERS`."""
    tree = ast.parse(source)
    spans = [(node.lineno, node.end_lineno or node.lineno, node.name) for node in ast.walk(tree)
             if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))]
    found = []
    for number, line in enumerate(source.splitlines(), 1):
        if not OLD_STATE_WORDS.search(line):
            continue
        inside = {name for start, end, name in spans if start <= number <= end}
        if not any((where, name) in OLD_LOG_READERS for name in inside):
            found.append(f"{where}:{number}: {line.strip()}")
    return found


def test_generic_code_says_drive_state_and_protocol_state_not_axis_state() -> None:
    found = [hit for path in generic_modules()
             for hit in old_state_words(path.read_text(encoding="utf-8"), str(path.relative_to(PACKAGE)))]
    assert not found, "\n".join(found)


def test_the_old_state_words_check_finds_a_planted_one() -> None:
    planted = "def write(record):\n    return record.axis_state\n"
    assert old_state_words(planted, "recording/schemas.py") == ["recording/schemas.py:2: return record.axis_state"]
    reader = "def feedback_state(payload):\n    return payload.get('axis_error', 0)\n"
    assert old_state_words(reader, "recording/schemas.py") == []
