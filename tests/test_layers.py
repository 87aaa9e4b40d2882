"""Layers point one way: the package order declared once (:data:`LAYERS`), no import circle
in the package, and no dependency's private names anywhere in ``dobhil/``."""

from __future__ import annotations

import ast
import re
from collections.abc import Iterator
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "dobhil"

#: The package order, lowest first. A module may import only its own package and packages of
#: lower layers; the packages of one layer are independent of each other (the plant emulator
#: and the recording, say, or the loop and the python-can plugins). Every module of ``dobhil/``
#: belongs to exactly one entry ("dobhil" is the package root: ``__version__``).
LAYERS: list[tuple[str, ...]] = [
    ("dobhil", "dobhil.errors"),                            # the root: version, error types
    ("dobhil.files", "dobhil.data", "dobhil.realtime",      # the OS: files, shipped data, scheduling,
     "dobhil.forkserver",                                   # children forked from one process,
     "dobhil.cluster"),                                     # work on a Dask cluster
    ("dobhil.config",),                                     # keys, loading, validation
    ("dobhil.synthesis", "dobhil.drives"),                  # the observers; drive profiles and codecs
    ("dobhil.analysis", "dobhil.emulator", "dobhil.recording"),  # the design analysed; the plant; logs
    ("dobhil.plotting", "dobhil.runtime", "dobhil.canio",   # figures; the loop; python-can plugins;
     "dobhil.live", "dobhil.run_report",                    # the live view; the report of a recorded run;
     "dobhil.identify",                                     # the plant identified from a recorded run;
     "dobhil.tune"),                                        # robust gains over an environment range
    ("dobhil.replay", "dobhil.paper",                       # a log replayed; the paper reproduced;
     "dobhil.campaign"),                                    # Monte-Carlo campaigns (on dobhil.cluster)
    ("dobhil.cli",),                                        # the command
    ("dobhil.__main__",),                                   # ``python -m dobhil``
]


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(p): p for p in PACKAGE.rglob("*.py")}


#: A module named in a string: ``dobhil.drives.odrive.emulator`` (or an entry point, ``module:name``).
MODULE_NAME = re.compile(r"dobhil(?:\.\w+)+(?::\w+)?")


