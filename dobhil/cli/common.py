"""Arguments and helpers shared by subcommands."""

from __future__ import annotations

import argparse

from dobhil.config import Config, load_config


def add_config_args(parser: argparse.ArgumentParser, *, required: bool = True) -> None:
    parser.add_argument("config", metavar="CONFIG", nargs=None if required else "?",
                        help="YAML config file, or a shipped config name (demo, paper/fig2c; "
                        "see docs/config.md)")
    parser.add_argument("--set", dest="overrides", action="append", default=[],
                        metavar="KEY=VALUE", help="override a config key (repeatable)")


def config_from_args(args: argparse.Namespace) -> Config:
    return load_config(args.config, args.overrides)
