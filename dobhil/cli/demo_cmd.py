"""``dobhil demo``: the main job, ready to run on a fresh clone."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("demo", help="reproduce the paper (Fig. 2, Fig. 3, Section IV claims)")
    p.add_argument("--out", type=Path, default=Path("out/demo"), help="output directory")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from dobhil.cli.paper_cmd import reproduce
    return reproduce(args.out)
