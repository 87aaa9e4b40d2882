"""Layers point one way: no import circle in the package, recording and the runtime apart,
and no dependency's private names anywhere in ``dobhil/``."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "dobhil"


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(p): p for p in PACKAGE.rglob("*.py")}


def imports(path: Path) -> set[str]:
    """Every dobhil module ``path`` imports, at any level (functions and TYPE_CHECKING too)."""
    out: set[str] = set()
    package = module_name(path) if path.name == "__init__.py" else module_name(path).rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join([*package.split(".")[: len(package.split(".")) - node.level + 1], base]).strip(".")
            out.add(base)
            out.update(f"{base}.{alias.name}" for alias in node.names)
    return {m for m in out if m in MODULES}


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


def test_no_import_circle_between_modules() -> None:
    assert cycles() == []


def test_the_report_and_its_figures_are_no_circle() -> None:
    assert "dobhil.plotting.report_figures" not in GRAPH["dobhil.analysis.run_report"]


@pytest.mark.parametrize(("low", "high"), [("dobhil.recording", "dobhil.runtime"),
                                           ("dobhil.runtime", "dobhil.recording")])
def test_recording_and_runtime_do_not_import_each_other(low: str, high: str) -> None:
    offenders = {m: sorted(i for i in deps if i == high or i.startswith(high + "."))
                 for m, deps in GRAPH.items() if m == low or m.startswith(low + ".")}
    assert {m: d for m, d in offenders.items() if d} == {}


#: Private names of dependencies a module must not touch.
PRIVATE = re.compile(r"mcap\._|_Writer__|\._buffer\b|multiprocessing\.connection\._|connection\._(?:send|recv)"
                     r"|can\.[a-z_.]*\._|foxglove\._|\bnumpy\._|scipy\.[a-z_.]*\._(?!_)|\bcontrol\.[a-z_.]*\._")


def test_no_private_name_of_a_dependency() -> None:
    hits = [f"{p.relative_to(PACKAGE.parent)}:{i}: {line.strip()}" for p in MODULES.values()
            for i, line in enumerate(p.read_text().splitlines(), 1) if PRIVATE.search(line)]
    assert hits == []


def test_the_private_name_check_finds_what_the_old_writer_did() -> None:
    old = ["from mcap._chunk_builder import ChunkBuilder", "builder = self._Writer__chunk_builder",
           "buf = builder.record_writer._buffer"]
    assert all(PRIVATE.search(line) for line in old)
