"""Child processes forked from one process that imported their code once.

A child of its own interpreter (``python -c ...``) spends most of its start importing:
measured on this 2-core VM, an emulated drive's process took 0.42-0.65 s of CPU for a
short real-time run, of which importing python-can, numpy, the configuration and the
drive code took about 0.35 s. A program (a test suite, a campaign of real-time runs) that
starts many such children pays that every time. :class:`ForkServer` is one process, started
the usual way, that imports the modules it is given once and then ``os.fork()``\\ s a child
per :meth:`ForkServer.start`: the child has the modules already.

Why by hand: the standard library's ``multiprocessing`` "forkserver" start method does the
same, but its children re-run the parent's main module (``multiprocessing.spawn.prepare``
imports ``__main__`` from its path), and a python-can program opening
``can.Bus(interface="dobhil")`` at the top of a script without a ``__main__`` guard would
start itself again (dobhil/emulator/process.py says so for the emulator); and its children
take their arguments through its own pickler. Here a child runs one named function with
the file descriptors it was handed (``socket.send_fds``) and pickled arguments, nothing else.

What a child gets, as a fresh ``subprocess`` child would: the caller's environment
(``os.environ`` at the call, not at the server's start), working directory and standard
error (the caller's fd 2 at the call), standard input and output /dev/null, default signal
handlers. What it shares with every other child is the server's import-time state. The
server is single-threaded when it forks (checked: a thread would not be in the child) and
ignores the stop signals (:data:`STOP_SIGNALS`: a Ctrl-C reaches the whole process group,
and the server only relays; each child decides for itself). It ends when the process that started it closes
its end of the control socket -- at exit, however it exits.

A child is not the caller's child but the server's, so its exit status travels: the server
reaps it (SIGCHLD) and writes the status into a pipe whose read end the caller holds
(:class:`Child`, with the methods of :class:`subprocess.Popen` the callers use: ``pid``,
``poll``, ``wait``, ``kill``, ``returncode``).

POSIX only (``os.fork``, ``socket.send_fds``): :func:`available` says whether this platform
has them; callers start a fresh interpreter where it does not.
"""

from __future__ import annotations

import atexit
import errno
import importlib
import os
import pickle
import resource
import select
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

