"""Progress of the long commands (tune, montecarlo, sweep, identify, report, log), on stderr
so that stdout -- tables, JSON -- stays clean.

Three modes, chosen from the stream and the command's output format (:func:`mode_for`):

- a terminal: a tqdm bar (its public ``file``, ``disable``, ``mininterval`` and postfix API),
  redrawn in place;
- anything else (a log file, CI, a pipe): plain lines, because a bar's carriage returns make
  one unreadable line of a log. A line at the first step, at the last, and in between when
  another tenth of a known total is done or :data:`LINE_SECONDS` have passed since the last
  line: at most 11 lines plus one per :data:`LINE_SECONDS`, however many steps;
- ``--json``: nothing (the one JSON object is the whole output).
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from enum import IntEnum
from typing import Any, TextIO


class Mode(IntEnum):
    OFF = 0
    BAR = 1
    LINES = 2


#: line mode: the longest silence between two lines [s]
LINE_SECONDS = 30.0
#: line mode: a line each time another 1/LINE_PARTS of a known total is done (tenths)
LINE_PARTS = 10
#: bar mode: tqdm's shortest redraw interval [s] (its default, 0.1 s, redraws too often in a
#: terminal multiplexer for no information)
BAR_SECONDS = 0.5


def mode_for(stream: TextIO, *, quiet: bool = False) -> Mode:
    """OFF with ``quiet`` (--json), BAR on a terminal, LINES otherwise."""
    if quiet:
        return Mode.OFF
    isatty = getattr(stream, "isatty", None)
    return Mode.BAR if isatty is not None and isatty() else Mode.LINES


def duration_text(seconds: float) -> str:
    """``42 s``, ``3 min 5 s``, ``1 h 02 min``."""
    s = max(0, int(round(seconds)))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60} s"
    return f"{s // 3600} h {(s % 3600) // 60:02d} min"


class Progress:
    """Counts steps of one piece of work and shows them as :class:`Mode` says.

    ``update(n, note)``: ``n`` more steps done; ``note`` (optional) says what the latest step
    found (a best value, a failure count) and is shown with the count."""

    def __init__(self, desc: str, *, total: int | None, unit: str, stream: TextIO, mode: Mode,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.desc, self.total, self.unit, self.stream, self.mode = desc, total, unit, stream, mode
        self.clock = clock
        self.done = 0
        self.note = ""
        self.started = clock()
        self._last_line = -math.inf      # clock of the last line written
        self._said = -1                  # self.done when the last line was written
        self._bar: Any = None
        if mode is Mode.BAR:
            from tqdm import tqdm
            self._bar = tqdm(total=total, desc=desc, unit=unit, file=stream, mininterval=BAR_SECONDS,
                             dynamic_ncols=True)

    def update(self, n: int = 1, note: str | None = None) -> None:
        self.done += n
        if note is not None:
            self.note = note
        if self._bar is not None:
            if note is not None:
                self._bar.set_postfix_str(note, refresh=False)
            self._bar.update(n)
        elif self.mode is Mode.LINES:
            self._maybe_line()

    def _maybe_line(self) -> None:
        now = self.clock()
        first = self._said < 0
        last = self.total is not None and self.done >= self.total
        part = bool(self.total) and self._part(self.done) > self._part(self._said)
        if first or last or part or now - self._last_line >= LINE_SECONDS:
            self._line(now)

    def _line(self, now: float) -> None:
        self.stream.write(self.text(now) + "\n")
        self.stream.flush()
        self._last_line, self._said = now, self.done

    def _part(self, done: int) -> int:
        """Which tenth of the total ``done`` is in (whole numbers: no rounding at 30 %)."""
        return LINE_PARTS * max(0, done) // (self.total or 1)

    def text(self, now: float) -> str:
        """``desc: 120/1000 runs (12 %), 9.8 runs/s, 1 min 30 s left; note`` (the first line
        without the rate and the time left)."""
        elapsed = now - self.started
        rate = self.done / elapsed if elapsed > 0 else math.nan
        units = self.unit if self.done == 1 else self.unit + "s"
        if self.total:
            head = f"{self.desc}: {self.done}/{self.total} {units} ({100 * self.done / self.total:.0f} %)"
        else:
            head = f"{self.desc}: {self.done} {units}"
        parts = [head, f"{duration_text(elapsed)} elapsed"]
        # the first line's one step timed mostly the start-up (imports, compilation, opening
        # files): a rate from it, and the time left, were off by orders of magnitude
        if self._said >= 0 and math.isfinite(rate) and rate > 0:
            parts.append(f"{rate:.3g} {self.unit}s/s")
            if self.total and self.done < self.total:
                parts.append(f"about {duration_text((self.total - self.done) / rate)} left")
        return ", ".join(parts) + (f"; {self.note}" if self.note else "")

    def close(self, *, last: bool = True) -> None:
        """The last line (lines mode) when ``last``, something was done and the last step did
        not already say it; the bar closed."""
        if self._bar is not None:
            self._bar.close()
        elif self.mode is Mode.LINES and last and self.done > 0 and self.done != self._said:
            self._line(self.clock())


@contextmanager
def progress(desc: str, *, total: int | None = None, unit: str = "step", quiet: bool = False,
             stream: TextIO | None = None) -> Iterator[Progress]:
    """A :class:`Progress` on ``stream`` (default: stderr), closed on leaving (with its last
    line when the work ended, without when it raised); ``quiet`` (--json, or work too small
    to be worth a line) shows nothing."""
    out = sys.stderr if stream is None else stream
    shown = Progress(desc, total=total, unit=unit, stream=out, mode=mode_for(out, quiet=quiet))
    try:
        yield shown
    except BaseException:
        # the work failed: its one error line is what the user reads, not a last count
        shown.close(last=False)
        raise
    shown.close()


__all__ = ["LINE_PARTS", "LINE_SECONDS", "Mode", "Progress", "duration_text", "mode_for", "progress"]
