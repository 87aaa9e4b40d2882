"""The exception root of dobhil and its specific subclasses.

Each subclass also inherits the matching builtin (the python-can habit:
``CanTimeoutError(CanError, TimeoutError)``), so callers can catch either.
Messages say what was expected and what came, in one line.
"""

from __future__ import annotations


class DobhilError(Exception):
    """Root of every error raised by dobhil."""


class ConfigError(DobhilError, ValueError):
    """A configuration key, value or file is not acceptable."""


class UnstableDesignError(ConfigError):
    """The loop a run would close is unstable at its force gain (the stability gate,
    :mod:`dobhil.analysis.gate`); the message says the verdict and how to proceed."""


class SynthesisError(DobhilError, ValueError):
    """The requested observer or loop cannot be synthesised (e.g. unobservable model)."""


class AnalysisError(DobhilError, ValueError):
    """A valid design the analysis cannot answer (one line saying why)."""


class BusError(DobhilError, OSError):
    """A CAN bus could not be opened or used."""


class DriveError(DobhilError):
    """A drive did not behave as its protocol promises."""


class DriveTimeoutError(DriveError, TimeoutError):
    """A drive did not answer in time."""


class DriveFaultError(DriveError):
    """A drive reported a fault (axis error, watchdog, emergency)."""


class WaitCancelled(DriveError):
    """A wait for a drive was cut short by a stop request (SIGINT, SIGTERM); the
    message names the request and the wait."""


class PreflightError(DriveError):
    """The drive's measured settings do not allow a safe run (e.g. stale feedback).

    ``report`` is the :class:`dobhil.drives.preflight.PreflightReport`; the message is
    its mismatches on one line.
    """

    def __init__(self, report: object) -> None:
        self.report = report
        lines: list[str] = getattr(report, "mismatches", lambda: [])()
        super().__init__("preflight refused the run: " + "; ".join(lines))


class CodecError(DriveError, ValueError):
    """A CAN frame could not be encoded or decoded by a drive codec."""


class LogFileError(DobhilError, ValueError):
    """A log file is missing, empty, truncated or not of the expected format."""


class RecorderError(DobhilError, OSError):
    """The recorder of a run failed (disk full, writer process gone); the run stops with
    reason ``recorder_failed``."""


class ReplayMismatchError(DobhilError, AssertionError):
    """Replay did not reproduce the recorded commands."""


def exception_line(exc: BaseException, *, named: bool = True) -> str:
    """``exc`` as one line for a message: its text with every run of white space (line
    breaks included: a transport's multi-line error, a parser's caret diagram) folded to
    one space, after its type's name when ``named`` (an ``OSError``'s or a ``KeyError``'s
    text alone says little). An exception with no text, or whose ``str`` itself fails,
    is its type's name. Never raises: it runs on error and safe-stop paths."""
    name = type(exc).__name__
    try:
        text = " ".join(str(exc).split())
    except Exception:  # a third party's __str__ that fails must not hide the first error
        text = ""
    if not text:
        return name
    return f"{name}: {text}" if named else text
