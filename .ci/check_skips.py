"""Every skip of a pytest run printed, and each one allowed by ``.ci/allowed-skips``.

``python .ci/check_skips.py PYTEST-LOG ALLOWED`` reads the short summary pytest prints with
``-ra`` (``SKIPPED [N] path:line: reason``) and exits 1 when a skip's reason matches no line
of ``ALLOWED`` for its file: a hub that did not start, or a package missing from the test
extra, would otherwise turn tests into silent skips.
"""

from __future__ import annotations

import re
import sys

SKIP = re.compile(r"SKIPPED \[(\d+)\] ([^:\n]+?)(?::\d+)?: (.*)")


def rules(text: str) -> list[tuple[str, re.Pattern[str]]]:
    """``TEST-FILE: REASON-REGEX`` lines; ``#`` comments and blank lines skipped."""
    out = []
    for line in text.splitlines():
        if line.strip() and not line.lstrip().startswith("#"):
            path, sep, reason = line.partition(": ")
            if not sep:
                raise SystemExit(f"allowed skips: {line!r} is not 'TEST-FILE: REASON'")
            out.append((path.strip(), re.compile(reason.strip())))
    return out


def main(log_path: str, allowed_path: str) -> int:
    with open(log_path, encoding="utf-8") as f:
        log = f.read()
    with open(allowed_path, encoding="utf-8") as f:
        allowed = rules(f.read())
    bad = 0
    for line in log.splitlines():
        if not line.startswith("SKIPPED "):
            continue
        match = SKIP.fullmatch(line)
        if match is None:   # a form this reader does not know is never allowed unread
            bad += 1
            print(f"ci: skip NOT ALLOWED (unread): {line}")
            continue
        count, path, reason = match.groups()
        ok = any(path == p and r.fullmatch(reason) for p, r in allowed)
        bad += not ok
        print(f"ci: skip {'allowed' if ok else 'NOT ALLOWED'}: {path}: {reason} ({count})")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:3]))
