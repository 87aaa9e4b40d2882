"""Entry point of the ``dobhil`` command.

Each subcommand lives in its own module of this package and exposes
``register(subparsers: argparse._SubParsersAction) -> None``; the parser it adds
sets ``func=callable(args) -> int``. Any :class:`dobhil.errors.DobhilError`
(and argparse usage errors) end in one line on stderr and exit code 2, with no
traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from dobhil import __version__
from dobhil.errors import DobhilError

#: Subcommand modules, in the order ``dobhil --help`` lists them.
_SUBCOMMANDS: tuple[str, ...] = (
    "dobhil.cli.analyze_cmd",
    "dobhil.cli.sweep_cmd",
    "dobhil.cli.paper_cmd",
    "dobhil.cli.run_cmd",
    "dobhil.cli.log_cmd",
    "dobhil.cli.replay_cmd",
    "dobhil.cli.report_cmd",
    "dobhil.cli.demo_cmd",
)

EXIT_USAGE = 2


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (exit code 2) instead of usage dumps."""

    def error(self, message: str) -> None:  # type: ignore[override]
        sys.stderr.write(f"{self.prog}: error: {message}\n")
        raise SystemExit(EXIT_USAGE)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="dobhil", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"dobhil {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    for name in _SUBCOMMANDS:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name != name:
                raise
            continue
        module.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    try:  # Ctrl-C while the subcommands are imported: one line, no traceback
        args = build_parser().parse_args(argv)
    except KeyboardInterrupt:
        sys.stderr.write("dobhil: interrupted\n")
        return 130
    try:
        return int(args.func(args) or 0)
    except DobhilError as exc:
        sys.stderr.write(f"dobhil {args.command}: error: {exc}\n")
        return EXIT_USAGE
    except KeyboardInterrupt:
        sys.stderr.write(f"dobhil {args.command}: interrupted\n")
        return 130
