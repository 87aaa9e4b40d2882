"""Progress of long commands (:mod:`dobhil.cli.progress`): plain lines when stderr is not a
terminal (first, last, each tenth, one per LINE_SECONDS at most in between), a bar on a
terminal (a fake ``isatty`` and a real pty), nothing with --json; ``tune`` and
``montecarlo`` say it as they run."""

from __future__ import annotations

import io
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dobhil.cli.main import main
from dobhil.cli.progress import LINE_SECONDS, Mode, Progress, mode_for, progress

ROOT = Path(__file__).resolve().parents[1]


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def lines_of(out: io.StringIO) -> list[str]:
    return out.getvalue().splitlines()


@settings(max_examples=60, deadline=None)
@given(total=st.integers(1, 5000), steps=st.lists(st.integers(1, 50), min_size=1, max_size=300),
       gaps=st.lists(st.floats(0.0, 2 * LINE_SECONDS), min_size=1, max_size=300))
def test_lines_first_last_tenths_and_time(total: int, steps: list[int], gaps: list[float]) -> None:
    out, clock = io.StringIO(), FakeClock()
    shown = Progress("work", total=total, unit="item", stream=out, mode=Mode.LINES, clock=clock)
    done, updates = 0, []
    for i, n in enumerate(steps):
        n = min(n, total - done)
        if n <= 0:
            break
        clock.now += gaps[i % len(gaps)]
        shown.update(n)
        done += n
        updates.append(done)
    elapsed = clock.now - 100.0
    shown.close()
    lines = lines_of(out)
    counts = [int(re.match(r"work: (\d+)/", line).group(1)) for line in lines]  # type: ignore[union-attr]
    assert counts[0] == min(steps[0], total) and counts[-1] == done          # the first and the last
    assert counts == sorted(set(counts))                                      # never twice the same
    assert len(lines) <= 2 + 10 + elapsed / LINE_SECONDS                      # at most a line a tenth / period
    said = -1
    for c in updates:                          # an update that reached a new tenth is a line
        if c in counts:
            said = c
        else:
            assert 10 * c // total == 10 * max(said, 0) // total


def test_without_a_total_a_line_per_period_and_the_last() -> None:
    out, clock = io.StringIO(), FakeClock()
    with_total = Progress("tune", total=None, unit="generation", stream=out, mode=Mode.LINES, clock=clock)
    for _ in range(100):
        clock.now += LINE_SECONDS / 10
        with_total.update(1, "best 3 ms")
    with_total.close()
    lines = lines_of(out)
    # the first, one per LINE_SECONDS of the 10 periods, and the last
    assert len(lines) == 1 + 9 + 1
    assert lines[0].startswith("tune: 1 generation, ") and lines[-1].startswith("tune: 100 generations, ")
    assert all(line.endswith("; best 3 ms") for line in lines)


def test_the_mode_follows_the_stream_and_json() -> None:
    assert mode_for(Terminal()) is Mode.BAR and mode_for(io.StringIO()) is Mode.LINES
    assert mode_for(Terminal(), quiet=True) is Mode.OFF and mode_for(io.StringIO(), quiet=True) is Mode.OFF


def test_a_terminal_gets_a_bar_redrawn_in_place_and_quiet_nothing() -> None:
    term = Terminal()
    with progress("montecarlo", total=50, unit="run", stream=term) as shown:
        for _ in range(50):
            shown.update(1, "0 failed")
    text = term.getvalue()
    assert "\r" in text and "50/50" in text and "0 failed" in text and text.count("\n") <= 1
    quiet = io.StringIO()
    with progress("montecarlo", total=50, unit="run", stream=quiet, quiet=True) as shown:
        shown.update(50)
    assert quiet.getvalue() == ""


#: a small tune problem (tests/tune/test_cli.py's)
SMALL_TUNE = ["tune", "paper/fig3", "--range", "environment.stiffness=1e3:1e5", "--grid", "6", "--generations", "4"]


