#!/usr/bin/env python3
"""A real Linux CAN stack for tests: Debian's kernel booted under qemu, the host's files inside.

The kernel this project's CI runs on may have no ``AF_CAN`` (a container's or a micro-VM's
kernel), so SocketCAN -- the interface most users run dobhil on -- could only be imitated. This
harness boots the machine's installed Debian kernel (``linux-image-amd64`` ships ``can``,
``can-raw``, ``can-bcm``, ``can-gw``, ``vcan``, ``vxcan`` and ``sch_netem`` as modules) with a
busybox initramfs built here, and runs one command inside it:

- the host's root filesystem is mounted read-only over virtio-9p, with a tmpfs overlay on top,
  so the checkout, its virtual environment and every host tool (``ip``, ``tc``, can-utils) are
  at the same paths and the guest may write anywhere without touching the host;
- the job's folder on the host is the only writable share (``/run/canvm`` in the guest): the
  command's exit status and whatever the caller asks for (the guest tests' results) land there;
- KVM is used where it boots and software emulation (TCG) otherwise; which one ran is printed.
  On some nested-virtualisation hosts the kernel stalls under KVM right after decompression (no
  console output at all), so KVM gets :data:`KVM_PROBE_S` seconds to show the guest's first line.

Nothing here needs a network, a disk image or root inside the host beyond reading the kernel
(Debian installs ``/boot/vmlinuz-*`` root-only). Why by hand: no maintained Python library builds
a Linux initramfs or drives qemu for a one-shot command; ``cpio``'s newc format is 30 lines.

Command line (from a checkout)::

    python tools/canvm/canvm.py check              # what was found, or the one thing to install
    python tools/canvm/canvm.py run -- ip -details link show
    python tools/canvm/canvm.py run -- python -m pytest -m socketcan tests/socketcan

``pytest`` runs the tests of ``tests/socketcan`` in the guest by itself (tools/canvm/pytest_canvm.py).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import fcntl
import json
import os
import re
import shlex
import shutil
import signal
import stat
import struct
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]

#: Debian packages the guest is made of, by what they provide (tools/canvm/install.sh installs them)
PACKAGES = {
    "qemu": "qemu-system-x86",
    "kernel": "linux-image-amd64",
    "busybox": "busybox-static",
    "can-utils": "can-utils",
    "iproute2": "iproute2",
}
INSTALL_HINT = "sudo tools/canvm/install.sh"

#: kernel modules loaded at boot, with their dependencies: the 9p share and the overlay, the CAN
#: stack, and the queueing disciplines the fault tests put on an interface
MODULES = (
    "virtio_pci", "9pnet_virtio", "9p", "overlay",
    "can", "can_raw", "can_bcm", "can_gw", "vcan", "vxcan",
    "sch_netem", "sch_tbf", "sch_prio", "cls_basic", "em_canid",
)
#: host programs the guest tests use (found on the host: the guest sees the same files)
PROGRAMS = {"ip": "iproute2", "tc": "iproute2", "candump": "can-utils", "cansend": "can-utils",
            "cangen": "can-utils"}

#: seconds KVM has to show the guest's first console line before TCG is used instead
KVM_PROBE_S = 10.0
#: guest memory (MiB) and processors; the overlay's tmpfs may use 75 % of the memory
MEMORY_MB = 2048
CPUS = 2
#: the processor software emulation offers: qemu's "max" without AVX and AVX2. Why: qemu 7.2
#: (Debian 12) emulates AVX2 wrongly -- in the guest, numpy 2.4's AVX2 argsort returned
#: unsorted indices in every one of 4 fresh processes and crashed a run with SIGSEGV, while
#: the same code with numpy's AVX2 paths off (NPY_DISABLE_CPU_FEATURES=X86_V3) was right in 4
#: of 4. Without the flags every program (numpy, numba's generated code, glibc) takes its
#: SSE paths, which emulate correctly.
TCG_CPU = "max,avx=off,avx2=off"
#: the line init.sh prints once the guest's root is ready
READY = re.compile(r"canvm: guest ready after ([0-9.]+) s")
FIRST_LINE = "canvm: kernel "


class Missing(Exception):
    """A requirement of the guest is not on this machine; the message says what to install."""


@dataclasses.dataclass(frozen=True)
class Requirements:
    qemu: Path
    kernel: Path
    kernel_version: str
    modules_dir: Path
    busybox: Path
    #: the module files to load, in dependency order, relative to ``modules_dir``
    modules: tuple[str, ...]
    kvm: bool

    def describe(self) -> str:
        return (f"kernel {self.kernel_version} ({self.kernel}), {self.qemu}, busybox {self.busybox}, "
                f"{len(self.modules)} modules, /dev/kvm {'usable' if self.kvm else 'not usable'}")


# ----------------------------------------------------------------------------------------------
# finding what the guest is made of


def _is_static_elf(path: Path) -> bool:
    """True for an ELF executable without a program interpreter (PT_INTERP): it runs alone in
    an initramfs that has no shared libraries."""
    with open(path, "rb") as f:
        head = f.read(64)
        if head[:4] != b"\x7fELF" or head[4] != 2:  # 64-bit ELF only (x86-64 guest)
            return False
        endian = "<" if head[5] == 1 else ">"
        phoff, = struct.unpack_from(endian + "Q", head, 32)
        phentsize, phnum = struct.unpack_from(endian + "HH", head, 54)
        f.seek(phoff)
        table = f.read(phentsize * phnum)
    return all(struct.unpack_from(endian + "I", table, i * phentsize)[0] != 3 for i in range(phnum))


def _module_key(name: str) -> str:
    """The kernel treats '-' and '_' in module names alike."""
    return name.replace("-", "_")


def _module_name(path: str) -> str:
    base = path.rsplit("/", 1)[-1]
    return _module_key(base.split(".ko", 1)[0])


def resolve_modules(modules_dir: Path, wanted: Iterable[str]) -> tuple[str, ...]:
    """The module files to load for ``wanted``, each after its dependencies (``modules.dep``, the
    file depmod writes); built-in modules (``modules.builtin``) need nothing."""
    dep_file = modules_dir / "modules.dep"
    if not dep_file.is_file():
        raise Missing(f"{dep_file} not found: the kernel's modules are not installed "
                      f"(install Debian's {PACKAGES['kernel']})")
    deps: dict[str, tuple[str, list[str]]] = {}
    for line in dep_file.read_text().splitlines():
        if ":" not in line:
            continue
        path, rest = line.split(":", 1)
        deps[_module_name(path)] = (path, rest.split())
    builtin_file = modules_dir / "modules.builtin"
    builtin = {_module_name(p) for p in builtin_file.read_text().split()} if builtin_file.is_file() else set()
    order: list[str] = []

    def visit(path: str) -> None:
        for dep in deps.get(_module_name(path), (path, []))[1]:
            visit(dep)
        if path not in order:
            order.append(path)

    for name in wanted:
        key = _module_key(name)
        if key in builtin:
            continue
        if key not in deps:
            raise Missing(f"kernel {modules_dir.name} has no module {name} (Debian's "
                          f"{PACKAGES['kernel']} has it; or set DOBHIL_CANVM_KERNEL to a kernel that does)")
        visit(deps[key][0])
    for path in order:
        if not path.endswith(".ko"):
            raise Missing(f"module {path} is compressed; this harness loads plain .ko files "
                          f"(Debian 12's {PACKAGES['kernel']})")
    return tuple(order)


def _kernels() -> list[tuple[str, Path]]:
    """Installed kernels with modules, newest first: (version, image)."""
    found = []
    for image in Path("/boot").glob("vmlinuz-*"):
        version = image.name[len("vmlinuz-"):]
        if (Path("/lib/modules") / version / "modules.dep").is_file():
            found.append((version, image))

    def key(item: tuple[str, Path]) -> list[int | str]:
        return [int(p) if p.isdigit() else p for p in re.split(r"[.-]", item[0])]

    return sorted(found, key=key, reverse=True)


def find_requirements(modules: Sequence[str] = MODULES) -> Requirements:
    """Everything the guest needs, or :class:`Missing` naming the first thing to install."""
    if sys.platform != "linux" or os.uname().machine != "x86_64":
        raise Missing(f"the kernel guest needs an x86-64 Linux host (this is {sys.platform} "
                      f"{os.uname().machine})")
    qemu = shutil.which("qemu-system-x86_64")
    if qemu is None:
        raise Missing(f"qemu-system-x86_64 not found: install Debian's {PACKAGES['qemu']} ({INSTALL_HINT})")
    chosen = os.environ.get("DOBHIL_CANVM_KERNEL")
    if chosen:
        image = Path(chosen)
        version = image.name[len("vmlinuz-"):] if image.name.startswith("vmlinuz-") else ""
        if not image.is_file() or not version:
            raise Missing(f"DOBHIL_CANVM_KERNEL={chosen}: expected a /boot/vmlinuz-VERSION file")
    else:
        kernels = _kernels()
        if not kernels:
            raise Missing(f"no kernel with modules in /boot: install Debian's {PACKAGES['kernel']} ({INSTALL_HINT})")
        version, image = kernels[0]
    if not os.access(image, os.R_OK):
        raise Missing(f"{image} is not readable by this user (Debian installs it root-only): "
                      f"run as root, or `sudo chmod 0644 {image}`")
    modules_dir = Path("/lib/modules") / version
    module_files = resolve_modules(modules_dir, modules)
    busybox = next((Path(p) for p in ("/bin/busybox", "/usr/bin/busybox") if Path(p).is_file()), None)
    if busybox is None or not _is_static_elf(busybox):
        what = "not found" if busybox is None else f"{busybox} is not statically linked"
        raise Missing(f"busybox {what}: install Debian's {PACKAGES['busybox']} ({INSTALL_HINT})")
    for program, package in PROGRAMS.items():
        if shutil.which(program) is None and not Path("/usr/sbin", program).exists() \
                and not Path("/sbin", program).exists():
            raise Missing(f"{program} not found: install Debian's {package} ({INSTALL_HINT})")
    kvm = os.access("/dev/kvm", os.R_OK | os.W_OK)
    return Requirements(Path(qemu), image, version, modules_dir, busybox, module_files, kvm)


# ----------------------------------------------------------------------------------------------
# the initramfs


def _cpio_entry(name: str, mode: int, data: bytes = b"", rdev: tuple[int, int] = (0, 0),
                ino: int = 0) -> bytes:
    """One member of a cpio archive in the "newc" format the kernel unpacks (see the kernel's
    Documentation/driver-api/early-userspace/buffer-format.rst)."""
    encoded = name.encode() + b"\0"
    fields = (ino, mode, 0, 0, 1, 0, len(data), 0, 0, rdev[0], rdev[1], len(encoded), 0)
    header = b"070701" + b"".join(b"%08X" % v for v in fields)
    out = header + encoded
    out += b"\0" * (-len(out) % 4)
    out += data
    out += b"\0" * (-len(out) % 4)
    return out


def build_initramfs(req: Requirements, dest: Path) -> Path:
    """An uncompressed initramfs at ``dest``: busybox, the modules, their order and /init."""
    entries: list[tuple[str, int, bytes, tuple[int, int]]] = []
    for folder in ("bin", "dev", "proc", "sys", "lib", "lib/modules"):
        entries.append((folder, stat.S_IFDIR | 0o755, b"", (0, 0)))
    # the kernel opens /dev/console for init's output before init mounts devtmpfs
    entries.append(("dev/console", stat.S_IFCHR | 0o600, b"", (5, 1)))
    entries.append(("bin/busybox", stat.S_IFREG | 0o755, req.busybox.read_bytes(), (0, 0)))
    entries.append(("init", stat.S_IFREG | 0o755, (HERE / "init.sh").read_bytes(), (0, 0)))
    names = []
    for i, rel in enumerate(req.modules):
        name = f"{i:02d}-{rel.rsplit('/', 1)[-1]}"
        names.append(name)
        entries.append((f"lib/modules/{name}", stat.S_IFREG | 0o644, (req.modules_dir / rel).read_bytes(), (0, 0)))
    entries.append(("modules", stat.S_IFREG | 0o644, ("\n".join(names) + "\n").encode(), (0, 0)))
    with open(dest, "wb") as f:
        for ino, (name, mode, data, rdev) in enumerate(entries, start=1):
            f.write(_cpio_entry(name, mode, data, rdev, ino))
        f.write(_cpio_entry("TRAILER!!!", 0))
    return dest


# ----------------------------------------------------------------------------------------------
# booting


@dataclasses.dataclass
class GuestRun:
    """What one boot did."""

    accel: str                  # "kvm" or "tcg"
    kvm_note: str               # why KVM was not used ("" when it was, or was not tried)
    boot_s: float | None        # qemu start to the guest's root ready (None: never ready)
    wall_s: float               # qemu start to its exit
    exit_status: int | None     # the command's, None when it did not finish
    reason: str                 # "" when the command finished, else why the guest ended
    console: Path

    def summary(self) -> str:
        boot = f"booted in {self.boot_s:.1f} s" if self.boot_s is not None else "never became ready"
        kvm = f"; kvm: {self.kvm_note}" if self.kvm_note else ""
        return f"guest {boot} ({self.accel}{kvm}), ran {self.wall_s:.0f} s"

    def as_dict(self) -> dict[str, object]:
        d = dataclasses.asdict(self)
        d["console"] = str(self.console)
        return d


def _job_script(command: Sequence[str], cwd: Path, env: dict[str, str]) -> str:
    exports = "\n".join(f"export {k}={shlex.quote(v)}" for k, v in sorted(env.items()))
    return (
        "#!/bin/sh\n"
        "# written by tools/canvm/canvm.py; runs as root in the guest\n"
        f"{exports}\n"
        "ip link set lo up 2>/dev/null\n"
        f"cd {shlex.quote(str(cwd))} || exit 125\n"
        f"{shlex.join(command)}\n"
        "status=$?\n"
        "echo $status > /run/canvm/exit-status\n"
        "exit $status\n"
    )


def guest_environment(accel: str, extra: dict[str, str] | None = None) -> dict[str, str]:
    """The command's environment: this interpreter's bin folder first on PATH (a virtual
    environment's tools), bytecode written (to the overlay: compiled once per boot, not per
    process), and ``DOBHIL_CANVM_GUEST``/``DOBHIL_CANVM_ACCEL`` for the tests."""
    path = [str(Path(sys.executable).parent), "/usr/local/sbin", "/usr/local/bin", "/usr/sbin",
            "/usr/bin", "/sbin", "/bin"]
    env = {"PATH": ":".join(dict.fromkeys(path)), "HOME": "/root", "LANG": "C.UTF-8",
           "TMPDIR": "/tmp", "DOBHIL_CANVM_GUEST": "1", "DOBHIL_CANVM_ACCEL": accel,
           "PYTHONUNBUFFERED": "1"}
    for key in ("CI", "DOBHIL_DEBUG", "PYTHONPATH"):
        if key in os.environ:
            env[key] = os.environ[key]
    if "VIRTUAL_ENV" in os.environ:
        env["VIRTUAL_ENV"] = os.environ["VIRTUAL_ENV"]
    env.update(extra or {})
    return env


def _firmware() -> list[str]:
    """qboot where qemu ships it: a firmware that only loads the kernel (SeaBIOS, the default,
    spends seconds of software emulation probing devices the guest never uses)."""
    for folder in ("/usr/share/qemu", "/usr/share/seabios"):
        if Path(folder, "qboot.rom").is_file():
            return ["-bios", str(Path(folder, "qboot.rom"))]
    return []


def _qemu_command(req: Requirements, initramfs: Path, job_dir: Path, accel: str, cpus: int,
                  memory_mb: int) -> list[str]:
    machine = ["-accel", "kvm", "-cpu", "host"] if accel == "kvm" else ["-accel", "tcg,thread=multi", "-cpu", TCG_CPU]
    return [
        str(req.qemu), *machine, "-smp", str(cpus), "-m", str(memory_mb),
        "-nodefaults", "-display", "none", *_firmware(), "-no-reboot", "-nic", "none",
        "-chardev", "stdio,id=console,signal=off", "-serial", "chardev:console",
        "-kernel", str(req.kernel), "-initrd", str(initramfs),
        "-append", "console=ttyS0 panic=-1 quiet loglevel=3",
        "-virtfs", "local,path=/,mount_tag=hostroot,security_model=none,readonly=on,multidevs=remap",
        "-virtfs", f"local,path={job_dir},mount_tag=canvm,security_model=none,multidevs=remap",
    ]


class _Console:
    """Reads qemu's serial console (its stdout) into a file, optionally echoing it, and notes
    when the guest's first line and its ready line appear."""

    def __init__(self, stream: object, path: Path, echo: Callable[[str], None] | None, start: float) -> None:
        self.path = path
        self.first_line = threading.Event()
        self.ready_after: float | None = None
        self.ready = threading.Event()
        self.last_line = ""
        self._echo = echo
        self._start = start
        self._thread = threading.Thread(target=self._pump, args=(stream,), name="canvm-console", daemon=True)
        self._thread.start()

    def _pump(self, stream: object) -> None:
        with open(self.path, "ab") as out:
            for raw in iter(stream.readline, b""):  # type: ignore[attr-defined]
                out.write(raw)
                out.flush()
                line = raw.decode(errors="replace").replace("\r", "").rstrip("\n")
                if line.strip():
                    self.last_line = line.strip()
                if FIRST_LINE in line:
                    self.first_line.set()
                if READY.search(line) and self.ready_after is None:
                    self.ready_after = time.monotonic() - self._start
                    self.ready.set()
                if self._echo is not None:
                    self._echo(line)

    def join(self, timeout: float) -> None:
        self._thread.join(timeout)


