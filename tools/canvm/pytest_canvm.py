"""pytest plugin: the tests of ``tests/socketcan/`` run inside the kernel guest (canvm.py), and
each is reported as a test of the host's run.

``python -m pytest -n 2`` collects those tests on the host like any other, then:

1. the process that schedules the run (pytest-xdist's controller, or the only process) writes
   their ids to a run folder and starts ``canvm.py pytest`` in the background, which boots the
   guest and runs exactly those ids there with this plugin in its guest role;
2. in the guest, every test report is appended to ``results.jsonl`` in the run folder (the
   guest's only writable share), as it happens;
3. on the host each of those tests is a :class:`GuestItem` that waits for its own reports and
   passes, fails with the guest's traceback and output, or skips with the guest's reason. They
   are put first, and every other test waits until the guest has finished: the guest under
   software emulation takes the machine's cores, and the timing tests on either side must not
   share them (the guest's time is reported apart);
4. the terminal summary gets one ``canvm:`` line: the counts, the boot time and which
   accelerator ran (KVM, or TCG and why not KVM).

Where the guest cannot be booted (no qemu, no kernel, no busybox-static), the tests skip with
the one line naming what to install; ``.ci/run`` fails on that skip. ``DOBHIL_CANVM_GUEST=1``
runs the tests on this machine's own kernel instead (a Linux box with vcan, as root).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

HERE = Path(__file__).resolve().parent
CANVM = HERE / "canvm.py"
#: the folder (relative to the rootdir) whose tests run in the guest
GUEST_TESTS = "tests/socketcan/"
POLL_S = 0.2
#: seconds the guest has to power off after its last test (pytest's own end, then poweroff)
SHUTDOWN_S = 120.0


def in_guest() -> bool:
    return os.environ.get("DOBHIL_CANVM_GUEST") == "1"


def _run_dir(uid: str) -> Path:
    return Path(tempfile.gettempdir()) / f"dobhil-canvm-{uid}"


def _read_results(run_dir: Path) -> list[dict[str, Any]]:
    try:
        text = (run_dir / "results.jsonl").read_text()
    except OSError:
        return []
    out = []
    for line in text.splitlines():
        try:
            out.append(json.loads(line))
        except ValueError:
            pass  # a line the guest is still writing
    return out


def _read_status(run_dir: Path) -> dict[str, Any] | None:
    try:
        status: dict[str, Any] = json.loads((run_dir / "status.json").read_text())
        return status
    except (OSError, ValueError):
        return None


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _console_tail(run_dir: Path, lines: int = 30) -> str:
    try:
        text = (run_dir / "console.log").read_text(errors="replace").replace("\r", "")
    except OSError:
        return "(no console output)"
    return "\n".join(text.splitlines()[-lines:])


class GuestFailure(Exception):
    """A test that failed in the guest; the message is the guest's own report."""


