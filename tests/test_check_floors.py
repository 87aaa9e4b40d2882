"""tools/check_floors.py: every requirement pyproject declares is installed at its floor (or its
exact pin), and the README's floors table lists each at the floor pyproject declares.

The requirement strings are read a second, independent way, with ``packaging`` (the parser pip
itself uses), so a declaration the tool's own parsing missed or misread fails here.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

from hypothesis import given
from hypothesis import strategies as st

from tool_module import load_tool

from packaging.requirements import Requirement  # matplotlib's dependency: always there
from packaging.version import Version

if sys.version_info >= (3, 11):
    import tomllib
else:  # Python 3.10: pytest's own dependency
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]
check_floors = load_tool(ROOT / "tools" / "check_floors.py", "check_floors")


def _declared() -> list[str]:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    reqs = list(project["dependencies"])
    for extra in check_floors.EXTRAS:
        reqs += project["optional-dependencies"][extra]
    return reqs


def _lower_bound(req: object) -> str | None:
    """The lowest version ``req`` (a packaging Requirement) admits, as declared."""
    for spec in req.specifier:  # type: ignore[attr-defined]
        if spec.operator in (">=", "~=", "=="):
            return str(spec.version)
    return None


def test_every_declared_requirement_is_installed_at_its_floor_or_pin() -> None:
    pins = {check_floors._key(f.name): f for f in check_floors.floors()}
    declared = [Requirement(r) for r in _declared()]
    assert {check_floors._key(r.name) for r in declared} == set(pins)
    for req in declared:
        low = _lower_bound(req)
        assert low is not None, f"{req}: every dependency declares a floor (>=) or an exact pin (==)"
        floor = pins[check_floors._key(req.name)]
        pinned = Requirement(floor.pin)
        assert [(s.operator, s.version) for s in pinned.specifier] == [("==", low)], (req, floor.pin)
        assert pinned.marker == req.marker, (req, floor.pin)
        assert floor.exact == any(s.operator == "==" for s in req.specifier)


def test_the_extras_checked_are_the_ones_tests_and_users_install() -> None:
    # `lint` is CI's pinned tool set; `live` and `test` are what the suite imports
    assert set(check_floors.EXTRAS) == {"live", "test"}
    names = {check_floors._key(f.name) for f in check_floors.floors()}
    assert {"lmfit", "numba", "threadpoolctl", "canopen", "dask", "distributed", "pyarrow",
            "pytest-xdist", "foxglove-sdk", "websockets", "moteus"} <= names
    assert "ruff" not in names and "dobhil" not in names


def test_a_candidate_replaces_the_floor_of_its_name_only() -> None:
    declared = check_floors.floors()
    out = check_floors.pins(declared, ["PyYAML==6.0.1", "Python_Can==4.4.0"])
    assert "PyYAML==6.0.1" in out and "Python_Can==4.4.0" in out
    assert "pyyaml==6" not in out and "python-can==4.3" not in out
    assert len(out) == len(declared)


_NAME = st.from_regex(r"[A-Za-z][A-Za-z0-9]{0,6}([-_.][A-Za-z0-9]{1,5}){0,2}", fullmatch=True)
_VERSION = st.from_regex(r"[0-9]{1,4}(\.[0-9]{1,3}){0,3}", fullmatch=True)
_MARKER = st.sampled_from(["", "; python_version >= '3.11'", "; sys_platform == 'linux'"])


@given(_NAME, st.sampled_from([">=", "~=", "=="]), _VERSION, st.sampled_from(["", ",<99", ", <99.1"]),
       st.sampled_from(["", " "]), _MARKER)
def test_floor_of_agrees_with_pip_parser(name: str, op: str, version: str, upper: str, space: str,
                                         marker: str) -> None:
    if op == "~=" and "." not in version:
        version += ".0"  # ~= needs two components
    if op == "==":
        upper = ""
    text = f"{name}{space}{op}{space}{version}{upper}{marker}"
    req = Requirement(text)
    floor = check_floors.floor_of(text)
    assert floor is not None and floor.name == req.name
    pinned = Requirement(floor.pin)
    assert [(s.operator, s.version) for s in pinned.specifier] == [("==", _lower_bound(req))]
    assert pinned.marker == req.marker


def test_readme_floors_table_lists_each_floor_as_declared() -> None:
    readme = (ROOT / "README.md").read_text()
    start = readme.index("**True dependency floors.**")
    section = readme[start:readme.index("\n### ", start)]
    rows = re.findall(r"^\| `([^`]+)` \| ([^|]+?) \|", section, re.MULTILINE)
    assert rows, "the README's floors section has a table of `name` | floor"
    table = {check_floors._key(name): floor.strip() for name, floor in rows}
    want = {check_floors._key(f.name): f.pin.split(";")[0].split("==")[1] for f in check_floors.floors()}
    assert set(table) == set(want)
    for key, floor in want.items():  # "1.24" and "1.24.0" are one version
        assert Version(table[key]) == Version(floor), (key, table[key])
