"""Arguments and helpers shared by subcommands."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TextIO

from dobhil.config import Config, load_config, resolve_config
from dobhil.recording.layouts import DEFAULT_LAYOUT, LAYOUTS

#: exit code of a run that ended in a safety stop (not bad input)
EXIT_STOPPED = 1


def add_config_args(parser: argparse.ArgumentParser, *, required: bool = True) -> None:
    parser.add_argument("config", metavar="CONFIG", nargs=None if required else "?",
                        help="YAML config file, or a shipped config name (demo, paper/fig2c; "
                        "see docs/config.md)")
    parser.add_argument("--set", dest="overrides", action="append", default=[],
                        metavar="KEY=VALUE", help="override a config key (repeatable)")
    parser.add_argument("--set-file", dest="set_files", action="append", default=[], metavar="F.yaml",
                        help="override config keys from a YAML mapping of section.key: value, e.g. the "
                        "overlay of dobhil identify --out (repeatable; applied before --set)")


def output_path(text: str) -> Path:
    """argparse type of an output file or directory. An empty name is refused: as a Path it
    would be the working directory, and where a default exists it would stand for "not
    given" and pick the default file."""
    if not text.strip():
        raise argparse.ArgumentTypeError("an empty name; give a file or directory name")
    return Path(text)


def config_from_args(args: argparse.Namespace) -> Config:
    """The config a command works on; for a command that takes ``--axis``, the axis'
    (:func:`dobhil.cli.axis_option.axis_config`)."""
    if hasattr(args, "axis"):
        from dobhil.cli.axis_option import axis_config
        return axis_config(args)
    return load_config(args.config, args.overrides, args.set_files)


def design_on_drive(config: Config, args: argparse.Namespace, out: TextIO | None = None) -> Config:
    """The config as the design runs on its drive profile (``drive.profile``, looked up
    near the config; the files it names checked as its drive reads them, so a design
    command refuses what ``dobhil run`` would): the protocol's command delay when the
    profile fixes one (:func:`dobhil.drives.timing.effective_config`), its one-line note
    printed to ``out`` (stdout by default) when that changed the design's values."""
    from dobhil.config.load import resolve_config
    from dobhil.drives.load import load_drive_profile
    from dobhil.drives.registry import protocol
    from dobhil.drives.timing import effective_config
    profile = load_drive_profile(config, resolve_config(args.config).parent)
    protocol(profile.protocol).check_files(profile)   # bad input the run would refuse
    config, note = effective_config(config, profile)
    if note:
        print(note, file=out or sys.stdout)
    return config


def files_read(config: Config, args: argparse.Namespace) -> list[Path]:
    """The files a command reads for ``config`` -- the inputs its outputs may never
    overwrite: the config, its ``--set-file`` overlays, an overlay of ``--uncertainty-from``
    or ``--draw-from``, and the files the config names (a csv reference and a drive profile
    YAML, each where the run looks for it: beside the config, or as given)."""
    config_dir = resolve_config(args.config).parent if getattr(args, "config", None) else None
    files = [Path(f) for f in (getattr(args, "config", None), *getattr(args, "set_files", ()),
                               getattr(args, "uncertainty_from", None), getattr(args, "draw_from", None))
             if f]
    named = [config.drive.profile] if Path(config.drive.profile).suffix in (".yaml", ".yml") else []
    if config.reference.kind == "csv" and config.reference.file:
        named.append(config.reference.file)
    for name in named:
        files.append(Path(name))
        if config_dir is not None and not Path(name).is_absolute():
            files.append(config_dir / name)
    return files


def add_log_layout_arg(parser: argparse.ArgumentParser) -> None:
    """``--log-layout``: how ``--log`` lays out its messages (docs/recording.md)."""
    parser.add_argument("--log-layout", choices=LAYOUTS, default=DEFAULT_LAYOUT,
                        help="cycle: one /cycle message per control cycle holding its topics and CAN frames "
                             "(default); topics: a message per topic per cycle and per CAN frame, for tools "
                             "that read topics by name, about three times the bytes (docs/recording.md)")
