"""dobhil.forkserver: a child forked from the server is what a child the caller started
itself would be -- its function run with the descriptors and arguments handed to it, the
caller's environment, directory, standard error and thread state of the call, its exit
code reported the ``subprocess`` way -- and the server comes and goes with its caller."""

from __future__ import annotations

import os
import pickle
import resource
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from dobhil import forkserver
from dobhil.forkserver import LOST, ForkServer

pytestmark = pytest.mark.skipif(not forkserver.available(), reason="POSIX fork server")


@pytest.fixture
def server() -> Iterator[ForkServer]:
    srv = ForkServer(["tests.test_forkserver"])
    yield srv
    srv.close()


# -- what the children run (this module, imported by the server) -----------------------------


def report(fd: int, *words: str) -> None:
    """Write what the test asks about this child to ``fd``."""
    answers = {
        "env": os.environ.get("DOBHIL_TEST_FORKSERVER", "-"),
        "cwd": os.getcwd(),
        "sockets": str(sum(os.readlink(f"/proc/self/fd/{fd}").startswith("socket:")
                           for fd in os.listdir("/proc/self/fd")
                           if os.path.exists(f"/proc/self/fd/{fd}"))),
        "pipes": str(sum(os.readlink(f"/proc/self/fd/{fd}").startswith("pipe:")
                         for fd in os.listdir("/proc/self/fd")
                         if int(fd) > 2 and os.path.exists(f"/proc/self/fd/{fd}"))),
        "affinity": ",".join(str(c) for c in sorted(os.sched_getaffinity(0))),
        "nice": str(os.getpriority(os.PRIO_PROCESS, 0)),
        "mask": ",".join(str(int(s)) for s in sorted(signal.pthread_sigmask(signal.SIG_BLOCK, []))),
        "sigint": str(signal.getsignal(signal.SIGINT)),
        "parent": str(os.getppid()),
        "fsize": str(resource.getrlimit(resource.RLIMIT_FSIZE)[0]),
    }
    os.write(fd, "\n".join(answers[w] for w in words).encode())


def fail() -> None:
    raise RuntimeError("this child fails")


def exit_with(code: int) -> None:
    sys.exit(code)


def ignore_sigint(fd: int, *_: object) -> None:
    """What a run's writer does first (dobhil/recording/process.py, ``main``): ignore SIGINT,
    then unblock it; then say so on ``fd``."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    os.write(fd, b"alive")


class SigintOnArrival:
    """An argument whose unpickling, in the child, raises SIGINT there: a Ctrl-C (or a
    ``kill``) that reaches the new pid while it still reads its request, every time."""

    def __reduce__(self) -> tuple[object, tuple[int]]:
        return signal.raise_signal, (int(signal.SIGINT),)


def _ask(server: ForkServer, *words: str) -> list[str]:
    mine, theirs = socket.socketpair()
    with mine, theirs:
        child = server.start("tests.test_forkserver:report", words, [theirs.fileno()])
        assert child.wait(30) == 0
        theirs.close()
        return mine.recv(1 << 16).decode().split("\n")


# -- tests ------------------------------------------------------------------------------------


def test_exit_codes_as_subprocess_gives_them(server: ForkServer, tmp_path: Path) -> None:
    assert server.start("tests.test_forkserver:exit_with", (0,)).wait(30) == 0
    assert server.start("tests.test_forkserver:exit_with", (7,)).wait(30) == 7
    # the traceback goes to the caller's standard error of the call (not the server's,
    # which it had when the server started), as python -c prints it
    saved = os.dup(2)
    with open(tmp_path / "err", "wb") as err:
        os.dup2(err.fileno(), 2)
        try:
            child = server.start("tests.test_forkserver:fail")
        finally:
            os.dup2(saved, 2)
            os.close(saved)
    assert child.wait(30) == 1
    text = (tmp_path / "err").read_text()
    assert "Traceback" in text and "RuntimeError: this child fails" in text
    sleeper = server.start("time:sleep", (30,))
    assert sleeper.poll() is None and sleeper.returncode is None
    with pytest.raises(subprocess.TimeoutExpired):
        sleeper.wait(0.05)
    sleeper.kill()
    assert sleeper.wait(30) == -signal.SIGKILL and sleeper.poll() == -signal.SIGKILL
    sleeper.kill()   # gone already: nothing to do, no error


def test_the_call_s_environment_directory_and_descriptors(server: ForkServer, tmp_path: Path,
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    _ask(server, "env")          # the server runs from here on
    monkeypatch.setenv("DOBHIL_TEST_FORKSERVER", "set after the server started")
    monkeypatch.chdir(tmp_path)
    server.start("time:sleep", (0.5,))   # another child running: its status pipe is open
    env, cwd, sockets, pipes, parent = _ask(server, "env", "cwd", "sockets", "pipes", "parent")
    assert env == "set after the server started"
    assert Path(cwd) == tmp_path
    # the one socket handed over, not the server's control socket nor any of the caller's
    assert sockets == "1"
    assert pipes == "0"     # nor the server's wake-up pipe or another child's status pipe
    assert int(parent) != os.getpid()   # the server's child, not ours


def test_the_calling_thread_s_affinity_nice_value_and_signal_mask() -> None:
    """Started from a thread pinned to one CPU, at nice +4, SIGUSR1 blocked: the child is so
    too; from the main thread the same server's child is not (a server made by the first
    caller keeps that caller's state itself)."""
    if len(os.sched_getaffinity(0)) < 2:
        pytest.skip("one CPU: no affinity to tell apart")
    srv = ForkServer(["tests.test_forkserver"])
    answers: list[list[str]] = []
    cpu = min(os.sched_getaffinity(0))

    def pinned() -> None:
        os.sched_setaffinity(0, {cpu})
        os.setpriority(os.PRIO_PROCESS, 0, os.getpriority(os.PRIO_PROCESS, 0) + 4)
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGUSR1})
        answers.append(_ask(srv, "affinity", "nice", "mask"))

    try:
        thread = threading.Thread(target=pinned)
        thread.start()
        thread.join()
        main = _ask(srv, "affinity", "nice", "mask", "sigint")
    finally:
        srv.close()
    nice = os.getpriority(os.PRIO_PROCESS, 0)
    assert answers[0] == [str(cpu), str(nice + 4), str(int(signal.SIGUSR1))]
    assert main[:3] == [",".join(str(c) for c in sorted(os.sched_getaffinity(0))), str(nice), ""]
    assert main[3] == str(signal.default_int_handler)   # Python's default, as python -c


