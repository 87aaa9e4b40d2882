#!/usr/bin/env python3
"""Figures measured inside the kernel guest (tools/canvm), for ``tools/bench.py`` and the tests.

Run in the guest (``python tools/canvm/canvm.py run -- python tools/canvm/figures.py NAME...``):
each NAME is one measurement in :data:`FIGURES`; the JSON object of the results is printed on
one line prefixed ``figures:``. Every figure is a guest figure: under software emulation (TCG)
it says what this machine's emulated kernel did, not what a real one does.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from typing import Any

#: name -> a function of no arguments returning a JSON-able mapping
FIGURES: dict[str, Callable[[], dict[str, Any]]] = {}


def figure(name: str) -> Callable[[Callable[[], dict[str, Any]]], Callable[[], dict[str, Any]]]:
    """Register a measurement under ``name``."""
    def register(fn: Callable[[], dict[str, Any]]) -> Callable[[], dict[str, Any]]:
        FIGURES[name] = fn
        return fn
    return register


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("names", nargs="*", help=f"figures to measure (default: all of {sorted(FIGURES)})")
    args = parser.parse_args(argv)
    unknown = [n for n in args.names if n not in FIGURES]
    if unknown:
        print(f"figures.py: unknown figure(s) {', '.join(unknown)}; known: {', '.join(sorted(FIGURES))}",
              file=sys.stderr)
        return 2
    out = {name: FIGURES[name]() for name in (args.names or sorted(FIGURES))}
    print("figures: " + json.dumps(out), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
