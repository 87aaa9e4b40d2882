"""``python -m dobhil ARGS`` in a child forked from one process that imported dobhil once
(``from dobhil_forks import DobhilForks``).

A command of the docs pages spends a second or more of CPU importing dobhil, numpy, scipy,
python-control and matplotlib before it does its work: measured, ``python -m dobhil analyze
demo`` took 2.8 s of user time, of which importing took 1.6 s. The server (this file run as a
script) imports them once; each command then runs in a child ``os.fork()`` makes of it, which
``runpy`` runs as ``python -m dobhil`` runs it (``dobhil/__main__.py`` as ``__main__``, the
working directory first on ``sys.path``), its standard output and error into files, its
standard input /dev/null, its exit code the process's. A child is a process of its own: what
one command changes (modules' state, the working directory, signal handlers) dies with it,
as between two ``python -m dobhil`` processes. What a child shares with the others is the
server's import-time state, the same for every ``python -m dobhil`` of one environment.
tests/test_docs_figures.py checks that a command answers the same here as in a new process.

The forking (POSIX only) is the standard library's: :func:`os.fork`, then the child's exit
handlers (:mod:`atexit`, so logging and matplotlib close as at interpreter exit) and
:func:`os._exit`, as ``multiprocessing``'s fork start method does
(``multiprocessing/popen_fork.py``).
"""

from __future__ import annotations

import atexit
import importlib
import importlib.util
import json
import os
import runpy
import selectors
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import traceback
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType

#: imported once by the server: what the pages' commands (analyze, identify, run, compare,
#: certify) import at their start -- and numba, which every identify imports at its first
#: simulation (dobhil/identify/model.py, closedloop.py: 0.09 s of CPU each time, measured;
#: docs/identify.md runs eleven)
#: Also what a run and an identify import only once they start (python-can and its log
#: formats, the runtime, lmfit and the fits): 0.3-0.5 s of CPU in each such command, measured
#: by diffing ``sys.modules`` around a forked ``run``/``identify``.
WARM = ("dobhil.cli.main", "dobhil.analysis.report", "dobhil.identify", "matplotlib.pyplot",
        "scipy.optimize", "scipy.signal", "numba", "dobhil.cli.recording", "dobhil.runtime.session",
        "dobhil.recording.reader", "dobhil.identify.fit", "dobhil.identify.closedloop",
        "dobhil.identify.choose", "dobhil.identify.intervals", "dobhil.identify.compare", "lmfit")


@dataclass(frozen=True)
class Done:
    """What one command gave: as :func:`subprocess.run` with ``capture_output``."""

    returncode: int
    stdout: str
    stderr: str


