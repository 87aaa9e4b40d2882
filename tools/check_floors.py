#!/usr/bin/env python3
"""Run the test suite against the declared minimum of every dependency.

Each ``name>=X`` in ``pyproject.toml`` (the runtime dependencies and the ``live``
and ``test`` extras) becomes ``name==X`` in a fresh virtual environment without
system site-packages; a requirement pinned ``name==X`` is installed as pinned (it
has no range to be at the bottom of); dobhil itself is installed from this
checkout without dependencies,
``pip check`` must find the set consistent, and then the whole test suite runs
there. A floor that cannot be installed (no wheel for this Python, no such
release, a conflict) is reported as such: a lower bound is only true when the code
has been run with it.

    python tools/check_floors.py                 # all floors, the whole suite
    python tools/check_floors.py --pin mcap==1.5.0 -- tests/recording   # try a candidate
    python tools/check_floors.py --keep /tmp/floors --json
    python tools/check_floors.py --python python3.10                # the floors on another Python

Exit code 0 when every floor installed and the suite passed, 1 otherwise.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
#: extras whose floors are checked with the runtime dependencies (``lint`` is CI's
#: pinned tool set, not something the suite imports)
EXTRAS = ("live", "test")
_REQ = re.compile(r"^\s*([A-Za-z0-9][A-Za-z0-9._-]*)\s*(\[[^\]]*\])?\s*(.*?)\s*(;.*)?$")
_FLOOR = re.compile(r"(?:>=|~=)\s*([0-9][^,\s]*)")  # ~=X is >=X too
_EXACT = re.compile(r"^==\s*([0-9][^,\s]*)$")


@dataclass(frozen=True)
class Floor:
    name: str
    spec: str  # as declared, e.g. ">=1.5"
    pin: str | None  # "name==X" (the floor, or the declared exact pin), None when there is no lower bound
    exact: bool = False  # declared "==X": installed as pinned, not a floor


def _key(name: str) -> str:
    """The name as pip compares it (PEP 503: case, "-", "_" and "." alike)."""
    return re.sub(r"[-_.]+", "-", name).lower()


def _load_pyproject() -> dict[str, Any]:
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib
    with (ROOT / "pyproject.toml").open("rb") as fh:
        return tomllib.load(fh)


def floor_of(req: str) -> Floor | None:
    """One requirement string (PEP 508, as pyproject declares it) and its pin, None when it
    is not a requirement (a blank or a comment)."""
    m = _REQ.match(req)
    if m is None:
        return None
    name, spec, marker = m.group(1), m.group(3), m.group(4) or ""
    low, exact = _FLOOR.search(spec), _EXACT.match(spec)
    version = low or exact
    pin = f"{name}=={version.group(1)}{marker}" if version else None
    return Floor(name, spec, pin, exact is not None)


def floors(extras: tuple[str, ...] = EXTRAS) -> list[Floor]:
    """The declared requirements (runtime + extras) with their ``==floor`` pins, each name once."""
    project = _load_pyproject()["project"]
    reqs = list(project["dependencies"])
    for extra in extras:
        reqs += project.get("optional-dependencies", {}).get(extra, [])
    out: list[Floor] = []
    seen = {_key(project["name"])}
    for req in reqs:
        floor = floor_of(req)
        if floor is None or _key(floor.name) in seen:  # e.g. foxglove-sdk in both `live` and `test`
            continue
        seen.add(_key(floor.name))
        out.append(floor)
    return out


def pins(declared: list[Floor], candidates: list[str]) -> list[str]:
    """What pip installs: each declared pin, or the ``--pin NAME==VERSION`` given for that name."""
    override = {_key(p.split("==")[0].strip()): p for p in candidates}
    return [override.get(_key(f.name), f.pin) for f in declared if f.pin is not None]


def _run(cmd: list[str], log: Path, cwd: Path = ROOT) -> tuple[int, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    with log.open("a") as fh:
        fh.write(f"\n$ {' '.join(cmd)}\n")
        fh.flush()
        # line by line into the log as it comes: a suite of minutes can be followed (tail -f)
        with subprocess.Popen(cmd, cwd=cwd, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True) as proc:
            assert proc.stdout is not None
            lines = []
            for line in proc.stdout:
                fh.write(line)
                fh.flush()
                lines.append(line)
    return proc.returncode, "".join(lines)


def _last_line(text: str) -> str:
    lines = [ln for ln in text.strip().splitlines() if ln.strip() and not ln.startswith("WARNING:")]
    return lines[-1] if lines else ""


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="install every dependency at its declared minimum "
                                 "in a fresh venv and run the tests")
    ap.add_argument("--pin", action="append", default=[], metavar="NAME==VERSION",
                    help="use this version instead of a declared floor (to try a candidate)")
    ap.add_argument("--keep", type=Path, metavar="DIR", help="build the venv here and keep it")
    ap.add_argument("--python", default=sys.executable, metavar="PATH",
                    help="interpreter of the fresh venv (default: this one)")
    ap.add_argument("--json", action="store_true", help="print the result as JSON")
    ap.add_argument("pytest_args", nargs="*", help="arguments for pytest (default: the whole suite)")
    args = ap.parse_args(argv)

    declared = floors()
    installed = pins(declared, args.pin)
    unfloored = [f.name for f in declared if f.pin is None]
    work = args.keep or Path(tempfile.mkdtemp(prefix="dobhil-floors-"))
    work.mkdir(parents=True, exist_ok=True)
    venv, log = work / "venv", work / "floors.log"
    py = venv / "bin" / "python"
    version = subprocess.run([args.python, "-c", "import sys; print(sys.version.split()[0])"],
                             capture_output=True, text=True, check=True).stdout.strip()
    result: dict[str, object] = {"python": version, "pins": installed, "unfloored": unfloored, "log": str(log)}
    t0 = time.monotonic()
    steps = [
        ("venv", [args.python, "-m", "venv", "--clear", str(venv)]),
        ("install floors", [str(py), "-m", "pip", "install", "--quiet", *installed]),
        ("install dobhil", [str(py), "-m", "pip", "install", "--quiet", "--no-deps", str(ROOT)]),
        ("pip check", [str(py), "-m", "pip", "check"]),
        ("pytest", [str(py), "-m", "pytest", "-q", "-p", "no:cacheprovider", "--maxfail=20",
                    *(args.pytest_args or [])]),
    ]
    ok = True
    for step, cmd in steps:
        code, out = _run(cmd, log, cwd=ROOT)
        result[step] = {"exit": code, "last": _last_line(out)}
        if code != 0 and step == "pip check" and args.pin:
            continue  # a candidate below a declared floor conflicts with dobhil's own requirement
        if code != 0:
            ok = False
            break
    code, frozen = _run([str(py), "-m", "pip", "freeze", "--all"], log)
    result["freeze"] = frozen.splitlines() if code == 0 else []  # one requirement a line
    result["ok"] = ok
    result["seconds"] = round(time.monotonic() - t0, 1)
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print(f"python {result['python']}; floors: {', '.join(installed)}")
        if unfloored:
            print(f"no lower bound declared: {', '.join(unfloored)}")
        for step, _ in steps:
            if step in result:
                r = result[step]
                print(f"  {step:<15} exit {r['exit']}  {r['last']}")  # type: ignore[index]
        print(f"{'PASS' if ok else 'FAIL'} in {result['seconds']} s; log: {log}")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
