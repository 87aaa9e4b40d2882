"""Arguments and helpers shared by subcommands."""

from __future__ import annotations

import argparse
from pathlib import Path

from dobhil.config import Config, load_config


def add_config_args(parser: argparse.ArgumentParser, *, required: bool = True) -> None:
    parser.add_argument("config", metavar="CONFIG", nargs=None if required else "?",
                        help="YAML config file, or a shipped config name (demo, paper/fig2c; "
                        "see docs/config.md)")
    parser.add_argument("--set", dest="overrides", action="append", default=[],
                        metavar="KEY=VALUE", help="override a config key (repeatable)")


#: keys naming a file: relative in a config file, from the config's directory; relative
#: in a ``--set`` override, from the working directory (where the user typed it)
_FILE_KEYS = ("reference.file",)


def config_from_args(args: argparse.Namespace) -> Config:
    return load_config(args.config, [_from_cwd(o) for o in args.overrides])


def _from_cwd(override: str) -> str:
    key, sep, value = override.partition("=")
    if sep and key.strip() in _FILE_KEYS and value.strip() and not Path(value.strip()).is_absolute():
        return f"{key}={Path(value.strip()).absolute()}"
    return override