class DobhilForks:
    """The server process, started with ``env`` (this process' when None); :meth:`run` one
    command at a time. A server killed by a command's time-out is started again by the next
    command (one fixture serves a whole session)."""

    def __init__(self, env: dict[str, str] | None = None) -> None:
        self._env = env
        self._files = Path(tempfile.mkdtemp(prefix="dobhil-forks-"))
        self._proc = self._start()

    def _start(self) -> subprocess.Popen[str]:
        return subprocess.Popen([sys.executable, __file__], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                env=self._env, text=True, start_new_session=True)

    def run(self, args: list[str], cwd: Path, timeout: float, env: Mapping[str, str] | None = None) -> Done:
        """``python -m dobhil *args`` in ``cwd``, with the environment ``env`` (the server's
        when None; read by the command, not by the imports the server made); TimeoutError
        (the server and its child killed) when it takes over ``timeout`` seconds."""
        if self._proc.poll() is not None:
            self._proc = self._start()
        out, err = self._files / "stdout", self._files / "stderr"
        assert self._proc.stdin is not None and self._proc.stdout is not None
        request = {"args": args, "cwd": str(cwd), "stdout": str(out), "stderr": str(err),
                   "env": None if env is None else dict(env)}
        self._proc.stdin.write(json.dumps(request) + "\n")
        self._proc.stdin.flush()
        with selectors.DefaultSelector() as sel:
            sel.register(self._proc.stdout, selectors.EVENT_READ)
            if not sel.select(timeout):
                self._stop()
                raise TimeoutError(f"dobhil {' '.join(args)}: no exit in {timeout} s")
        line = self._proc.stdout.readline()
        if not line:
            raise RuntimeError(f"the fork server died (exit {self._proc.wait()})")
        try:
            return Done(int(line), out.read_text(encoding="utf-8"), err.read_text(encoding="utf-8"))
        finally:
            out.unlink()
            err.unlink()

    def _stop(self) -> None:
        """The server and the command it runs killed (its process group)."""
        if self._proc.poll() is None:
            os.killpg(self._proc.pid, signal.SIGKILL)
        self._proc.wait()
        for pipe in (self._proc.stdin, self._proc.stdout):
            if pipe is not None:
                pipe.close()

    def close(self) -> None:
        self._stop()
        shutil.rmtree(self._files, ignore_errors=True)

    def __enter__(self) -> DobhilForks:
        return self

    def __exit__(self, kind: type[BaseException] | None, value: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


# -- the server ----------------------------------------------------------------------


def _serve() -> None:
    for name in WARM:
        importlib.import_module(name)
    from dobhil.cli.main import build_parser
    build_parser()   # imports every subcommand's module
    from dobhil.drives.registry import PROTOCOL_CLASSES
    for module, _ in PROTOCOL_CLASSES.values():   # the built-in drives a run loads by name
        importlib.import_module(module)
    # a thread would not be in the child (os.fork copies the calling thread only)
    assert threading.active_count() == 1, threading.enumerate()
    replies = os.fdopen(os.dup(1), "w")
    for line in sys.stdin:
        request = json.loads(line)
        sys.stdout.flush()
        sys.stderr.flush()
        pid = os.fork()
        if pid == 0:
            _child(request)   # never returns
        _, status = os.waitpid(pid, 0)
        replies.write(f"{os.waitstatus_to_exitcode(status)}\n")
        replies.flush()


def _child(request: dict[str, object]) -> None:
    """Run the command as ``python -m dobhil`` would, then exit the process."""
    code = 1
    try:
        os.chdir(str(request["cwd"]))
        if isinstance(request["env"], dict):
            os.environ.clear()
            os.environ.update(request["env"])
        for fd, path, flags in ((0, os.devnull, os.O_RDONLY), (1, request["stdout"], os.O_WRONLY | os.O_CREAT),
                                (2, request["stderr"], os.O_WRONLY | os.O_CREAT)):
            target = os.open(str(path), flags | (os.O_TRUNC if fd else 0), 0o644)
            os.dup2(target, fd)
            os.close(target)
        sys.stdin = open(0, encoding="utf-8", closefd=False)   # the server's was its request pipe
        args = request["args"]
        assert isinstance(args, list)
        main = importlib.util.find_spec("dobhil.__main__")
        assert main is not None and main.origin is not None
        sys.argv = [main.origin, *map(str, args)]
        sys.path[0] = os.getcwd()   # as `python -m` puts the working directory first
        code = _exit_code(lambda: runpy.run_module("dobhil", run_name="__main__", alter_sys=True))
    except BaseException:
        traceback.print_exc()
    finally:
        # an interpreter's exit: wait for non-daemon threads, then the exit handlers (as
        # multiprocessing's forked child does, multiprocessing/process.py _bootstrap)
        threading._shutdown()  # type: ignore[attr-defined]
        atexit._run_exitfuncs()
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        os._exit(code)


def _exit_code(body: Callable[[], object]) -> int:
    """The exit code of ``body()`` as the interpreter gives it: SystemExit's code (None 0, a
    text printed and 1), an uncaught exception's traceback and 1."""
    try:
        body()
    except SystemExit as exc:
        if exc.code is None or isinstance(exc.code, int):
            return int(exc.code or 0)
        print(exc.code, file=sys.stderr)
        return 1
    except BaseException:
        traceback.print_exc()
        return 1
    return 0


if __name__ == "__main__":
    _serve()
