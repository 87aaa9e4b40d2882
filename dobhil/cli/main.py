"""Entry point of the ``dobhil`` command.

Each subcommand lives in its own module of this package and exposes
``register(subparsers: argparse._SubParsersAction) -> None``; the parser it adds
sets ``func=callable(args) -> int``. Any :class:`dobhil.errors.DobhilError`
(and argparse usage errors) end in one line on stderr and exit code 2, with no
traceback; so does an operating-system refusal on a named file (``--out /proc/x``:
the error names the path). Any other exception is a bug in dobhil: one
``internal error`` line and exit code 3; ``DOBHIL_DEBUG=1`` in the environment prints
the traceback as well (for every error, bad input included). Standard output that cannot be
written (a full disk or device: ``dobhil analyze demo > /dev/full``) is one line and exit code
2, as a full disk under ``--out`` is: the environment refused, dobhil did not fail.
"""

from __future__ import annotations

import argparse
import importlib
import os
import select
import sys
import traceback
import warnings
from collections.abc import Sequence
from typing import Any

from dobhil import __version__
from dobhil.errors import DobhilError, exception_line

#: Subcommand modules, in the order ``dobhil --help`` lists them.
_SUBCOMMANDS: tuple[str, ...] = (
    "dobhil.cli.analyze_cmd",
    "dobhil.cli.sweep_cmd",
    "dobhil.cli.tune_cmd",
    "dobhil.cli.certify_cmd",
    "dobhil.cli.paper_cmd",
    "dobhil.cli.run_cmd",
    "dobhil.cli.check_cmd",
    "dobhil.cli.log_cmd",
    "dobhil.cli.replay_cmd",
    "dobhil.cli.report_cmd",
    "dobhil.cli.identify_cmd",
    "dobhil.cli.montecarlo_cmd",
    "dobhil.cli.demo_cmd",
    "dobhil.cli.init_cmd",
)

EXIT_USAGE = 2
#: exit code of an unexpected exception (a bug in dobhil, not bad input)
EXIT_INTERNAL = 3
#: environment variable that makes every error also print its traceback
DEBUG_ENV = "DOBHIL_DEBUG"
#: exit code when the reader of stdout went away (``dobhil ... | head``): 128 + SIGPIPE, as a shell reports
EXIT_BROKEN_PIPE = 141

DESCRIPTION = ("Robust force control of servo drives over CAN with the disturbance observer (DOb) and "
               "reaction torque observer (RTOb): design and check the controller, run it on a drive "
               "through python-can or against the plant emulator, record every run to MCAP, replay "
               "and analyse it.")
