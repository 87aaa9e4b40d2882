"""``.ci/check_skips.py``: CI fails on a skip its allowed list does not name."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("check_skips", ROOT / ".ci" / "check_skips.py")
assert spec is not None and spec.loader is not None
check_skips = importlib.util.module_from_spec(spec)
spec.loader.exec_module(check_skips)

ALLOWED = "# why\ntests/test_a.py: needs DOBHIL_SLOW=1\ntests/test_b.py: root .*\n"


@pytest.mark.parametrize(("line", "rc"), [
    ("SKIPPED [1] tests/test_a.py:12: needs DOBHIL_SLOW=1", 0),
    ("SKIPPED [3] tests/test_b.py:40: root writes anywhere", 0),
    ("SKIPPED [1] tests/test_b.py: root writes anywhere", 0),        # a module-level skip
    ("SKIPPED [1] tests/test_a.py:12: could not import 'lmfit'", 1),  # a package missing
    ("SKIPPED [1] tests/test_c.py:5: needs DOBHIL_SLOW=1", 1),       # allowed elsewhere only
    ("SKIPPED (unknown form)", 1),
])
def test_only_allowed_skips_pass(tmp_path: Path, line: str, rc: int, capsys: pytest.CaptureFixture[str]) -> None:
    log, allowed = tmp_path / "pytest.log", tmp_path / "allowed"
    log.write_text(f"=== short test summary info ===\n{line}\n=== 1 passed ===\n")
    allowed.write_text(ALLOWED)
    assert check_skips.main(str(log), str(allowed)) == rc
    assert "ci: skip" in capsys.readouterr().out   # every skip is printed


def test_the_repository_list_parses() -> None:
    rules = check_skips.rules((ROOT / ".ci" / "allowed-skips").read_text())
    assert rules and all(path.startswith("tests/") and (ROOT / path).is_file() for path, _ in rules)