def test_a_sigint_before_the_child_has_its_caller_s_mask_waits_for_it() -> None:
    """A SIGINT that reaches the child while it reads its request (before it has its caller's
    mask): from a caller with SIGINT blocked, it stays pending and the child that then
    ignores it runs on, as a run's writer must; from a caller without, the child gets it as
    its own KeyboardInterrupt, as a child the caller started itself would (exit 1)."""
    srv = ForkServer(["tests.test_forkserver"])
    outcomes: dict[str, tuple[int | None, bytes]] = {}

    def start(name: str) -> None:
        mine, theirs = socket.socketpair()
        with mine, theirs:
            child = srv.start("tests.test_forkserver:ignore_sigint", (SigintOnArrival(),), [theirs.fileno()])
            code = child.wait(30)
            theirs.close()
            mine.settimeout(5)
            outcomes[name] = (code, mine.recv(64))

    def blocked() -> None:
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        start("blocked")

    try:
        thread = threading.Thread(target=blocked)
        thread.start()
        thread.join()
        start("unblocked")
    finally:
        srv.close()
    assert outcomes["blocked"] == (0, b"alive")
    assert outcomes["unblocked"] == (1, b"")


def test_the_call_s_resource_limits(server: ForkServer) -> None:
    """A file-size limit set after the server started (what a full disk looks like to a
    writer) is the child's, and only while it is the caller's."""
    assert _ask(server, "fsize") == [str(resource.getrlimit(resource.RLIMIT_FSIZE)[0])]
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (150_000, hard))
    try:
        assert _ask(server, "fsize") == ["150000"]
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
    assert _ask(server, "fsize") == [str(soft)]


def test_a_killed_server_loses_the_status_and_the_next_start_makes_a_new_one(
        server: ForkServer) -> None:
    sleeper = server.start("time:sleep", (0.5,))
    proc = server._proc
    assert proc is not None
    proc.kill()
    proc.wait()
    assert sleeper.wait(30) == LOST      # it ended; how, only the dead server knew
    assert server.start("tests.test_forkserver:exit_with", (3,)).wait(30) == 3
    assert server._proc is not None and server._proc.pid != proc.pid


def test_the_server_ends_with_its_caller(server: ForkServer) -> None:
    server.start("tests.test_forkserver:exit_with", (0,)).wait(30)
    proc = server._proc
    assert proc is not None and proc.poll() is None
    running = server.start("time:sleep", (0.3,))
    server.close()          # our end closed: the server exits; its running child goes on
    assert proc.poll() is not None
    deadline = time.monotonic() + 30
    while running.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    assert running.returncode == LOST


