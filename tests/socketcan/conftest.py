"""The kernel's CAN stack, for real: what runs in the guest of tools/canvm (every test of this
folder is marked ``socketcan``; on the host, tools/canvm/pytest_canvm.py runs them there).

Each test makes what it needs -- its own vcan interface (by the README's ``tools/setup_vcan.sh``),
its own config overlay -- and removes it. Periods follow the accelerator: under software emulation
(TCG) Python runs 30-50 times slower than on the host, so the runs use 10 ms, with observer
bandwidths and profiles to match; under KVM or on a native kernel, the shipped 1 ms.
"""

from __future__ import annotations

import itertools
import os
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from .guest import REPO, Dobhil

ACCEL = os.environ.get("DOBHIL_CANVM_ACCEL", "native")
_names = itertools.count()


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    here = Path(__file__).parent
    for item in items:
        if here in item.path.parents:
            item.add_marker(pytest.mark.socketcan)


@pytest.fixture(autouse=True)
def _kernel_can() -> None:
    """Run only where a test may create CAN interfaces (the guest, or a native Linux kernel
    as root with DOBHIL_CANVM_GUEST=1)."""
    if os.environ.get("DOBHIL_CANVM_GUEST") != "1":
        pytest.fail("tests/socketcan runs in the kernel guest (tools/canvm); got here without it")


@pytest.fixture
def vcan() -> Iterator[str]:
    """A fresh vcan interface made by tools/setup_vcan.sh, deleted afterwards."""
    name = f"vcan{next(_names)}x{os.getpid() % 1000}"
    out = subprocess.run(["bash", str(REPO / "tools" / "setup_vcan.sh"), name], capture_output=True, text=True)
    assert out.returncode == 0, out.stdout + out.stderr
    try:
        yield name
    finally:
        subprocess.run(["ip", "link", "del", "dev", name], capture_output=True)


@pytest.fixture
def dobhil(tmp_path: Path) -> Iterator[Dobhil]:
    """Starts dobhil commands as processes; stops whatever is left at the end."""
    runner = Dobhil(tmp_path)
    try:
        yield runner
    finally:
        runner.stop_all()