class GuestItem(pytest.Item):
    """The host's stand-in for one test that runs in the guest."""

    def __init__(self, *, plugin: CanvmPlugin, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.plugin = plugin
        # the wait for the guest is bounded by the guest's own time-out, not pytest-timeout's
        self.add_marker(pytest.mark.timeout(0))

    def runtest(self) -> None:
        reports = self.plugin.wait_for(self.nodeid)
        failed = [r for r in reports if r["outcome"] == "failed"]
        if failed:
            parts = []
            for r in failed:
                parts.append(f"--- in the guest ({r['when']}, {r.get('accel', '?')}) ---\n{r.get('longrepr') or ''}")
                parts.extend(f"--- {name} ---\n{content}" for name, content in r.get("sections", []))
            raise GuestFailure("\n".join(parts))
        for r in reports:
            if r["outcome"] == "skipped":
                if r.get("wasxfail") is not None:
                    pytest.xfail(f"in the guest: {r['wasxfail']}")
                pytest.skip(f"in the guest: {r.get('longrepr') or ''}")

    def repr_failure(self, excinfo: pytest.ExceptionInfo[BaseException], style: Any = None) -> str:
        if isinstance(excinfo.value, GuestFailure):
            return str(excinfo.value)
        return str(super().repr_failure(excinfo, style))

    def reportinfo(self) -> tuple[Path, int | None, str]:
        return self.path, None, f"{self.name} (in the kernel guest)"


class CanvmPlugin:
    """Registered by tests/conftest.py in every pytest process; its role follows from where it runs."""

    def __init__(self, config: pytest.Config) -> None:
        self.config = config
        self.worker = hasattr(config, "workerinput")
        self.uid = os.environ.get("PYTEST_XDIST_TESTRUNUID") if self.worker else None
        self.started: subprocess.Popen[bytes] | None = None
        self.run_dir: Path | None = _run_dir(self.uid) if self.uid else None
        self.guest_ids: list[str] = []
        self._results_file: Any = None
        self._keep = False
        self._guest_done = False

    # -- in the guest: stream every report to the host --------------------------------------

    def pytest_runtest_logreport(self, report: pytest.TestReport) -> None:
        path = os.environ.get("DOBHIL_CANVM_RESULTS")
        if not in_guest() or not path:
            return
        if self._results_file is None:
            self._results_file = open(path, "a", encoding="utf-8")
        longrepr = report.longrepr
        if report.skipped and isinstance(longrepr, tuple):
            text = str(longrepr[2])
        else:
            text = str(longrepr) if longrepr is not None else ""
        record = {"nodeid": report.nodeid, "when": report.when, "outcome": report.outcome,
                  "duration": report.duration, "longrepr": text,
                  "accel": os.environ.get("DOBHIL_CANVM_ACCEL", "native"),
                  "wasxfail": getattr(report, "wasxfail", None),
                  "sections": [list(s) for s in report.sections] if report.failed else []}
        self._results_file.write(json.dumps(record) + "\n")
        self._results_file.flush()

    # -- on the host: stand-ins, first in the run ---------------------------------------------

    @pytest.hookimpl(trylast=True)
    def pytest_collection_modifyitems(self, session: pytest.Session, config: pytest.Config,
                                      items: list[pytest.Item]) -> None:
        if in_guest():
            return
        guest, host = [], []
        for item in items:
            if item.nodeid.startswith(GUEST_TESTS) and item.parent is not None:
                # selection (-m, -k) is done by now; the guest applies the test's own marks
                guest.append(GuestItem.from_parent(item.parent, name=item.name, plugin=self))
            else:
                host.append(item)
        items[:] = guest + host

    @pytest.hookimpl(optionalhook=True)
    def pytest_xdist_node_collection_finished(self, node: Any, ids: list[str]) -> None:
        """xdist's controller: every worker collected the same ids; start the guest once."""
        if self.started is None and self.run_dir is None:
            self.uid = node.workerinput["testrunuid"]
            self._start([i for i in ids if i.startswith(GUEST_TESTS)])

    def pytest_collection_finish(self, session: pytest.Session) -> None:
        """Without xdist (or -n 0) this process is both scheduler and runner."""
        if self.worker or in_guest() or self.run_dir is not None:
            return
        self.uid = uuid.uuid4().hex
        self._start([i.nodeid for i in session.items if isinstance(i, GuestItem)])

    def _start(self, ids: list[str]) -> None:
        assert self.uid is not None
        self.run_dir = _run_dir(self.uid)
        self.guest_ids = ids
        if not ids or self.config.option.collectonly:
            return
        self.run_dir.mkdir(parents=True, exist_ok=True)
        (self.run_dir / "ids.txt").write_text("\n".join(ids) + "\n")
        timeout = os.environ.get("DOBHIL_CANVM_TIMEOUT", "3600")
        log = open(self.run_dir / "canvm.log", "wb")
        with log:
            self.started = subprocess.Popen(
                [sys.executable, str(CANVM), "pytest", "--run-dir", str(self.run_dir),
                 "--cwd", str(self.config.rootpath), "--timeout", timeout],
                stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        (self.run_dir / "pid").write_text(str(self.started.pid))

    @pytest.hookimpl(hookwrapper=True, tryfirst=True)
    def pytest_runtest_protocol(self, item: pytest.Item) -> Iterator[None]:
        """A host test starts once the guest is done (see the module's docstring). Outside the
        test's own phases: the wait is neither its duration nor within its pytest-timeout."""
        self._wait_for_guest(item)
        yield

    def _wait_for_guest(self, item: pytest.Item) -> None:
        run_dir = self.run_dir
        if in_guest() or isinstance(item, GuestItem) or run_dir is None or self._guest_done:
            return
        if not (run_dir / "ids.txt").is_file():
            self._guest_done = True   # no guest in this session
            return
        pid_file = run_dir / "pid"
        while _read_status(run_dir) is None:
            if pid_file.is_file() and not _alive(int(pid_file.read_text())):
                break
            time.sleep(POLL_S)
        self._guest_done = True

    def wait_for(self, nodeid: str) -> list[dict[str, Any]]:
        """This test's reports from the guest, once its teardown is in; fails the test when the
        guest ended without running it."""
        run_dir = self.run_dir
        if run_dir is None or not (run_dir / "ids.txt").is_file():
            pytest.fail("the kernel guest was not started (is tools/canvm/pytest_canvm.py registered by "
                        "tests/conftest.py?)", pytrace=False)
        pid_file = run_dir / "pid"
        while True:
            mine = [r for r in _read_results(run_dir) if r["nodeid"] == nodeid]
            if any(r["when"] == "teardown" for r in mine):
                return mine
            status = _read_status(run_dir)
            if status is not None:
                if "missing" in status:
                    pytest.skip(f"canvm: {status['missing']}")
                mine = [r for r in _read_results(run_dir) if r["nodeid"] == nodeid]
                if any(r["when"] == "teardown" for r in mine):
                    return mine
                why = (status.get("error") or status.get("reason")
                       or f"the guest's pytest exited with {status.get('exit_status')}")
                pytest.fail(f"did not run to its end in the kernel guest: {why}\nconsole:\n{_console_tail(run_dir)}",
                            pytrace=False)
            if pid_file.is_file() and not _alive(int(pid_file.read_text())) and _read_status(run_dir) is None:
                pytest.fail(f"the kernel guest's harness died (log: {run_dir / 'canvm.log'})\n"
                            f"{_console_tail(run_dir)}", pytrace=False)
            time.sleep(POLL_S)

    # -- the summary, and nothing left running -------------------------------------------------

    def _finish(self) -> dict[str, Any] | None:
        proc = self.started
        if proc is None or self.run_dir is None:
            return None
        done = {r["nodeid"] for r in _read_results(self.run_dir) if r["when"] == "teardown"}
        if proc.poll() is None and done >= set(self.guest_ids):
            try:  # every test is in: the guest is powering off
                proc.wait(SHUTDOWN_S)
            except subprocess.TimeoutExpired:
                pass
        if proc.poll() is None:  # the run ended early (-x, Ctrl-C) or hangs: the guest goes with it
            try:
                os.killpg(proc.pid, signal.SIGTERM)
                proc.wait(10)
            except (ProcessLookupError, subprocess.TimeoutExpired):
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
        return _read_status(self.run_dir)

    def pytest_terminal_summary(self, terminalreporter: Any) -> None:
        if self.started is None or self.run_dir is None:
            return
        status = self._finish() or {}
        results = _read_results(self.run_dir)
        outcome: dict[str, str] = {}
        for r in results:
            if r["outcome"] == "failed" or r["nodeid"] not in outcome or r["when"] == "call":
                if outcome.get(r["nodeid"]) != "failed":
                    outcome[r["nodeid"]] = r["outcome"]
        counts = {k: sum(1 for v in outcome.values() if v == k) for k in ("passed", "failed", "skipped")}
        not_run = len(set(self.guest_ids) - set(outcome))
        if "missing" in status:
            line = f"canvm: {len(self.guest_ids)} guest tests not run: {status['missing']}"
        else:
            boot = status.get("boot_s")
            boot_text = f"booted in {boot:.1f} s" if isinstance(boot, (int, float)) else "never became ready"
            kvm = f"; kvm: {status['kvm_note']}" if status.get("kvm_note") else ""
            line = (f"canvm: {len(self.guest_ids)} guest tests: {counts['passed']} passed, {counts['failed']} failed, "
                    f"{counts['skipped']} skipped, {not_run} not run; guest {boot_text} "
                    f"({status.get('accel', '?')}{kvm}), ran {status.get('wall_s', 0):.0f} s")
            if status.get("error") or status.get("reason"):
                line += f"; {status.get('error') or status.get('reason')}"
        terminalreporter.write_line(line)

    def pytest_sessionfinish(self, session: pytest.Session) -> None:
        self._finish()
        self._keep = os.environ.get("DOBHIL_CANVM_KEEP") == "1" or bool(session.testsfailed)

    def pytest_unconfigure(self, config: pytest.Config) -> None:
        """After the summary has read the run folder."""
        self._finish()
        if self.run_dir is not None and self.started is not None and self.run_dir.is_dir():
            if self._keep:
                return  # the console and results stay for a look; the path is in each failure
            for child in self.run_dir.iterdir():
                child.unlink()
            self.run_dir.rmdir()