def imported_names(source: str, module: str, is_package: bool) -> Iterator[tuple[int, str]]:
    """``(line, name)`` of every dotted name ``source`` (the text of ``module``) imports, at any
    level (functions and TYPE_CHECKING too), relative imports resolved; ``from a import b``
    gives ``a`` and ``a.b`` (``b`` may be a module or a name in ``a``). A string that is a
    dobhil module name counts too: registries import by name (``importlib.import_module``);
    but not one naming ``module`` itself or a package it is in (an entry-point group named after
    its package, ``"dobhil.drives"``): Python has imported those before ``module`` runs."""
    package = module if is_package else module.rpartition(".")[0]
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and MODULE_NAME.fullmatch(node.value):
            named = node.value.partition(":")[0]
            if not (module == named or module.startswith(named + ".")):
                yield node.lineno, named
        elif isinstance(node, ast.Import):
            yield from ((node.lineno, alias.name) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join([*package.split(".")[: len(package.split(".")) - node.level + 1], base]).strip(".")
            yield node.lineno, base
            yield from ((node.lineno, f"{base}.{alias.name}") for alias in node.names)


def imports(path: Path) -> set[str]:
    """Every dobhil module ``path`` imports, at any level (functions and TYPE_CHECKING too)."""
    name = module_name(path)
    return {m for _, m in imported_names(path.read_text(), name, path.name == "__init__.py") if m in MODULES}


def layer_entry(module: str) -> str | None:
    """The :data:`LAYERS` entry ``module`` belongs to (the longest that contains it)."""
    inside = [p for layer in LAYERS for p in layer
              if module == p or (p != "dobhil" and module.startswith(p + "."))]
    return max(inside, key=len, default=None)


def layer_index(entry: str) -> int:
    return next(i for i, layer in enumerate(LAYERS) if entry in layer)


def layer_problems(source: str, module: str, is_package: bool = False, where: str = "") -> list[str]:
    """Each import of ``source`` (module ``module``) against :data:`LAYERS`, one line each:
    where, the line, the module, what it imports and why that is not allowed."""
    own = layer_entry(module)
    if own is None:
        return [f"{where or module}: module {module} is in no layer of LAYERS"]
    problems, seen = [], set()
    for line, name in sorted(set(imported_names(source, module, is_package))):
        target = layer_entry(name) if name == "dobhil" or name.startswith("dobhil.") else own
        if target is None or target == own or layer_index(target) < layer_index(own) or (line, target) in seen:
            continue
        seen.add((line, target))  # ``from a.b import c``: one line for a.b, not another for a.b.c
        how = "a peer in the same layer as" if layer_index(target) == layer_index(own) else "a higher layer than"
        problems.append(f"{where or module}:{line}: {module} imports {name} ({target}: {how} {own})")
    return problems


GRAPH = {name: imports(path) - {name} for name, path in MODULES.items()}


def cycles() -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in GRAPH[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    for v in sorted(GRAPH):
        if v not in index:
            visit(v)
    return out


def test_every_import_follows_the_layers() -> None:
    problems = [problem for name, path in sorted(MODULES.items())
                for problem in layer_problems(path.read_text(), name, path.name == "__init__.py",
                                              str(path.relative_to(PACKAGE.parent)))]
    assert problems == [], "imports against LAYERS:\n" + "\n".join(problems)


def test_every_layer_entry_is_a_module_of_the_package() -> None:
    entries = [p for layer in LAYERS for p in layer]
    assert len(entries) == len(set(entries))
    assert [p for p in entries if p not in MODULES and not any(m.startswith(p + ".") for m in MODULES)] == []


def test_the_package_docstring_lists_the_layers() -> None:
    """``dobhil/__init__.py`` shows the order to a reader: its items must be :data:`LAYERS`."""
    text = ast.get_docstring(ast.parse((PACKAGE / "__init__.py").read_text())) or ""
    items = [set(re.findall(r"``(dobhil\.\w+)``", item)) for item in text.split("\n- ")[1:]]
    assert items == [set(layer) - {"dobhil"} for layer in LAYERS if set(layer) - {"dobhil", "dobhil.__main__"}]


FUNCTION_LEVEL = "def start() -> None:\n    from dobhil.runtime.realtime import lower_priority\n    lower_priority()\n"
TYPE_CHECKING_ONLY = "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from dobhil.replay import ReplayResult\n"
IN_A_METHOD = "class A:\n    def f(self) -> None:\n        import dobhil.runtime.loop as loop\n"


@pytest.mark.parametrize(("module", "is_package", "source", "expected"), [
    # upward, however it is written
    ("dobhil.emulator.plant", False, FUNCTION_LEVEL,
     ["dobhil.emulator.plant:2: dobhil.emulator.plant imports dobhil.runtime.realtime (dobhil.runtime: "
      "a higher layer than dobhil.emulator)"]),
    ("dobhil.emulator.plant", False, "from ..runtime import realtime\n",
     ["dobhil.emulator.plant:1: dobhil.emulator.plant imports dobhil.runtime (dobhil.runtime: "
      "a higher layer than dobhil.emulator)"]),
    ("dobhil.emulator", True, "from .. import runtime\n",
     ["dobhil.emulator:1: dobhil.emulator imports dobhil.runtime (dobhil.runtime: a higher layer than "
      "dobhil.emulator)"]),
    ("dobhil.plotting.report_figures", False, TYPE_CHECKING_ONLY,
     ["dobhil.plotting.report_figures:3: dobhil.plotting.report_figures imports dobhil.replay (dobhil.replay: "
      "a higher layer than dobhil.plotting)"]),
    ("dobhil.config.load", False, IN_A_METHOD,
     ["dobhil.config.load:3: dobhil.config.load imports dobhil.runtime.loop (dobhil.runtime: a higher layer "
      "than dobhil.config)"]),
    ("dobhil.emulator.faults", False, "import importlib\nCLASSES = {'x': ('dobhil.runtime.loop', 'ForceLoop')}\n",
     ["dobhil.emulator.faults:2: dobhil.emulator.faults imports dobhil.runtime.loop (dobhil.runtime: "
      "a higher layer than dobhil.emulator)"]),
    # a peer of the same layer
    ("dobhil.canio.bus", False, "import dobhil.runtime\n",
     ["dobhil.canio.bus:1: dobhil.canio.bus imports dobhil.runtime (dobhil.runtime: a peer in the same layer "
      "as dobhil.canio)"]),
    # allowed: own package (relative too), lower layers, the root, other libraries
    ("dobhil.recording.process", False, "from . import writer\nfrom .writer import LogWriter\nimport dobhil\n"
     "from dobhil import __version__\nfrom dobhil.errors import RecorderError\nimport os\n", []),
    ("dobhil.cli.main", False, "def f() -> None:\n    from dobhil.runtime.session import RunSession\n", []),
    ("dobhil.runtime.session", False, "from dobhil.realtime import lower_priority\n", []),
    ("dobhil.emulator.faults", False, "CLASSES = {'odrive': ('dobhil.drives.odrive.emulator', 'EmulatedODrive')}\n"
     "DOC = 'like :mod:`dobhil.runtime.loop`'\n", []),
    # a string naming the module's own package (an entry-point group) is no import of it
    ("dobhil.drives.registry", False, "ENTRY_POINT_GROUP = 'dobhil.drives'\n", []),
    # a module of a package no layer names
    ("dobhil.newpackage.thing", False, "", ["dobhil.newpackage.thing: module dobhil.newpackage.thing is in no "
                                            "layer of LAYERS"]),
])
def test_the_layer_check(module: str, is_package: bool, source: str, expected: list[str]) -> None:
    assert layer_problems(source, module, is_package) == expected


def test_no_import_circle_between_modules() -> None:
    assert cycles() == []


@pytest.mark.parametrize(("low", "high"), [("dobhil.recording", "dobhil.runtime"),
                                           ("dobhil.runtime", "dobhil.recording")])
def test_recording_and_runtime_do_not_import_each_other(low: str, high: str) -> None:
    """Beyond the layers (recording is below the runtime): the loop knows its recorder only
    as a ``CycleSink``."""
    offenders = {m: sorted(i for i in deps if i == high or i.startswith(high + "."))
                 for m, deps in GRAPH.items() if m == low or m.startswith(low + ".")}
    assert {m: d for m, d in offenders.items() if d} == {}


#: Import name of each runtime dependency whose distribution name differs from it.
IMPORT_NAMES = {"python-can": "can", "pyyaml": "yaml", "foxglove-sdk": "foxglove"}


def runtime_dependencies() -> list[str]:
    """The import names of ``pyproject.toml``'s dependencies, and of its ``live`` extra."""
    text = (PACKAGE.parent / "pyproject.toml").read_text()
    block = re.search(r"^dependencies = \[(.*?)^\]", text, re.M | re.S)
    live = re.search(r"^live = \[(.*?)\]", text, re.M)
    assert block is not None and live is not None
    names = re.findall(r'^\s*"([A-Za-z0-9_.-]+)', block[1], re.M) + re.findall(r'"([A-Za-z0-9_.-]+)', live[1])
    return sorted({IMPORT_NAMES.get(n.lower(), n.lower().replace("-", "_")) for n in names})


_DEPENDENCIES = "|".join(runtime_dependencies())
#: Private names of dependencies a module must not touch: ``dep.x._y`` (any case), ``from dep.x
#: import _y``, ``from dep._x import y``, and the old writer's mangled and buffer names.
PRIVATE = re.compile(rf"\b(?:{_DEPENDENCIES})(?:\.\w+)*\._(?!_)"
                     rf"|\bfrom (?:{_DEPENDENCIES})(?:\.\w+)* import .*\b_(?!_)\w"
                     r"|_Writer__|\._buffer\b|multiprocessing\.connection\._|connection\._(?:send|recv)")


def test_the_private_name_check_covers_every_runtime_dependency() -> None:
    assert {"can", "canopen", "control", "dask", "distributed", "foxglove", "mcap", "numpy", "scipy",
            "yaml"} <= set(runtime_dependencies())


@pytest.mark.parametrize("line", [
    "from canopen.sdo.client import _Private", "canopen.sdo.client.SdoClient._read_response",
    "distributed.comm._probe(x)", "from dask._task_spec import Task", "can.BusABC._matches_filters(m)",
])
def test_the_private_name_check_finds(line: str) -> None:
    assert PRIVATE.search(line)


@pytest.mark.parametrize("line", ["canopen.sdo.SdoClient.upload(i, s)", "self._inner.recv(0.0)",
                                  "scipy.linalg.__version__", "from dobhil.cluster import _probe"])
def test_the_private_name_check_passes(line: str) -> None:
    assert not PRIVATE.search(line)


def test_no_private_name_of_a_dependency() -> None:
    hits = [f"{p.relative_to(PACKAGE.parent)}:{i}: {line.strip()}" for p in MODULES.values()
            for i, line in enumerate(p.read_text().splitlines(), 1) if PRIVATE.search(line)]
    assert hits == []


def test_the_private_name_check_finds_what_the_old_writer_did() -> None:
    old = ["from mcap._chunk_builder import ChunkBuilder", "builder = self._Writer__chunk_builder",
           "buf = builder.record_writer._buffer"]
    assert all(PRIVATE.search(line) for line in old)


def test_a_string_naming_an_own_package_is_no_import_but_a_sibling_is() -> None:
    """The registry's entry-point group (``"dobhil.drives"``) names its own package, which
    Python imports before the registry; a string naming a sibling module is a real import."""
    found = dict(imported_names("G = 'dobhil.drives'\nM = 'dobhil.drives.base'\n", "dobhil.drives.registry", False))
    assert found == {2: "dobhil.drives.base"}
