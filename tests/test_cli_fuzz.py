"""The ``dobhil`` command never answers bad input with a traceback (hypothesis, fixed seed).

Random command lines are built from the real parser: real command and action names, the
real option strings of each (read from ``build_parser()``, so a new option is fuzzed as
soon as it exists), real config keys for ``--set``, and hostile values (NaN, 400-digit
numbers, empty and very long strings, control characters, non-UTF-8 bytes as surrogates,
paths to a directory, a FIFO, an empty file, garbage bytes, a truncated MCAP ...). Each
runs in-process through :func:`dobhil.cli.main.main` and must end with exit code 0, 1
or 2, print no traceback, and, for exit 2, exactly one line on stderr.

``run``, ``emulate``, ``demo``, ``log serve`` and ``paper`` are left out of the random command
lines: a valid one runs a control loop, waits for a Foxglove client or reproduces every figure
of the paper. They get hand-picked bad command lines here, each bounded (``--emulate
--lockstep --duration 0.05``); ``paper``'s valid run is tests/test_analysis.py's.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, seed, settings
from hypothesis import strategies as st

from dobhil.cli.main import EXIT_INTERNAL, build_parser, main
from dobhil.config import key_fields

ROOT = Path(__file__).resolve().parents[1]
#: commands whose valid command lines run a loop, serve until a client comes or (``paper``)
#: render every figure of the paper: 2 s of CPU a line, where the other commands take 0.01-0.5 s
#: (a random ``paper`` line is valid but for its one option, ``--out``: its bad values are
#: hand-picked below)
LONG_RUNNING = {"run", "emulate", "demo", "serve", "paper"}
KEYS = sorted(key_fields())
#: random command lines per fuzzed command. One draw of 150 over all commands left whole
#: commands out (log export, or certify, drew none); 20 a command run 10,824 lines of dobhil
#: against that draw's 9,982 (coverage.py; the 235 only it ran are paper's, valid plots and
#: log info's text, which tests/test_analysis.py and tests/recording/ run). A line takes
#: 0.01 s (refused) to 2 s (a valid analyze --plot or report)
FUZZ = settings(max_examples=20, derandomize=True, deadline=None, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:  # argparse has no public accessor for its subparsers
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def _commands() -> dict[tuple[str, ...], argparse.ArgumentParser]:
    """Every leaf command (``("analyze",)``, ``("log", "info")`` ...) and its parser."""
    out: dict[tuple[str, ...], argparse.ArgumentParser] = {}
    for name, sub in _subparsers(build_parser()).items():
        nested = _subparsers(sub)
        if nested:
            out.update({(name, action): p for action, p in nested.items()})
        else:
            out[(name,)] = sub
    return out


COMMANDS = _commands()
FUZZED = sorted(c for c in COMMANDS if not LONG_RUNNING & set(c))


def _options(parser: argparse.ArgumentParser) -> list[tuple[str, bool, tuple[str, ...]]]:
    """(option string, takes a value, its choices) of a parser, without -h/--help."""
    return [(action.option_strings[-1], action.nargs != 0, tuple(map(str, action.choices or ())))
            for action in parser._actions
            if action.option_strings and not isinstance(action, argparse._HelpAction)]


# -- the scratch directory every command line runs in -----------------------------------------

#: "billion laughs": nine levels of nine aliases, 9**9 references in 300 bytes of YAML
BOMB = "[&a [1,1,1,1,1,1,1,1,1], " + ", ".join(
    f"&{b} [{', '.join([f'*{a}'] * 9)}]" for a, b in zip("abcdefgh", "bcdefghi")) + "]"


def _scratch(root: Path) -> None:
    """Hostile input files, and one good recording, in ``root``."""
    (root / "empty.yaml").write_text("")
    (root / "list.yaml").write_text("- a\n- b\n")
    (root / "scalar.yaml").write_text("plant: 3\n")
    (root / "dup.yaml").write_text("design:\n  force_gain: 1\n  force_gain: 2\n")
    (root / "deep.yaml").write_text("a: " + "[" * 3000 + "]" * 3000 + "\n")
    (root / "tag.yaml").write_text("design: !!python/object:os.system ls\n")
    (root / "garbage.yaml").write_bytes(bytes(range(256)) * 4)
    (root / "huge.yaml").write_text("# pad\n" * 200_000)
    (root / "dir.yaml").mkdir()
    (root / "dir.mcap").mkdir()
    os.mkfifo(root / "fifo.yaml")
    os.mkfifo(root / "fifo.mcap")
    (root / "empty.mcap").write_bytes(b"")
    (root / "garbage.mcap").write_bytes(b"\x89MCAP0\r\n" + bytes(range(256)) * 8)
    (root / "text.mcap").write_text("not an mcap\n")
    (root / "garbage.blf").write_bytes(b"LOGG" + bytes(100))
    (root / "bomb.yaml").write_text(f"design:\n  force_gain: {BOMB}\n")
    profile = (ROOT / "drivers" / "odrive-0.6.yaml").read_text()
    (root / "bomb-profile.yaml").write_text(profile.replace("\ntorque_limit:", f"\ntorque_limit: {BOMB}\n#", 1))
    (root / "loop").symlink_to(root / "loop2")
    (root / "loop2").symlink_to(root / "loop")
    (root / "bad.asc").write_text("date Mon Jan 1 00:00:00 2024\nbase hex timestamps absolute\n0.1 1 zz Rx d 8\n")
    good = root / "good.mcap"
    code, _, err = run_cli(["run", "demo", "--emulate", "--lockstep", "--duration", "0.05", "--log", str(good)])
    assert code == 0, err
    data = good.read_bytes()
    (root / "cut.mcap").write_bytes(data[: len(data) // 2])
    flipped = bytearray(data)
    for i in range(200, len(flipped), 97):
        flipped[i] ^= 0x5A
    (root / "flipped.mcap").write_bytes(bytes(flipped))


@pytest.fixture(scope="module")
def scratch() -> Iterator[Path]:
    with tempfile.TemporaryDirectory(prefix="dobhil-fuzz-") as tmp:
        root = Path(tmp)
        with _chdir(root):
            _scratch(root)
        yield root


@contextlib.contextmanager
def _chdir(path: Path) -> Iterator[None]:
    before = Path.cwd()
    os.chdir(path)
    try:
        yield
    finally:
        os.chdir(before)


def run_cli(argv: list[str]) -> tuple[int, str, str]:
    """``dobhil ARGV`` in this process: (exit code, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main(argv)
        except SystemExit as exc:  # --help, --version and argparse usage errors
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    return code, out.getvalue(), err.getvalue()


def assert_clean(argv: list[str], code: int, err: str) -> None:
    shown = " ".join(repr(a) if not a or " " in a else a for a in argv)
    assert "Traceback" not in err, f"dobhil {shown}\n{err}"
    assert code in (0, 1, 2), f"dobhil {shown}: exit {code}\n{err}"
    if code == 2:
        lines = err.strip().splitlines()
        assert len(lines) == 1, f"dobhil {shown}: exit 2 with {len(lines)} lines on stderr\n{err}"
        assert lines[0].startswith("dobhil"), f"dobhil {shown}: {lines[0]}"


# -- strategies ---------------------------------------------------------------------------------

INPUT_FILES = ["empty.yaml", "list.yaml", "scalar.yaml", "dup.yaml", "deep.yaml", "tag.yaml",
               "garbage.yaml", "huge.yaml", "dir.yaml", "fifo.yaml", "nonexistent.yaml",
               "good.mcap", "cut.mcap", "flipped.mcap", "empty.mcap", "garbage.mcap", "text.mcap",
               "dir.mcap", "fifo.mcap", "garbage.blf", "bad.asc", "nonexistent.mcap", "/dev/null",
               "/dev/zero", "/", ".", "..", "demo", "paper/fig2c", "paper/../demo", "../configs/demo",
               "odrive-0.6", "x" * 300, "x/" * 2100]
NUMBERS = ["0", "-0", "-1", "1e-320", "5e-324", "1e308", "1e400", "-1e400", "nan", "-nan", "inf",
           "-inf", ".nan", ".inf", "9" * 400, "0x10", "1_000", "1e15", "2**63", str(2**63), "1847",
           "200", "0.0001", "1/3", "1,5"]
ODD = ["", " ", "-", "--", "=", "==", ":", "::", "a:b:c", "[", "{", "&a", "*a", "!!binary", "%TAG",
       "~", "null", "true", "yes", "'", '"', "\\", "\t", "a\x0bb", "x\x85y", "\u2028", "\x1c", "\n",
       "é", "\udcff", "💥",
       "a" * 5000, "virtual:", "virtual:x", "dobhil:demo", "dobhil:fifo.yaml", "nonexistent:x",
       "socketcan:can0", "127.0.0.1:0", "[::1]:1", "0.0.0.0:99999", "log:0:1:3",
       "design.force_gain=1:2:3", "design.force_gain=log:1:2:3", "design.force_gain=nan:1:2",
       "plant.inertia=1:2:100001"]
#: what a shell can pass: any text but NUL (a non-UTF-8 byte arrives as a lone surrogate)
shell_text = st.text(st.characters(blacklist_characters="\x00"), max_size=12)
hostile = st.one_of(st.sampled_from(INPUT_FILES + NUMBERS + ODD),
                    shell_text,
                    st.from_regex(r"-?[0-9]{1,3}(\.[0-9]{0,3})?(e-?[0-9]{1,3})?", fullmatch=True))
sets = st.builds(lambda key, value: f"{key}={value}",
                 st.sampled_from(KEYS + ["design", "design.", "nokey", "design.force_gain.x", ""]),
                 st.one_of(st.sampled_from(NUMBERS + ODD[:30] + INPUT_FILES), shell_text))
#: a valid first positional half of the time, so options are fuzzed past the config check
VALID_POSITIONAL = {"analyze": "demo", "sweep": "demo", "check": "demo", "replay": "good.mcap",
                    "report": "good.mcap", "info": "good.mcap", "recover": "good.mcap",
                    "export": "good.mcap", "import": "good.mcap", "init": "fresh", "identify": "good.mcap",
                    "compare": "good.mcap"}
#: values of options naming a file the command writes: fresh names inside the scratch
#: directory (hostile output names are tested by hand below)
outputs = st.sampled_from(["o1.png", "o2.csv", "o3.mcap", "o4.blf", "o5", "out/o6.png", "o7.txt", "o8.svg",
                          "good.mcap/o9.png", "x" * 300 + ".png"])
OUTPUT_OPTIONS = {"--plot", "--out", "--output", "--log"}


@st.composite
def command_lines(draw: st.DrawFn, command: tuple[str, ...]) -> list[str]:
    parser = COMMANDS[command]
    argv = list(command)
    positionals = [a for a in parser._actions if not a.option_strings]
    for _ in positionals:
        if draw(st.integers(0, 9)):  # now and then one missing
            valid = VALID_POSITIONAL.get(command[-1])
            argv.append(valid if valid and draw(st.booleans()) else draw(hostile))
    options = _options(parser)
    for _ in range(draw(st.integers(0, 3))):
        name, takes_value, choices = draw(st.sampled_from(options)) if options else ("--bogus", False, ())
        argv.append(name)
        if name == "--set":
            argv.append(draw(sets))
        elif name == "--window":
            argv.append(draw(st.sampled_from(["0.05", "nan", "-1", "0", "61", "1e-300", "abc"])))
        elif name in OUTPUT_OPTIONS:
            argv.append(draw(outputs))
        elif choices:   # one of them half the time: a hostile one stops at argparse
            argv.append(draw(st.one_of(st.sampled_from(choices), hostile)))
        elif takes_value:
            argv.append(draw(hostile))
    if draw(st.integers(0, 7)) == 0:
        argv.append(draw(st.sampled_from(["--bogus", "extra", "--set", "-x", "--help"])))
    return argv


@seed(20261122)
@pytest.mark.parametrize("command", FUZZED, ids=" ".join)
@FUZZ
@given(data=st.data())
def test_no_command_line_ends_in_a_traceback(scratch: Path, command: tuple[str, ...], data: st.DataObject) -> None:
    argv = data.draw(command_lines(command), label="argv")
    with _chdir(scratch):
        code, _, err = run_cli(argv)
    assert_clean(argv, code, err)


# -- hand-picked: the long-running commands and hostile output paths -----------------------------

RUN = ["run", "demo", "--emulate", "--lockstep", "--duration", "0.05"]
HAND_PICKED = [
    [*RUN[:4], "--duration", "nan"], [*RUN[:4], "--duration", "-1"], [*RUN[:4], "--duration", "1e308"],
    [*RUN, "--set", "plant.initial_position=1e308"], [*RUN, "--set", "design.force_gain=1e400"],
    [*RUN, "--set", "drive.profile=fifo.yaml"], [*RUN, "--set", "drive.profile=garbage.yaml"],
    [*RUN, "--set", "drive.profile=dir.yaml"], [*RUN, "--set", "drive.profile=" + "x" * 300],
    [*RUN, "--log", "dir.mcap"], [*RUN, "--log", "good.mcap"], [*RUN, "--log", "x.txt"],
    [*RUN, "--plot", "good.mcap"], [*RUN, "--live", "abc", "--log", "l.mcap"], [*RUN, "--live", "1"],
    [*RUN, "--preflight-window", "nan"], [*RUN, "--log", "\udcfd.mcap"],
    [*RUN, "--set", "drive.profile=bomb-profile.yaml"], ["analyze", "bomb.yaml"],
    ["analyze", "demo", "--set", f"design.force_gain={BOMB}"],
    ["run", "fifo.yaml", "--emulate"], ["run", "demo", "--lockstep"],
    ["emulate", "demo", "--bus", "virtual:fuzz", "--duration", "-1"],
    ["emulate", "demo", "--bus", "x", "--duration", "0.05"],
    ["emulate", "fifo.yaml", "--bus", "virtual:fuzz", "--duration", "0.05"],
    ["demo", "fifo.yaml"], ["demo", "--out", "good.mcap"], ["demo", "--log", "good.mcap"],
    ["demo", "--live", "abc"], ["demo", "--set", "loop.duration=-1"],
    ["log", "serve", "fifo.mcap"], ["log", "serve", "cut.mcap"], ["log", "serve", "good.mcap", "--speed", "0"],
    ["log", "serve", "good.mcap", "--speed", "1e-300"], ["log", "serve", "good.mcap", "--live", "x:y:z"],
    ["log", "export", "good.mcap", "--topic", "/controller", "--format", "csv", "-o", "/dev/null"],
    ["log", "export", "good.mcap", "--topic", "/controller", "--format", "csv", "-o", "/dev/stdout"],
    ["log", "recover", "good.mcap", "-o", "fifo.mcap"], ["paper", "--out", "/proc"],
    ["paper", "--out", "good.mcap"], ["paper", "--out", "good.mcap/o9.png"], ["paper", "--out", "x" * 300 + ".png"],
    ["paper", "--out", "fifo.mcap"], ["paper", "--out"], ["paper", "--bogus"], ["paper", "extra"],
    ["analyze", "line\nbreak\x0bvt\x85nel\u2028ls"],
    ["analyze", "demo", "--bogus\x0c"], ["log", "info", "a\rb.mcap"], ["analyze", "demo", "--plot", "good.mcap"],
    ["init", ""], ["init", "good.mcap"], ["init", "x" * 300], ["init", "fifo.yaml"],
    ["check", "demo", "--bus", "dobhil:fifo.yaml", "--window", "0.05"],
    ["check", "demo", "--bus", "dobhil:" + "x" * 300, "--window", "0.05"],
    [*RUN, "--set", "reference.kind=csv", "--set", "reference.file=/dev/zero"],
    [*RUN, "--set", "reference.kind=csv", "--set", "reference.file=fifo.yaml"],
    [*RUN, "--bus", "nonexistent:x"], [*RUN, "--plot", "x" * 300 + ".png"],
    ["log", "recover", "good.mcap", "-o", "recovered.txt"],
]

#: bad input found only after the work, once: (command line, words the one line must hold);
#: each must be refused before the work starts (nothing on stdout, nothing written)
EARLY = [
    (["sweep", "demo", "--vary", "design.force_gain=1:2:3", "--plot", "sweep.txt"], ".png or .svg or .pdf"),
    (["sweep", "demo", "--vary", "design.force_gain=1:2:3", "--out", "good.mcap/x.csv"], "not a directory"),
    (["sweep", "demo", "--vary", "design.force_gain=1:2:3", "--plot", "x" * 300 + ".png"], "too long"),
    (["analyze", "demo", "--plot", "good.mcap"], "not a directory"),
    (["paper", "--out", "good.mcap/o9.png"], "not a directory"),
    (["paper", "--out", "x" * 300 + ".png"], "too long"),
    (["analyze", "demo", "--plot", "good.mcap/sub"], "not a directory"),
    (["analyze", "demo", "--plot", "x" * 300], "too long"),
    (["log", "import", "dir.mcap", "-o", "imported.mcap"], "is a directory"),
    (["log", "import", "fifo.mcap", "-o", "imported.mcap"], "FIFO"),
    (["log", "recover", "good.mcap", "-o", "recovered.txt"], ".mcap"),
    (["log", "info", "dir.mcap"], "is a directory"),
    (["analyze", "demo", "--plot", "loop"], "loop of symbolic links"),
    (["report", "loop", "--out", "report-out"], "symbolic links"),
    ([*RUN, "--bus", "nonexistent:x"], "--emulate"),
    ([*RUN, "--set", "reference.kind=csv", "--set", "reference.file=/dev/zero"], "not a regular file"),
]


@pytest.mark.parametrize(("argv", "words"), EARLY, ids=lambda a: " ".join(a)[:60] if isinstance(a, list) else "")
def test_bad_input_is_refused_before_the_work(scratch: Path, argv: list[str], words: str) -> None:
    with _chdir(scratch):
        before = set(os.listdir("."))
        code, out, err = run_cli(argv)
        after = set(os.listdir("."))
    assert_clean(argv, code, err)
    assert code == 2 and words in err, err
    assert out == "", out  # no analysis, sweep summary or run printed: refused first
    assert after == before, after ^ before


def test_report_of_a_file_named_in_no_encoding(scratch: Path, tmp_path: Path) -> None:
    """A recording whose name is not UTF-8 (0xff from the shell) is reported, its name escaped."""
    source = tmp_path / "run\udcff.mcap"
    source.write_bytes((scratch / "good.mcap").read_bytes())
    code, out, err = run_cli(["report", str(source), "--out", str(tmp_path / "rep")])
    assert code == 0 and "Traceback" not in err, err
    assert "run\\xff.mcap" in (tmp_path / "rep" / "summary.txt").read_text(encoding="utf-8")


@pytest.mark.parametrize("argv", HAND_PICKED, ids=lambda a: " ".join(a)[:60])
def test_hand_picked_bad_command_lines_are_one_line(scratch: Path, argv: list[str]) -> None:
    with _chdir(scratch):
        code, _, err = run_cli(argv)
    assert_clean(argv, code, err)
    assert code == 2, (argv, code, err)


def test_an_internal_error_is_one_line_exit_3_and_debug_shows_the_traceback(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A bug (here: an analysis that raises ZeroDivisionError) is not called bad input."""
    import dobhil.cli.analyze_cmd as analyze_cmd

    def broken(args: argparse.Namespace) -> int:
        raise ZeroDivisionError("float division by zero")

    monkeypatch.setattr(analyze_cmd, "run", broken)
    monkeypatch.delenv("DOBHIL_DEBUG", raising=False)
    code, _, err = run_cli(["analyze", "demo"])
    assert code == EXIT_INTERNAL
    assert err.splitlines() == [err.strip()] and "Traceback" not in err
    assert "internal error: ZeroDivisionError: float division by zero" in err and "DOBHIL_DEBUG=1" in err
    monkeypatch.setenv("DOBHIL_DEBUG", "1")
    code, _, err = run_cli(["analyze", "demo"])
    assert code == EXIT_INTERNAL
    assert "Traceback (most recent call last)" in err and 'raise ZeroDivisionError("float division by zero")' in err


def test_a_refused_output_file_is_one_line_exit_2(scratch: Path) -> None:
    """The system refusing a named file (here: a directory under a regular file) is bad input."""
    with _chdir(scratch):
        code, _, err = run_cli(["paper", "--out", "good.mcap/sub"])
    assert code == 2 and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert "good.mcap/sub" in err


@pytest.mark.skipif(shutil.which("dobhil") is None and not (Path(sys.executable).parent / "dobhil").exists(),
                    reason="the dobhil console script is not installed")
def test_the_installed_command_reads_no_fifo(scratch: Path) -> None:
    """Through the real entry point: a FIFO as config is refused at once (it used to block)."""
    exe = shutil.which("dobhil") or str(Path(sys.executable).parent / "dobhil")
    done = subprocess.run([exe, "analyze", "fifo.yaml"], cwd=scratch, capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and "not a regular file" in done.stderr, done.stderr


@pytest.mark.skipif(shutil.which("sh") is None, reason="needs a POSIX shell")
@pytest.mark.parametrize(("command", "redirect", "code"), [
    ("analyze demo", ">&-", 0),
    ("analyze demo --json", ">&-", 0),     # json.dump writes to sys.stdout itself
    ("analyze nonexistent.yaml", "2>&-", 2),
    ("log export run.mcap --can --format candump -o run.log", "2>&-", 0),   # its progress on stderr
])
def test_a_closed_stdout_or_stderr_is_no_traceback(scratch: Path, command: str, redirect: str, code: int) -> None:
    """Started with stdout (or stderr) closed, Python's sys.stdout (sys.stderr) is None: what
    would go there is discarded, and the command answers as it would otherwise."""
    if "run.mcap" in command:
        assert main(["run", "demo", "--emulate", "--lockstep", "--set", "loop.duration=0.05",
                     "--log", str(scratch / "run.mcap")]) == 0
    done = subprocess.run(["sh", "-c", f'"$0" -m dobhil {command} {redirect}', sys.executable],
                          cwd=scratch, capture_output=True, text=True, timeout=120)
    assert done.returncode == code and "Traceback" not in done.stderr, done.stderr
    assert "internal error" not in done.stderr, done.stderr


@pytest.mark.parametrize("argv", [
    ["analyze", "demo", "--plot", ""],
    ["paper", "--out", ""],
    ["demo", "--no-log", "--out", ""],
    ["run", "demo", "--emulate", "--lockstep", "--log", ""],
    ["sweep", "demo", "--vary", "design.force_gain=1:2:2", "--out", " "],
    ["log", "export", "x.mcap", "--can", "--format", "candump", "-o", ""],
    ["log", "recover", "x.mcap", "-o", ""],
    ["report", "x.mcap", "--out", ""],
])
def test_an_empty_output_name_is_refused(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    """An empty name is not the working directory (Path("") is "."), nor the default file:
    argparse refuses it, in one line, exit 2 (its usage error, raised as SystemExit)."""
    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "an empty name; give a file or directory name" in err, err


@pytest.mark.parametrize(("option", "line"), [
    ("--log", "--no-log with --log: give one (record the run to --log, or not at all)"),
    # not "--live needs a log (--log FILE.mcap)": following that, --log is refused with --no-log
    ("--live", "--no-log with --live: the live view plays the run's log; drop --no-log (the run is "
               "then recorded to OUT/run-*.mcap) or --live"),
])
def test_no_log_with_a_log_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str], option: str,
                                      line: str) -> None:
    """Two options that contradict each other: one line, nothing run, nothing written."""
    log = tmp_path / "a.mcap"
    value = str(log) if option == "--log" else "127.0.0.1:0"
    assert main(["demo", "--no-log", option, value, "--out", str(tmp_path / "out")]) == 2
    assert capsys.readouterr().err == f"dobhil demo: error: {line}\n"
    assert not log.exists() and not (tmp_path / "out").exists()


@pytest.mark.parametrize(("argv", "prog"), [
    (["analyze", "demo", "--bogus"], "dobhil analyze"),
    (["report", "x.mcap", "--out", "r", "--axis", "a"], "dobhil report"),
    (["log", "info", "x.mcap", "--bogus"], "dobhil log info"),
    (["analyze", "demo", "extra"], "dobhil analyze"),
])
def test_an_unknown_argument_is_the_commands_own_one_line(argv: list[str], prog: str,
                                                           capsys: pytest.CaptureFixture[str]) -> None:
    """argparse hands a subcommand's unknown arguments up to the top parser: the line must
    name the command whose ``--help`` lists what it takes, not ``dobhil`` alone (argparse's
    usage error: a SystemExit of 2)."""
    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 2
    out, err = capsys.readouterr()
    extra = " ".join(argv[-2:] if argv[-2] == "--axis" else argv[-1:])
    assert not out and err == f"{prog}: error: unrecognized arguments: {extra} ('{prog} --help' lists what it takes)\n"