def _kill(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        proc.wait()


@contextlib.contextmanager
def _machine_lock() -> Iterator[None]:
    """With ``DOBHIL_CANVM_LOCK=FILE``, one guest at a time on this machine: guests started
    meanwhile wait. Two guests under software emulation on two cores starve each other's
    real-time runs; for developers running several test sessions at once (CI runs one)."""
    path = os.environ.get("DOBHIL_CANVM_LOCK")
    if not path:
        yield
        return
    with open(path, "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def run_in_guest(command: Sequence[str], *, job_dir: Path, cwd: Path | None = None,
                 env: dict[str, str] | None = None, accel: str = "auto", timeout: float = 3600.0,
                 cpus: int = CPUS, memory_mb: int = MEMORY_MB, echo: Callable[[str], None] | None = None,
                 req: Requirements | None = None) -> GuestRun:
    """Boot the guest, run ``command`` in ``cwd`` (default: this directory) as root, power off.

    ``job_dir`` is the guest's ``/run/canvm``. ``accel``: "auto" (KVM where it boots, else TCG),
    "kvm" or "tcg" (also from ``DOBHIL_CANVM_ACCEL``). ``timeout`` bounds the whole boot; a
    guest still running then is killed and the run says so.
    """
    req = req or find_requirements()
    with _machine_lock():
        return _run_in_guest(command, job_dir, cwd, env, accel, timeout, cpus, memory_mb, echo, req)


def _run_in_guest(command: Sequence[str], job_dir: Path, cwd: Path | None, env: dict[str, str] | None,
                  accel: str, timeout: float, cpus: int, memory_mb: int,
                  echo: Callable[[str], None] | None, req: Requirements) -> GuestRun:
    accel = os.environ.get("DOBHIL_CANVM_ACCEL", accel)
    if accel not in ("auto", "kvm", "tcg"):
        raise Missing(f"DOBHIL_CANVM_ACCEL={accel!r}: allowed auto, kvm, tcg")
    job_dir.mkdir(parents=True, exist_ok=True)
    initramfs = build_initramfs(req, job_dir / "initramfs.cpio")
    console_path = job_dir / "console.log"
    kvm_note = ""
    if accel == "kvm" and not req.kvm:
        raise Missing("/dev/kvm is not usable by this user: DOBHIL_CANVM_ACCEL=tcg, or give access to /dev/kvm")
    choices = ["kvm", "tcg"] if accel == "auto" and req.kvm else [accel if accel != "auto" else "tcg"]
    if accel == "auto" and not req.kvm:
        kvm_note = "no usable /dev/kvm"
    for choice in choices:
        status_file = job_dir / "exit-status"
        status_file.unlink(missing_ok=True)
        (job_dir / "job.sh").write_text(_job_script(command, cwd or Path.cwd(), guest_environment(choice, env)))
        start = time.monotonic()
        proc = subprocess.Popen(_qemu_command(req, initramfs, job_dir, choice, cpus, memory_mb),
                                stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                start_new_session=True)
        console = _Console(proc.stdout, console_path, echo, start)
        try:
            if choice == "kvm" and len(choices) > 1:
                probe_end = start + KVM_PROBE_S
                while not console.first_line.wait(0.05) and proc.poll() is None and time.monotonic() < probe_end:
                    pass
                if not console.first_line.is_set():
                    exited = proc.poll()
                    _kill(proc)
                    console.join(5)
                    kvm_note = (f"stalled (no console output within {KVM_PROBE_S:.0f} s)" if exited is None
                                else f"qemu exited with {exited} before the guest started "
                                     f"({console.last_line[-100:]})")
                    continue
            reason = ""
            try:
                proc.wait(timeout=max(0.0, timeout - (time.monotonic() - start)))
            except subprocess.TimeoutExpired:
                reason = f"killed after {timeout:.0f} s (the guest did not power off)"
                _kill(proc)
        finally:
            _kill(proc)
        console.join(5)
        wall = time.monotonic() - start
        exit_status: int | None = None
        if status_file.is_file():
            try:
                exit_status = int(status_file.read_text().strip())
            except ValueError:
                exit_status = None
        if exit_status is None and not reason:
            reason = (f"the guest ended before the command finished (qemu exit {proc.returncode}; "
                      f"console: {console_path})")
        return GuestRun(choice, kvm_note, console.ready_after, wall, exit_status, reason, console_path)
    raise AssertionError("unreachable: TCG is always the last choice")


def console_tail(path: Path, lines: int = 40) -> str:
    try:
        text = path.read_text(errors="replace").replace("\r", "")
    except OSError:
        return ""
    return "\n".join(text.splitlines()[-lines:])


# ----------------------------------------------------------------------------------------------
# command line


def _cmd_check(_: argparse.Namespace) -> int:
    req = find_requirements()
    print(f"canvm: {req.describe()}")
    print("canvm: modules: " + " ".join(_module_name(m) for m in req.modules))
    return 0


def _cmd_run(args: argparse.Namespace) -> int:
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        raise Missing("canvm run: give the command after --, e.g. canvm.py run -- ip link")
    with tempfile.TemporaryDirectory(prefix="canvm-") as tmp:
        job_dir = Path(args.job_dir) if args.job_dir else Path(tmp)
        result = run_in_guest(command, job_dir=job_dir, accel=args.accel, timeout=args.timeout,
                              cpus=args.cpus, memory_mb=args.memory,
                              echo=lambda line: print(line, flush=True))
    print(f"canvm: {result.summary()}; exit {result.exit_status}{' -- ' + result.reason if result.reason else ''}",
          file=sys.stderr)
    return result.exit_status if result.exit_status is not None else 124


def _cmd_pytest(args: argparse.Namespace) -> int:
    """The guest half of tools/canvm/pytest_canvm.py: run the given test ids in the guest and
    write ``status.json`` in the run folder (its results stream into ``results.jsonl``)."""
    run_dir = Path(args.run_dir)
    status = run_dir / "status.json"
    ids = [line for line in (run_dir / "ids.txt").read_text().splitlines() if line]
    try:
        req = find_requirements()
    except Missing as exc:
        status.write_text(json.dumps({"missing": str(exc)}))
        return 0
    command = [sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-o", "addopts=", "-q", "-rA", "--color=no",
               "--timeout", str(args.test_timeout), *ids]
    env = {"DOBHIL_CANVM_RESULTS": "/run/canvm/results.jsonl"}
    try:
        result = run_in_guest(command, job_dir=run_dir, cwd=Path(args.cwd), env=env, accel=args.accel,
                              timeout=args.timeout, req=req)
        info = result.as_dict()
        info["requirements"] = req.describe()
        (run_dir / "initramfs.cpio").unlink(missing_ok=True)
    except Exception as exc:
        info = {"error": f"{type(exc).__name__}: {exc}"}
    tmp = status.with_suffix(".tmp")
    tmp.write_text(json.dumps(info))
    tmp.replace(status)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="canvm.py", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="cmd", required=True)
    sub.add_parser("check", help="find the kernel, qemu, busybox, the modules and can-utils")
    run = sub.add_parser("run", help="run one command in the guest (its exit status is this one's)")
    run.add_argument("--accel", choices=("auto", "kvm", "tcg"), default="auto")
    run.add_argument("--timeout", type=float, default=3600.0, help="seconds before the guest is killed")
    run.add_argument("--cpus", type=int, default=CPUS)
    run.add_argument("--memory", type=int, default=MEMORY_MB, help="MiB")
    run.add_argument("--job-dir", help="keep the guest's /run/canvm here (default: a temporary folder)")
    run.add_argument("command", nargs=argparse.REMAINDER)
    pt = sub.add_parser("pytest", help=argparse.SUPPRESS)
    pt.add_argument("--run-dir", required=True)
    pt.add_argument("--cwd", required=True)
    pt.add_argument("--accel", default="auto")
    pt.add_argument("--timeout", type=float, default=3600.0)
    pt.add_argument("--test-timeout", type=float, default=600.0)
    args = parser.parse_args(argv)
    try:
        return {"check": _cmd_check, "run": _cmd_run, "pytest": _cmd_pytest}[args.cmd](args)
    except Missing as exc:
        print(f"canvm: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