#: how many file descriptors one request may hand over
MAX_FDS = 16
#: the largest request (the target, its arguments, the environment), bytes
MAX_REQUEST = 1 << 20
#: the exit status a pipe carries: the ``subprocess`` convention (negative: the signal)
_STATUS = struct.Struct("<i")
#: the signals that stop a run safely (dobhil/runtime/signals.py routes them to the loop's
#: stop request). A terminal sends them to the whole process group (Ctrl-C, Ctrl-\\, its
#: closing), so the run's helper processes -- this server, the log's writer, the emulated
#: drive -- ignore them and outlive the run's safe stop. SIGHUP and SIGQUIT: POSIX only.
STOP_SIGNALS: tuple[signal.Signals, ...] = tuple(
    getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP", "SIGQUIT") if hasattr(signal, name))
#: the signals whose handling a child sets for itself (:func:`_child`)
_CHANGED = frozenset({*STOP_SIGNALS, signal.SIGCHLD})
#: returncode of a child whose status was lost with its server (the server was killed)
LOST = -255

_BOOT = "import sys; sys.path.insert(0, sys.argv[1]); from dobhil.forkserver import serve; serve()"


#: the directory holding this very dobhil (a child of ``python -c`` must import it from there)
ROOT = str(Path(__file__).resolve().parents[1])


def child_env() -> dict[str, str]:
    """This process' environment with :data:`ROOT` first on the path: a new interpreter
    imports the same dobhil (the parent may have put a source tree on ``sys.path`` by hand)."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([ROOT, *filter(None, [env.get("PYTHONPATH")])])
    return env


def available() -> bool:
    """``os.fork`` and ``socket.send_fds`` are there (POSIX, Python 3.9+)."""
    return hasattr(os, "fork") and hasattr(socket, "send_fds") and hasattr(socket, "AF_UNIX")


class Child:
    """A child of the server, as the caller sees it (the :class:`subprocess.Popen` methods
    dobhil uses). ``returncode``: None while it runs, then its exit code, or minus the
    signal that killed it, or :data:`LOST` when its server died before saying."""

    def __init__(self, pid: int, status_fd: int) -> None:
        self.pid = pid
        self.returncode: int | None = None
        self._fd: int | None = status_fd
        os.set_blocking(status_fd, False)

    def _read(self) -> bool:
        """Take the status if it is there; True once it is known."""
        if self.returncode is not None:
            return True
        if self._fd is not None:
            try:
                data = os.read(self._fd, _STATUS.size)   # one write of 4 bytes: atomic
            except BlockingIOError:
                return False
            os.close(self._fd)
            self._fd = None
            if len(data) == _STATUS.size:
                self.returncode = _STATUS.unpack(data)[0]
                return True
        # the pipe ended without a status: the server died (killed); the child, if still
        # there, is init's now, and only its absence can be seen
        if _alive(self.pid):
            return False
        self.returncode = LOST
        return True

    def poll(self) -> int | None:
        self._read()
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        """The exit code; :class:`subprocess.TimeoutExpired` after ``timeout`` seconds."""
        end = None if timeout is None else time.monotonic() + timeout
        while not self._read():
            left = None if end is None else end - time.monotonic()
            if left is not None and left <= 0:
                raise subprocess.TimeoutExpired(f"forked child {self.pid}", timeout or 0.0)
            if self._fd is not None:
                select.select([self._fd], [], [], left)
            else:
                time.sleep(0.02 if left is None else min(left, 0.02))
        assert self.returncode is not None
        return self.returncode

    def kill(self) -> None:
        if self.poll() is None:
            try:
                os.kill(self.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass

    def __del__(self) -> None:
        if self._fd is not None:
            os.close(self._fd)


def _alive(pid: int) -> bool:
    """``pid`` is a process that has not ended (a zombie has: init may be slow to reap it,
    or, in a container, never)."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as stat:
            return stat.read().rsplit(b")", 1)[1].split()[0] != b"Z"
    except FileNotFoundError:
        return False
    except OSError:
        pass   # no /proc: ask the kernel (a zombie then counts as there)
    try:
        os.kill(pid, 0)
        return True
    except PermissionError:   # another user's process: it is there
        return True
    except ProcessLookupError:
        return False


class ForkServer:
    """The server process, importing ``preload`` once (module names, or ``module:function``
    to call a function of the module once it is imported); :meth:`start` forks a
    child of it. Started with this process' environment and with the directory of this very
    dobhil first on the path (as a child of ``python -c`` needs it)."""

    def __init__(self, preload: Sequence[str]) -> None:
        self.preload = tuple(preload)
        self._lock = threading.Lock()
        self._sock: socket.socket | None = None
        self._proc: subprocess.Popen[bytes] | None = None
        self._owner = 0

    def _ensure(self) -> socket.socket:
        if self._sock is not None and self._owner == os.getpid() and self._proc is not None \
                and self._proc.poll() is None:
            return self._sock
        self._close()
        host, server = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        try:
            self._proc = subprocess.Popen(
                [sys.executable, "-c", _BOOT, ROOT, str(server.fileno()), *self.preload],
                pass_fds=(server.fileno(),), stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL, env=child_env())
        except BaseException:
            host.close()
            raise
        finally:
            server.close()
        self._sock, self._owner = host, os.getpid()
        return host

    def start(self, target: str, args: tuple[Any, ...] = (), fds: Sequence[int] = ()) -> Child:
        """Fork a child that runs ``target`` (``"module:function"``) as ``function(*fds,
        *args)``, ``fds`` its own copies of the caller's descriptors; its exit code is the
        function's ``sys.exit`` code (0 when it returns, 1 on an uncaught exception)."""
        payload = pickle.dumps((target, args, dict(os.environ), os.getcwd(), _thread_state()))
        if len(payload) > MAX_REQUEST or len(fds) + 1 > MAX_FDS:
            raise ValueError("request too large for the fork server")
        with self._lock:
            for _try in (0, 1):
                sock = self._ensure()
                try:
                    socket.send_fds(sock, [payload], [2, *fds])
                    msg, got, _, _ = socket.recv_fds(sock, 64, 1)
                except OSError:
                    msg, got = b"", []
                if msg and got:
                    return Child(int(msg), got[0])
                for fd in got:
                    os.close(fd)
                self._close()   # the server died (killed?): one new one, once
        raise OSError(errno.ECHILD, "the fork server did not start the child")

    def _close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        proc, self._proc = self._proc, None
        if proc is not None and self._owner == os.getpid():
            try:
                proc.wait(5.0)   # it reads the end of its socket and exits
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()

    @property
    def pid(self) -> int | None:
        """The server's pid while it runs (None before the first child, or after close)."""
        proc = self._proc
        return proc.pid if proc is not None and proc.poll() is None else None

    def close(self) -> None:
        """End the server (at exit: registered with atexit). A Ctrl-C while it waits for the
        server to go -- a second one just after a run's end lands here -- kills it at once:
        no server left behind, no traceback after the run's last line."""
        with self._lock:
            proc = self._proc
            try:
                self._close()
            except KeyboardInterrupt:
                if proc is not None:
                    proc.kill()
                    proc.wait()


_SERVERS: dict[tuple[str, ...], ForkServer] = {}
_SERVERS_LOCK = threading.Lock()


def server(preload: Sequence[str]) -> ForkServer:
    """The one server of this process for ``preload`` (made on first use, closed at exit)."""
    key = tuple(preload)
    with _SERVERS_LOCK:
        found = _SERVERS.get(key)
        if found is None:
            found = _SERVERS[key] = ForkServer(key)
            atexit.register(found.close)
        return found


def server_pids() -> set[int]:
    """The pids of this process' running fork servers (:func:`server`): processes it keeps
    on purpose, whose children are the ones it started."""
    with _SERVERS_LOCK:
        servers = list(_SERVERS.values())
    return {pid for pid in (srv.pid for srv in servers) if pid is not None}


# -- the server ------------------------------------------------------------------------


def serve() -> None:
    """The server's main (``python -c _BOOT root fd module...``)."""
    for sig in STOP_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)
    # the mask of the thread that started it (a writer starts with SIGINT blocked): none
    # here, or a blocked SIGCHLD would leave every child unreported (each child sets its
    # caller's own)
    signal.pthread_sigmask(signal.SIG_SETMASK, [])
    ctl = socket.socket(fileno=int(sys.argv[2]))
    for name in sys.argv[3:]:   # "module" or "module:function" (called once imported)
        module, _, function = name.partition(":")
        imported = importlib.import_module(module)
        if function:
            getattr(imported, function)()
    # a thread would not be in the children (os.fork copies the calling thread only)
    assert threading.active_count() == 1, threading.enumerate()
    wake_r, wake_w = os.pipe()
    os.set_blocking(wake_r, False)
    os.set_blocking(wake_w, False)
    signal.set_wakeup_fd(wake_w)
    signal.signal(signal.SIGCHLD, lambda *_: None)
    pipes: dict[int, int] = {}      # child pid -> the write end of its status pipe
    while True:
        try:
            readable, _, _ = select.select([ctl.fileno(), wake_r], [], [])
        except InterruptedError:
            continue
        if wake_r in readable:
            while True:
                try:
                    os.read(wake_r, 512)
                except BlockingIOError:
                    break
            _reap(pipes)
        if ctl.fileno() in readable:
            try:
                msg, fds, _, _ = socket.recv_fds(ctl, MAX_REQUEST, MAX_FDS)
            except OSError:
                msg, fds = b"", []
            if not msg:
                break   # the caller closed its end (or is gone): no more children
            _fork(ctl, msg, fds, pipes, (wake_r, wake_w))
            _reap(pipes)
    for fd in pipes.values():   # children still running report nothing more: their ends close
        os.close(fd)