EPILOG = ("CONFIG is a YAML file or the name of a shipped config (demo, paper/fig2c); "
          "'dobhil init DIR' copies them for editing. 'dobhil COMMAND --help' shows a command's options. "
          "Exit codes: 0 done, 1 safety stop or failed check, 2 bad input, 3 internal error "
          f"(a bug; {DEBUG_ENV}=1 shows its traceback).")


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (exit code 2) instead of usage dumps."""

    def error(self, message: str) -> None:  # type: ignore[override]
        _say(f"{self.prog}: error: {message}")
        raise SystemExit(EXIT_USAGE)

    def parse_known_args(self, args: Sequence[str] | None = None,  # type: ignore[override]
                         namespace: argparse.Namespace | None = None) -> tuple[argparse.Namespace, list[str]]:
        """Arguments this parser does not know are its error, said under its own name
        (``dobhil analyze: error: ...``). argparse hands a subcommand's unknown arguments up
        to the top parser, whose error named ``dobhil`` alone: the user could not tell which
        command's ``--help`` to read. No dobhil command passes arguments through."""
        parsed, extras = super().parse_known_args(args, namespace)
        if extras:
            self.error(f"unrecognized arguments: {' '.join(extras)} ('{self.prog} --help' lists what it takes)")
        return parsed, extras


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="dobhil", description=DESCRIPTION, epilog=EPILOG)
    parser.add_argument("--version", action="version", version=f"dobhil {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    for name in _SUBCOMMANDS:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name != name:
                raise
            continue
        module.register(sub)
    return parser


class StdoutWriteError(OSError):
    """A write to standard output failed for a reason other than a closed pipe (a full disk
    or device, an I/O error); raised by :class:`_GuardedStdout` so that it is told apart
    from an ``OSError`` of anything else a command does (a socket, a worker, a file)."""


class _GuardedStdout:
    """``sys.stdout`` while :func:`main` runs: every attribute is the real stream's, but a
    failed ``write`` or ``flush`` raises :class:`StdoutWriteError` (a closed pipe stays a
    ``BrokenPipeError``: :func:`main` tells a reader gone from a pipe of a worker)."""

    def __init__(self, stream: Any) -> None:
        self._stream = stream
        #: the first failure, kept: argparse's --help swallows an OSError of its write
        self.failed: StdoutWriteError | None = None

    def _failure(self, exc: OSError) -> StdoutWriteError:
        failure = StdoutWriteError(exc.errno, exc.strerror or exception_line(exc, named=False))
        self.failed = self.failed or failure
        return failure

    def write(self, text: str) -> int:
        try:
            return int(self._stream.write(text))
        except BrokenPipeError:
            raise
        except OSError as exc:
            raise self._failure(exc) from exc

    def writelines(self, lines: Any) -> None:
        for line in lines:
            self.write(line)

    def flush(self) -> None:
        try:
            self._stream.flush()
        except BrokenPipeError:
            raise
        except OSError as exc:
            raise self._failure(exc) from exc

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)


def main(argv: Sequence[str] | None = None) -> int:
    _closed_streams_to_devnull()
    real = sys.stdout
    guard = _GuardedStdout(real)
    sys.stdout = guard
    try:
        return _main_flushed(argv, guard)
    finally:
        if sys.stdout is guard:  # unless a command replaced it for good
            sys.stdout = real


def _main_flushed(argv: Sequence[str] | None, guard: _GuardedStdout) -> int:
    try:
        with warnings.catch_warnings():   # restores Python's own display on return
            warnings.showwarning = _one_line_warning
            try:
                code = _main(argv)
            except SystemExit:   # --help, --version: argparse printed (its write errors ignored), then exits
                guard.flush()  # a full stdout shows here, not as an ignored error at exit
                if guard.failed is not None:
                    return _stdout_failed("", guard.failed)
                raise
        guard.flush()  # a closed pipe shows here, not as a traceback at exit
        if guard.failed is not None and code == 0:  # a failed write something caught and went on from
            return _stdout_failed("", guard.failed)
    except StdoutWriteError as exc:
        return _stdout_failed("", exc)
    except BrokenPipeError:
        if not _stdout_gone():
            raise  # another pipe (a worker process, a socket): a real failure, not ours to hide
        # the reader (e.g. ``head``) has gone: stop quietly; point stdout at devnull so the
        # interpreter's final flush does not complain either
        _stdout_to_devnull()
        return EXIT_BROKEN_PIPE
    return code


