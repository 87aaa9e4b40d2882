"""Helpers of the kernel-guest tests: configs a slow guest can hold, dobhil and can-utils as
processes, candump's log read back.

Nothing here asserts a wall-clock figure: time-outs are bounds for a guest under software
emulation on a loaded machine, and every figure a test checks comes from the run itself.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

REPO = Path(__file__).resolve().parents[2]
DRIVERS = REPO / "drivers"
CONFIGS = REPO / "configs"
ACCEL = os.environ.get("DOBHIL_CANVM_ACCEL", "native")
#: under TCG the guest's Python is 30-50x slower than the host's: 10 ms periods, 40 rad/s observers
#: (sampled loop, delay 0 / 1 sample: gain margins 13.3 / 7.6 dB); elsewhere the shipped 1 ms
SLOW = ACCEL == "tcg"
PERIOD = 10e-3 if SLOW else 1e-3
BANDWIDTH = 40.0 if SLOW else None
#: candump's own options in every capture: an 8 MiB socket receive buffer (SO_RCVBUFFORCE, root
#: in the guest) instead of the kernel's ~200 KB default, which holds ~250 frames -- a quarter
#: of a second of a 1 kHz CiA 402 bus; candump descheduled longer than that on a loaded TCG
#: guest loses frames, and a frame the run logged then has no twin in the capture. ``-d``
#: writes a DROPCOUNT line into the capture if it still happens (see :func:`candump_drops`).
CANDUMP_OPTIONS = ("-r", str(8 << 20), "-d")
#: bound for a process to print its first line or finish a short run under TCG (Python starts
#: in ~8 s there): a bound, not a measurement
START_TIMEOUT = 120.0
#: bound for ``dobhil report`` of a run's log under TCG: it draws five figures with matplotlib,
#: which takes 60-130 s there (a bound for a hang, not a measurement)
REPORT_TIMEOUT = 4 * START_TIMEOUT
#: nice decrement of ``dobhil emulate`` in the guest (root there): the emulated drive stands for
#: a drive with a CPU of its own, but the guest's two vCPUs are shared by the loop, its writer,
#: candump and pytest; at nice 0 (its thread at +3) it was seen answering one SYNC in four for
#: half a second at a run's start under TCG, which the loop's rate watch rightly stops on
EMULATOR_NICE = 8

#: the demo config of each protocol and what the emulator prints once it listens
DEMOS = {"odrive": "demo.yaml", "cia402": "cia402-demo.yaml", "mit": "mit-demo.yaml"}
PROFILES = {"odrive": "odrive-0.6", "cia402": "cia402-emulated", "mit": "ak80-9"}


def dobhil_command() -> list[str]:
    """The ``dobhil`` console script of this environment (the README's workflow), else -m."""
    script = Path(sys.executable).parent / "dobhil"
    return [str(script)] if script.is_file() else [sys.executable, "-m", "dobhil"]


def profile_copy(tmp_path: Path, name: str, **changes: Any) -> Path:
    """The shipped profile ``name`` with ``changes``, written to ``tmp_path`` (an EDS path
    made absolute, since it is relative to the profile's folder)."""
    data = yaml.safe_load((DRIVERS / f"{name}.yaml").read_text(encoding="utf-8"))
    section = data.get("cia402")
    if isinstance(section, dict) and "eds" in section:
        section["eds"] = str((DRIVERS / section["eds"]).resolve())
    for key, value in changes.items():
        if "." in key:
            outer, inner = key.split(".", 1)
            data.setdefault(outer, {})[inner] = value
        else:
            data[key] = value
    path = tmp_path / f"{name}-guest-{len(list(tmp_path.glob('*-guest-*.yaml')))}.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return path


def guest_overlay(tmp_path: Path, protocol: str, extra: dict[str, Any] | None = None,
                  profile: dict[str, Any] | None = None, profile_name: str | None = None) -> Path:
    """A ``--set-file`` overlay for ``configs/<protocol demo>``: the guest's period, a profile
    (the demo's, or ``profile_name``) whose rates match it, and time-outs that a guest under
    software emulation can keep."""
    changes: dict[str, Any] = {"enable_timeout": 5.0}
    if protocol != "mit":
        changes["feedback_period"] = PERIOD
    if protocol == "odrive":
        changes["watchdog_timeout"] = 0.25
    if protocol == "mit":
        changes["enable_timeout"] = 2.0
    changes.update(profile or {})
    values: dict[str, Any] = {
        "drive.profile": str(profile_copy(tmp_path, profile_name or PROFILES[protocol], **changes)),
        "loop.period": PERIOD,
        "loop.feedback_timeout": 0.1 if SLOW else 0.02,
    }
    if BANDWIDTH is not None:
        values["design.dob_bandwidth"] = BANDWIDTH
        values["design.rtob_bandwidth"] = BANDWIDTH
    values.update(extra or {})
    path = tmp_path / f"overlay-{protocol}-{len(list(tmp_path.glob('overlay-*.yaml')))}.yaml"
    path.write_text(yaml.safe_dump(values), encoding="utf-8")
    return path


@dataclass
class Proc:
    """A started process, its output in one file."""

    name: str
    args: list[str]
    popen: subprocess.Popen[bytes]
    out: Path
    returncode: int | None = None

    def text(self) -> str:
        return self.out.read_text(errors="replace")

    def wait_for(self, needle: str | re.Pattern[str], timeout: float = START_TIMEOUT) -> str:
        """Until the output contains ``needle``; fails if the process ends first."""
        deadline = time.monotonic() + timeout
        while True:
            text = self.text()
            found = needle.search(text) if isinstance(needle, re.Pattern) else needle in text
            if found:
                return text
            if self.popen.poll() is not None:
                raise AssertionError(f"{self.name} exited {self.popen.returncode} before printing {needle!r}:\n{text}")
            if time.monotonic() > deadline:
                raise AssertionError(f"{self.name} did not print {needle!r} within {timeout:.0f} s:\n{text}")
            time.sleep(0.05)

    def wait(self, timeout: float = START_TIMEOUT) -> int:
        try:
            self.returncode = self.popen.wait(timeout)
        except subprocess.TimeoutExpired:
            raise AssertionError(f"{self.name} did not end within {timeout:.0f} s:\n{self.text()}") from None
        return self.returncode

    def signal(self, sig: int) -> None:
        if self.popen.poll() is None:
            os.kill(self.popen.pid, sig)

    def stop(self) -> None:
        if self.popen.poll() is None:
            self.popen.send_signal(signal.SIGINT)
            try:
                self.popen.wait(15)
            except subprocess.TimeoutExpired:
                self.popen.kill()
                self.popen.wait()
        self.returncode = self.popen.returncode


@dataclass
class Dobhil:
    """Starts dobhil commands and can-utils in ``tmp_path``."""

    tmp_path: Path
    procs: list[Proc] = field(default_factory=list)

    def start(self, name: str, args: list[str], program: list[str] | None = None, nice: int = 0) -> Proc:
        """``nice``: added to the process' nice value before it runs (negative: root only)."""
        out = self.tmp_path / f"{name}.out"
        with out.open("wb") as f:
            popen = subprocess.Popen([*(program if program is not None else dobhil_command()), *args],
                                     stdout=f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                     cwd=self.tmp_path, preexec_fn=(lambda: os.nice(nice)) if nice else None)
        proc = Proc(name, args, popen, out)
        self.procs.append(proc)
        return proc

    def run(self, name: str, args: list[str], timeout: float = START_TIMEOUT,
            program: list[str] | None = None) -> Proc:
        proc = self.start(name, args, program)
        proc.wait(timeout)
        return proc

    def emulate(self, config: str | Path, bus: str, overlay: Path, *more: str, protocol: str = "odrive") -> Proc:
        """``dobhil emulate CONFIG --bus socketcan:IFACE`` until it says it listens; above the
        run's priority where this process may raise it (:data:`EMULATOR_NICE`)."""
        proc = self.start(f"emulate-{protocol}-{len(self.procs)}",
                          ["emulate", str(config), "--bus", f"socketcan:{bus}", "--set-file", str(overlay), *more],
                          nice=-EMULATOR_NICE if os.geteuid() == 0 else 0)
        proc.wait_for(f"emulating {protocol}")
        return proc

    def stop_all(self) -> None:
        for proc in self.procs:
            proc.stop()


def summary_json(proc: Proc) -> dict[str, Any]:
    """The JSON object ``dobhil run --summary-json`` printed (the last line that parses)."""
    for line in reversed(proc.text().splitlines()):
        line = line.strip()
        if line.startswith("{"):
            try:
                return dict(json.loads(line))
            except ValueError:
                continue
    raise AssertionError(f"no JSON summary in the output of {proc.name}:\n{proc.text()}")


#: a candump log line (``candump -L``): (seconds) interface id#data, FD as id##flags data
CANDUMP_LINE = re.compile(r"^\((\d+\.\d+)\) (\S+) ([0-9A-Fa-f]+)(##?)([0-9A-Fa-f.R]*)$")


@dataclass(frozen=True)
class Dumped:
    stamp: float
    iface: str
    arbitration_id: int
    data: bytes
    is_fd: bool


def read_candump(path: Path) -> list[Dumped]:
    """candump's log format: kernel receive stamps (SO_TIMESTAMP), classic and FD frames."""
    frames = []
    for line in path.read_text(errors="replace").splitlines():
        m = CANDUMP_LINE.match(line.strip())
        if not m:
            continue
        stamp, iface, ident, sep, payload = m.groups()
        is_fd = sep == "##"
        hex_data = payload[1:] if is_fd else payload
        if hex_data.startswith("R"):
            hex_data = ""
        frames.append(Dumped(float(stamp), iface, int(ident, 16), bytes.fromhex(hex_data), is_fd))
    return frames


def candump_drops(path: Path) -> list[str]:
    """candump's DROPCOUNT lines in its capture (``-d``): frames the kernel dropped from its
    socket's queue, which the capture therefore lacks."""
    return [line for line in path.read_text(errors="replace").splitlines() if "DROPCOUNT" in line]


def have(program: str) -> bool:
    return shutil.which(program) is not None