def _reap(pipes: dict[int, int]) -> None:
    while pipes:
        try:
            pid, status = os.waitpid(-1, os.WNOHANG)
        except ChildProcessError:
            return
        if pid == 0:
            return
        fd = pipes.pop(pid, None)
        if fd is not None:
            try:
                os.write(fd, _STATUS.pack(os.waitstatus_to_exitcode(status)))
            except OSError:
                pass   # the caller dropped its end
            os.close(fd)


def _fork(ctl: socket.socket, msg: bytes, fds: list[int], pipes: dict[int, int],
          own: tuple[int, int]) -> None:
    status_r, status_w = os.pipe()
    sys.stdout.flush()
    sys.stderr.flush()
    # the signals whose handlers the child changes are blocked from the fork until it has
    # its caller's mask: one sent to the new pid early stays pending (on Linux a blocked
    # signal is kept even where the server ignores it), then goes where a child the caller
    # started itself would take it -- held on by a caller that blocked it (a run's writer),
    # delivered to the child's own handler otherwise -- never raised while the request is
    # still being read
    held = signal.pthread_sigmask(signal.SIG_BLOCK, _CHANGED)
    try:
        pid = os.fork()
    except BaseException:
        signal.pthread_sigmask(signal.SIG_SETMASK, held)
        raise
    if pid == 0:
        signal.set_wakeup_fd(-1)   # before its pipe closes
        os.close(status_r)
        os.close(status_w)
        for fd in pipes.values():
            os.close(fd)
        ctl.close()
        for fd in own:
            os.close(fd)
        _child(msg, fds)   # never returns
    signal.pthread_sigmask(signal.SIG_SETMASK, held)
    for fd in fds:
        os.close(fd)
    pipes[pid] = status_w
    try:
        socket.send_fds(ctl, [str(pid).encode()], [status_r])
    except OSError:
        # the caller is gone since it asked (a run killed while it starts): a normal end,
        # no traceback on the terminal it shared; its closed end is read next, and the
        # server exits as it does when the caller closes it
        pass
    finally:
        os.close(status_r)


