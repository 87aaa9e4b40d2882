"""The kernel guest's harness (tools/canvm/canvm.py) on the host: what it builds and how it
refuses. Booting is tested by every test of tests/socketcan, which runs in the guest."""

from __future__ import annotations

import json
import os
import shutil
import struct
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import pytest
from tool_module import load_tool

ROOT = Path(__file__).resolve().parents[1]
CANVM = ROOT / "tools" / "canvm" / "canvm.py"


def _load() -> ModuleType:
    return load_tool(CANVM, "canvm_under_test")


canvm = _load()


def test_a_cpio_member_is_the_kernels_newc_format() -> None:
    """Documentation/driver-api/early-userspace/buffer-format.rst: "070701", 13 fields of 8
    hex digits, the name with its NUL, padding to 4 bytes, the data, padding to 4."""
    member = canvm._cpio_entry("a", 0o100644, b"xy", ino=1)
    fields = ["00000001", "000081A4", "00000000", "00000000", "00000001", "00000000", "00000002",
              "00000000", "00000000", "00000000", "00000000", "00000002", "00000000"]
    assert member == ("070701" + "".join(fields)).encode() + b"a\0" + b"xy" + b"\0\0"
    assert len(member) % 4 == 0


def test_the_initramfs_lists_in_cpio(tmp_path: Path) -> None:
    """What ``cpio`` (GNU, an independent reader) lists in the archive built for a fake kernel."""
    if shutil.which("cpio") is None:
        pytest.skip("GNU cpio not installed")
    modules = tmp_path / "modules"
    (modules / "kernel").mkdir(parents=True)
    (modules / "kernel" / "vcan.ko").write_bytes(b"\x7fELF-not-really")
    busybox = tmp_path / "busybox"
    busybox.write_bytes(b"#!busybox")
    req = canvm.Requirements(Path("/usr/bin/true"), tmp_path / "vmlinuz-x", "x", modules, busybox,
                             ("kernel/vcan.ko",), False)
    archive = canvm.build_initramfs(req, tmp_path / "initramfs.cpio")
    listing = subprocess.run(["cpio", "-it", "--quiet"], input=archive.read_bytes(), capture_output=True)
    assert listing.returncode == 0, listing.stderr
    names = listing.stdout.decode().split()
    assert names == ["bin", "dev", "proc", "sys", "lib", "lib/modules", "dev/console", "bin/busybox", "init",
                     "lib/modules/00-vcan.ko", "modules"]


def test_modules_come_after_their_dependencies(tmp_path: Path) -> None:
    (tmp_path / "modules.dep").write_text(
        "kernel/net/can/can-bcm.ko: kernel/net/can/can.ko\n"
        "kernel/net/can/can.ko:\n"
        "kernel/drivers/net/can/vcan.ko: kernel/drivers/net/can/dev/can-dev.ko\n"
        "kernel/drivers/net/can/dev/can-dev.ko:\n")
    (tmp_path / "modules.builtin").write_text("kernel/net/sched/sch_fq_codel.ko\n")
    order = canvm.resolve_modules(tmp_path, ["can_bcm", "vcan", "can", "sch_fq_codel"])
    assert order == ("kernel/net/can/can.ko", "kernel/net/can/can-bcm.ko",
                     "kernel/drivers/net/can/dev/can-dev.ko", "kernel/drivers/net/can/vcan.ko")


def test_a_missing_module_names_the_package(tmp_path: Path) -> None:
    (tmp_path / "modules.dep").write_text("kernel/net/can/can.ko:\n")
    with pytest.raises(canvm.Missing, match=r"has no module vcan \(Debian's linux-image-amd64 has it"):
        canvm.resolve_modules(tmp_path, ["can", "vcan"])


def _elf(interp: bool) -> bytes:
    """A 64-bit little-endian ELF header with one program header (PT_INTERP or PT_LOAD)."""
    header = bytearray(64)
    header[:6] = b"\x7fELF\x02\x01"
    struct.pack_into("<Q", header, 32, 64)          # e_phoff
    struct.pack_into("<HH", header, 54, 56, 1)      # e_phentsize, e_phnum
    program = bytearray(56)
    struct.pack_into("<I", program, 0, 3 if interp else 1)
    return bytes(header + program)


def test_busybox_must_be_static(tmp_path: Path) -> None:
    static, dynamic = tmp_path / "static", tmp_path / "dynamic"
    static.write_bytes(_elf(interp=False))
    dynamic.write_bytes(_elf(interp=True))
    assert canvm._is_static_elf(static)
    assert not canvm._is_static_elf(dynamic)


def _check(env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, str(CANVM), "check"], capture_output=True, text=True,
                          env={**os.environ, **env}, timeout=60)


def test_no_qemu_is_one_line_naming_the_package() -> None:
    out = _check({"PATH": "/nonexistent"})
    assert out.returncode == 2, out
    assert out.stdout == ""
    assert out.stderr.count("\n") == 1 and "Traceback" not in out.stderr
    assert "qemu-system-x86_64 not found: install Debian's qemu-system-x86" in out.stderr


def test_no_kernel_is_one_line_naming_what_to_set(tmp_path: Path) -> None:
    if shutil.which("qemu-system-x86_64") is None:
        pytest.skip("needs qemu to get as far as the kernel")
    out = _check({"DOBHIL_CANVM_KERNEL": str(tmp_path / "vmlinuz-none")})
    assert out.returncode == 2, out
    assert out.stderr.count("\n") == 1 and "expected a /boot/vmlinuz-VERSION file" in out.stderr


def test_without_a_kernel_the_guest_tests_learn_why(tmp_path: Path) -> None:
    """The pytest plugin's side: ``canvm.py pytest`` writes the reason into status.json (each
    guest test then skips with it, and .ci/run fails on that skip)."""
    (tmp_path / "ids.txt").write_text("tests/socketcan/test_workflow.py::x\n")
    out = subprocess.run([sys.executable, str(CANVM), "pytest", "--run-dir", str(tmp_path), "--cwd", str(ROOT)],
                         capture_output=True, text=True, timeout=60,
                         env={**os.environ, "PATH": "/nonexistent"})
    assert out.returncode == 0, out
    status = json.loads((tmp_path / "status.json").read_text())
    assert "install Debian's qemu-system-x86" in status["missing"]


def test_an_unknown_accelerator_is_refused() -> None:
    out = subprocess.run([sys.executable, str(CANVM), "run", "--accel", "xen", "--", "true"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "invalid choice: 'xen'" in out.stderr
