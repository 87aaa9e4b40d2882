"""The last lines of a run: its stop line and, when the drive's disable is not confirmed,
the loud line -- said whatever standard output does (``dobhil run`` and the several-axis
run alike)."""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager


def say_safe_stop(warning: str, note: str) -> None:
    """The safe stop's last word on stderr: the loud line when the drive may still be
    enabled, else a note from a drive that cannot confirm its disable by design."""
    if warning:
        sys.stderr.write(f"WARNING: {warning}\n")
    elif note:
        sys.stderr.write(f"NOTE: {note}\n")


def say_last(prog: str, log_error: str, warning: str, note: str) -> None:
    """A run's last lines on stderr: its log's failure when the log could not be finished
    after the run stopped for another reason (``log_error``, one line), then
    :func:`say_safe_stop`."""
    if log_error:
        sys.stderr.write(f"{prog}: {log_error}\n")
    say_safe_stop(warning, note)


def flush_stdout() -> None:
    """What the run printed, flushed if stdout can take it: before an error's stop line on
    stderr, a stdout that cannot be written (its own error follows from main()) must not
    keep the stop line from being said."""
    try:
        sys.stdout.flush()
    except OSError:
        pass


@contextmanager
def stop_said(prog: str, stop_line: str, last_word: Callable[[], None]) -> Iterator[None]:
    """The run's account goes to stdout inside; its safety words get out whatever stdout
    does. Standard output that cannot be written (a reader gone from the pipe, a full disk:
    ``dobhil run ... | head``, ``> /dev/full``) puts the stop line on stderr, and
    ``last_word`` (the loud line, or the note) is written last either way; the stdout error
    then goes on to main(), which ends as it documents (exit 141, or 2)."""
    try:
        yield
    except OSError:   # BrokenPipeError, or main()'s StdoutWriteError
        sys.stderr.write(f"{prog}: {stop_line}\n")
        raise
    finally:
        last_word()


__all__ = ["flush_stdout", "say_last", "say_safe_stop", "stop_said"]