#: the resource limits a child takes from its caller (every RLIMIT_ this platform has)
_LIMITS = tuple(getattr(resource, name) for name in dir(resource) if name.startswith("RLIMIT_"))


def _thread_state() -> dict[str, Any]:
    """What a child of the calling thread inherits from it on Linux (scheduling is per
    thread there): its CPU affinity, nice value, scheduling policy, signal mask, and the
    process' resource limits. The
    server took them from whichever thread started it, at that time; a child must have the
    caller's of now, as a child the caller started itself would (a loop thread pinned to
    one CPU or set to a nice value starts children that are so too; the writer of a run
    starts with SIGINT blocked, dobhil/recording/process.py)."""
    state: dict[str, Any] = {"mask": signal.pthread_sigmask(signal.SIG_BLOCK, [])}
    if hasattr(os, "sched_getaffinity"):
        state["affinity"] = os.sched_getaffinity(0)
    if hasattr(os, "getpriority"):
        state["nice"] = os.getpriority(os.PRIO_PROCESS, 0)
    if hasattr(os, "sched_getscheduler"):
        state["policy"] = (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority)
    # and of the process: its resource limits (a file-size limit is what a full disk looks
    # like to a writer, tests/runtime/test_recorder_faults.py)
    state["limits"] = {limit: resource.getrlimit(limit) for limit in _LIMITS}
    return state


def _set_thread_state(state: dict[str, Any]) -> None:
    """:func:`_thread_state` of the caller, as far as this process may take it (a lower nice
    value or SCHED_FIFO need a privilege the caller had and the server may not: the
    server's then, as the OS decides)."""
    signal.pthread_sigmask(signal.SIG_SETMASK, state["mask"])
    for limit, values in state["limits"].items():
        try:
            if resource.getrlimit(limit) != values:
                resource.setrlimit(limit, values)
        except (OSError, ValueError):
            pass
    for apply in (lambda: os.sched_setaffinity(0, state["affinity"]) if "affinity" in state else None,
                  lambda: os.setpriority(os.PRIO_PROCESS, 0, state["nice"]) if "nice" in state else None,
                  lambda: os.sched_setscheduler(0, state["policy"][0], os.sched_param(state["policy"][1]))
                  if "policy" in state else None):
        try:
            apply()
        except OSError:
            pass


def _child(msg: bytes, fds: list[int]) -> None:
    """Run the request in this forked child, then exit the process (an uncaught exception:
    its traceback on standard error and exit code 1, as ``python -c`` does)."""
    code = 1
    try:
        for sig in _CHANGED:   # as a fresh interpreter has them
            signal.signal(sig, signal.SIG_DFL)
        signal.signal(signal.SIGINT, signal.default_int_handler)
        target, args, env, cwd, state = pickle.loads(msg)
        _set_thread_state(state)
        stderr, own = fds[0], fds[1:]
        os.dup2(stderr, 2)
        os.close(stderr)
        os.environ.clear()
        os.environ.update(env)
        try:
            os.chdir(cwd)
        except OSError:
            pass   # gone since: the server's directory, as a fresh child's would fail alike
        module, name = target.split(":")
        function = getattr(importlib.import_module(module), name)
        function(*own, *args)
        code = 0
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    except BaseException:
        import traceback
        traceback.print_exc()
    finally:
        # no atexit handlers: those registered are the server's (as in multiprocessing's
        # forked children, which end with os._exit too); the function's own clean-up is
        # its finally blocks
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
