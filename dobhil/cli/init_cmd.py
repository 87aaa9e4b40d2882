"""``dobhil init DIR``: copy the shipped configs and drive profiles into DIR for editing."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("init", help="copy the shipped configs and drive profiles into DIR to edit them")
    p.add_argument("dir", metavar="DIR", type=_directory, help="target directory (created; nothing is overwritten)")
    p.set_defaults(func=run)


def _directory(text: str) -> Path:
    """DIR as given; an empty string is refused (``Path("")`` would quietly be ``.``)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("empty; give a directory, e.g. dobhil init my-project")
    return Path(text)


def run(args: argparse.Namespace) -> int:
    from dobhil.data import copy_shipped
    written = copy_shipped(args.dir)
    yaml = [p.relative_to(args.dir).parts[0] for p in written if p.suffix in (".yaml", ".yml")]
    configs, profiles = yaml.count("configs"), yaml.count("drivers")
    print(f"copied {configs} configs to {args.dir / 'configs'} and {profiles} drive profiles "
          f"to {args.dir / 'drivers'} ({len(written)} files)")
    print(f"next: dobhil run {args.dir / 'configs' / 'demo.yaml'} --emulate --lockstep "
          f"(a profile name in a config is looked up in {args.dir / 'drivers'} first)")
    return 0