def test_tune_says_each_generation_on_stderr_and_nothing_with_json(capsys: pytest.CaptureFixture[str]) -> None:
    started = time.monotonic()
    assert main(SMALL_TUNE) == 0
    elapsed = time.monotonic() - started
    out, err = capsys.readouterr()
    lines = [line for line in err.splitlines() if line.startswith("tune: ")]
    assert lines and not any(line.startswith("tune: ") for line in out.splitlines())
    assert lines[0].startswith("tune: 1 generation, ") and len(lines) <= 2 + elapsed / LINE_SECONDS
    last = re.match(r"tune: (\d+) generations?, .*; round (\d+) generation (\d+): best worst-case rise time "
                    r"([\d.]+) ms; (.*)$", lines[-1])
    assert last, lines[-1]
    generations = int(re.search(r"(\d+) generations,", out).group(1))  # type: ignore[union-attr]
    assert int(last.group(1)) == generations    # the last line counts every generation the report counts
    assert any(w in last.group(5) for w in ("active", "to spare", "broken by"))
    assert main([*SMALL_TUNE, "--json"]) == 0
    out, err = capsys.readouterr()
    assert "tune: " not in err and out.startswith("{")


def test_montecarlo_lines_count_runs_and_failures(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # seed 3: two of the six inertias are drawn <= 0 (refused runs, tests/campaign/test_cli.py)
    code = main(["montecarlo", "demo", "--runs", "6", "--seed", "3", "--duration", "0.3", "--workers", "1",
                 "--vary", "plant.inertia=normal:0.06:0.05"])
    out, err = capsys.readouterr()
    lines = [line for line in err.splitlines() if line.startswith("montecarlo: ")]
    assert code == 1 and lines and "montecarlo: 1/6 run (17 %)" in lines[0]
    assert lines[-1].startswith("montecarlo: 6/6 runs (100 %)") and lines[-1].endswith("; 2 failed")
    assert "montecarlo: 1/6" not in out


def test_a_pty_gets_the_bar(tmp_path: Path) -> None:
    """stderr on a real terminal (a pty): a bar redrawn with carriage returns, no lines."""
    import fcntl
    import pty
    import struct
    import termios
    leader, follower = pty.openpty()
    # a fresh pty is 0 columns wide (a bar of width 0 draws nothing): a terminal's size
    fcntl.ioctl(follower, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 120, 0, 0))
    env = {**os.environ, "PYTHONPATH": str(ROOT), "COLUMNS": "120"}
    try:
        done = subprocess.run([sys.executable, "-m", "dobhil", *SMALL_TUNE], stdout=subprocess.PIPE,
                              stderr=follower, env=env, timeout=240)
        os.close(follower)
        follower = -1
        chunks = []
        while True:
            try:
                chunk = os.read(leader, 65536)
            except OSError:   # the pty's other end is closed: all read
                break
            if not chunk:
                break
            chunks.append(chunk)
    finally:
        if follower >= 0:
            os.close(follower)
        os.close(leader)
    err = b"".join(chunks).decode(errors="replace")
    assert done.returncode == 0 and b"tune: " not in done.stdout
    assert "\r" in err and "generation" in err and "tune: 1 generation, " not in err


def test_work_that_fails_leaves_its_error_line_alone() -> None:
    """Bad input must stay one line: a failure before any step writes no count at all."""
    out = io.StringIO()
    with pytest.raises(ValueError), progress("export", total=10, unit="message", stream=out):
        raise ValueError("no topic")
    assert out.getvalue() == ""
    with progress("export", total=None, unit="message", stream=out):
        pass
    assert out.getvalue() == ""            # nothing done, nothing to say


def test_the_first_line_gives_no_rate_of_the_start_up() -> None:
    """The first line comes at the first step, whose time is mostly the command's start-up
    (imports, compilation, opening the file): a rate and time left from it are wrong by
    orders of magnitude (``dobhil log export`` of 6043 frames said "22.9 messages/s, about 4
    min 23 s left" and was done in under a second). Later lines give both."""
    out, clock = io.StringIO(), FakeClock()
    shown = Progress("export", total=6043, unit="message", stream=out, mode=Mode.LINES, clock=clock)
    clock.now += 0.04
    shown.update(1)
    clock.now += 0.02
    shown.update(604)
    shown.close()
    first, second = lines_of(out)[:2]
    assert first == "export: 1/6043 message (0 %), 0 s elapsed", first
    assert "messages/s" in second and "left" in second, second