def _stdout_to_devnull() -> None:
    """Point stdout's file descriptor at devnull: what is still buffered for it (and the
    interpreter's final flush) then goes nowhere instead of failing again at exit."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (AttributeError, OSError, ValueError):  # no real file descriptor (a test's capture)
        pass


def _stdout_failed(command: str, exc: StdoutWriteError) -> int:
    """Standard output could not be written (a full disk or device): one line, exit code 2
    like a full disk under ``--out`` (the environment refused, not dobhil: no internal error)."""
    _stdout_to_devnull()
    prog = f"dobhil {command}" if command else "dobhil"
    return _fail(f"{prog}: error: cannot write standard output: {exc.strerror or exception_line(exc)}",
                 EXIT_USAGE)


def _closed_streams_to_devnull() -> None:
    """Started with stdout or stderr closed (``dobhil ... >&-``), Python's ``sys.stdout``
    (``sys.stderr``) is None: ``print`` then writes nothing, but a ``write`` (``--json``, a
    progress line) would raise. What the command writes there is discarded instead, as the
    user who closed it asked."""
    for name in ("stdout", "stderr"):
        if getattr(sys, name) is None:
            setattr(sys, name, open(os.devnull, "w", encoding="utf-8"))


def _one_line_warning(message: Warning | str, category: type[Warning], filename: str, lineno: int,
                      file: Any = None, line: str | None = None) -> None:
    """A warning on the command line is one line, as an error is (a deprecated config value:
    not Python's file, line number and source line, which mean nothing to the user)."""
    _say(f"dobhil: warning: {message}")


def _stdout_gone() -> bool:
    """Whether stdout is a pipe whose reader has closed it (poll reports an error on it)."""
    try:
        poller = select.poll()
        poller.register(sys.stdout.fileno(), select.POLLOUT)
        return any(events & (select.POLLERR | select.POLLHUP) for _, events in poller.poll(0))
    except (AttributeError, OSError, ValueError):  # no poll (Windows), no real file descriptor
        return False


def _main(argv: Sequence[str] | None) -> int:
    try:  # Ctrl-C while the subcommands are imported: one line, no traceback
        args = build_parser().parse_args(argv)
    except KeyboardInterrupt:
        _say("dobhil: interrupted")
        return 130
    except Exception as exc:  # a subcommand that cannot be imported: a broken install
        return _internal("", exc)
    try:
        code = int(args.func(args) or 0)
        sys.stdout.flush()  # a full stdout is said under the command's name
        return code
    except StdoutWriteError as exc:
        return _stdout_failed(args.command, exc)
    except DobhilError as exc:
        return _fail(f"dobhil {args.command}: error: {exception_line(exc, named=False)}", EXIT_USAGE)
    except KeyboardInterrupt:
        _say(f"dobhil {args.command}: interrupted")
        return 130
    except BrokenPipeError:
        raise  # main() tells a closed stdout from a real failure
    except OSError as exc:
        if exc.filename is None:
            return _internal(args.command, exc)
        # the system refused a file the command was given or derived from its arguments
        # (a read-only place, /proc, a name too long, a disk full): one line naming it
        where = _path(exc.filename) + (f" -> {_path(exc.filename2)}" if exc.filename2 is not None else "")
        said = exc.strerror or exception_line(exc, named=False)
        return _fail(f"dobhil {args.command}: error: {where}: {said}", EXIT_USAGE)
    except Exception as exc:
        return _internal(args.command, exc)


def _path(name: object) -> str:
    return os.fsdecode(name) if isinstance(name, (str, bytes, os.PathLike)) else str(name)


def _debug() -> bool:
    return os.environ.get(DEBUG_ENV, "") not in ("", "0")


def _fail(line: str, code: int) -> int:
    if _debug() and sys.stderr is not None:
        traceback.print_exc()
    _say(line)
    return code


#: characters that end a line for ``str.splitlines`` (and for most terminals and log
#: readers): in an error line, an argument holding one is shown escaped, so it stays one line
_LINE_BREAKS = {ord(c): c.encode("unicode_escape").decode("ascii")
                for c in "\n\r\x0b\x0c\x1c\x1d\x1e\x85\u2028\u2029"}


def _say(line: str) -> None:
    """One line on stderr (none when dobhil was started with stderr closed)."""
    if sys.stderr is not None:
        sys.stderr.write(line.translate(_LINE_BREAKS) + "\n")


def _internal(command: str, exc: Exception) -> int:
    """An exception no check anticipated: a bug, said as one, with the way to its traceback."""
    hint = "the traceback is above" if _debug() else f"{DEBUG_ENV}=1 shows the traceback"
    prog = f"dobhil {command}" if command else "dobhil"
    return _fail(f"{prog}: internal error: {exception_line(exc)[:300]} "
                 f"(a bug in dobhil; {hint}; please report it)", EXIT_INTERNAL)