def _cpu_of(pid: int) -> float:
    """CPU seconds of a live process and of its children it has reaped (proc(5): utime,
    stime, cutime, cstime, the 14th to 17th fields of /proc/PID/stat)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return sum(int(f) for f in fields[11:15]) / os.sysconf("SC_CLK_TCK")


#: what the server of this cost test imports, and the one interpreter it is weighed against:
#: the emulated drive's code, as the server that forks emulated drives has it
#: (dobhil/emulator/process.py), and this module for the children's function
COST_PRELOAD = ("dobhil.emulator.process", "tests.test_forkserver")


def test_the_fork_server_s_children_cost_a_fork_not_an_interpreter() -> None:
    """Counted in CPU, not timed: a child costs less than a tenth of the CPU of one
    interpreter importing what the server imported -- the point of the server. The server's
    own start (an interpreter and the same imports) is read from /proc before the children
    and taken out: left in, it made the bound one interpreter's cost against another's, which
    load alone could tip. The imports are the emulated drive's, as in use: this module's alone
    (pytest and dobhil.forkserver) cost 0.12 s of CPU, and 20 forks under a CPU-bound process
    0.15 s, too close to weigh in 10 ms clock ticks."""
    server = ForkServer(list(COST_PRELOAD))
    try:
        _children_against_one_interpreter(server)
    finally:
        server.close()


def _children_against_one_interpreter(server: ForkServer) -> None:
    server.start("tests.test_forkserver:exit_with", (0,)).wait(30)
    proc = server._proc
    assert proc is not None
    started = _cpu_of(proc.pid)
    before = os.times()
    for _ in range(20):
        assert server.start("tests.test_forkserver:exit_with", (0,)).wait(30) == 0
    server.close()
    after = os.times()
    # the server, reaped at close, brings its own CPU and that of everything it forked
    children = (after.children_user + after.children_system
                - before.children_user - before.children_system) - started
    fresh = subprocess.run([sys.executable, "-c", "; ".join(f"import {name}" for name in COST_PRELOAD)],
                           cwd=Path(__file__).resolve().parents[1], check=True)
    assert fresh.returncode == 0
    end = os.times()
    one_interpreter = end.children_user + end.children_system - after.children_user - after.children_system
    # a child a tenth of an interpreter at most (measured idle: 20 children 0.12-0.14 s of CPU,
    # one interpreter 0.21-0.23 s, in 10 ms clock ticks)
    assert children / 20 < one_interpreter / 10, (children, one_interpreter)


def test_a_server_started_with_sigchld_blocked_still_reports_its_children() -> None:
    """The first caller's mask is the server's at its start (a writer starts with SIGINT
    and SIGTERM blocked); one with SIGCHLD blocked would leave every exit unreported."""
    srv = ForkServer([])
    codes: list[int] = []

    def blocked() -> None:
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGCHLD, signal.SIGINT})
        codes.append(srv.start("sys:exit", (5,)).wait(30))

    try:
        thread = threading.Thread(target=blocked)
        thread.start()
        thread.join()
    finally:
        srv.close()
    assert codes == [5]


def test_a_ctrl_c_while_closing_kills_the_server_without_a_traceback(server: ForkServer,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """close() runs at exit; a second Ctrl-C after a run's end lands in its wait for the
    server: the server is killed, and the interrupt is not raised into atexit (whose
    traceback would follow the run's last line)."""
    server.start("tests.test_forkserver:exit_with", (0,)).wait(30)
    proc = server._proc
    assert proc is not None and proc.poll() is None

    def interrupted(timeout: float | None = None) -> int:
        monkeypatch.undo()   # the kill's own wait is the real one
        raise KeyboardInterrupt

    monkeypatch.setattr(proc, "wait", interrupted)
    server.close()
    assert proc.wait(30) is not None and proc.returncode is not None
    assert server.pid is None


def test_a_caller_gone_before_the_answer_ends_the_server_quietly(tmp_path: Path) -> None:
    """A run killed (``kill -9``) after asking for a child and before the answer: the server
    forks the child, cannot answer, and exits 0 with nothing on the standard error it shares
    with the run's terminal (not a BrokenPipeError traceback). The request is queued and the
    caller's end closed before the server starts, so the answer always finds the caller gone."""
    host, end = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    with open(tmp_path / "stderr", "wb") as err:
        request = ("os:getpid", (), dict(os.environ), os.getcwd(), forkserver._thread_state())
        socket.send_fds(host, [pickle.dumps(request)], [err.fileno()])
        host.close()
        with end:
            proc = subprocess.Popen([sys.executable, "-c", forkserver._BOOT, forkserver.ROOT, str(end.fileno())],
                                    pass_fds=(end.fileno(),), stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                    stderr=err)
        assert proc.wait(30) == 0
    assert (tmp_path / "stderr").read_text() == ""
