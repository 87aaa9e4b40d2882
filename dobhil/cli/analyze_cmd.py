"""``dobhil analyze CONFIG [--set k=v]... [--json] [--plot DIR]``."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from dobhil.cli.common import add_config_args, config_from_args, design_on_drive, output_path


#: the files ``--plot DIR`` writes (:func:`dobhil.plotting.figures.analysis_figures`)
PLOT_NAMES = ("root_locus.png", "step.png", "bode.png")


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("analyze", help="analyse a design: poles, zeros, stable gains, margins, step")
    add_config_args(p)
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--plot", metavar="DIR", type=output_path, help="write root locus, step and Bode PNGs")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from dobhil.config.axes import has_axes
    if has_axes(args.config):   # several axes: each alone, or coupled as one loop
        from dobhil.cli.axes_analyze import run as run_axes
        return run_axes(args, PLOT_NAMES)
    from dobhil.analysis.report import analyze, as_json, as_text
    # the design on its drive: a protocol that fixes the command delay sets it (the note
    # goes to stderr with --json, whose stdout is one JSON object)
    config = design_on_drive(config_from_args(args), args, sys.stderr if args.json else None)
    if args.plot:  # before the analysis: a bad directory fails at once, not after it
        from dobhil.files import check_output_dir
        check_output_dir(args.plot, PLOT_NAMES, inputs=[args.config], what="--plot")
    result = analyze(config)
    budget_line, budget = bus_budget(config, Path(args.config))
    quant_text, quant = quantisation(config, Path(args.config))
    if args.json:
        extra = {} if quant is None else {"quantisation": quant}
        json.dump({**as_json(result), "bus_budget": budget, **extra}, sys.stdout)
        sys.stdout.write("\n")
    else:
        print(as_text(result))
        print(budget_line)
        if quant_text:
            print(quant_text)
    if args.plot:
        from dobhil.plotting.figures import analysis_figures
        paths = analysis_figures(result.continuous, result.discrete, args.plot,
                                 f"({Path(args.config).stem})")
        if not args.json:
            print("wrote " + ", ".join(str(p) for p in paths))
    return 0


def bus_budget(config: Any, config_path: Path) -> tuple[str, dict[str, Any] | None]:
    """The run's bus budget (its line, and its dict for --json) from the config's drive
    profile; a profile that cannot be read makes the line say so (the design is still
    analysed: the profile matters to the bus, not to the analysis)."""
    from dobhil.config import resolve_config
    from dobhil.cli.check_cmd import run_budget
    from dobhil.drives.preflight import configured_bitrate
    from dobhil.drives.load import load_drive_profile
    from dobhil.errors import ConfigError
    try:
        profile = load_drive_profile(config, resolve_config(str(config_path)).parent)
        budget = run_budget(profile, config.loop.period, configured_bitrate(config.drive.bitrate, profile))
    except ConfigError as exc:
        return f"bus budget: not computed ({exc})", None
    if budget is None:
        return f"bus budget: not computed (protocol {profile.protocol!r} lists no frames)", None
    line = budget.line() + (f"; {budget.advice()}" if budget.over else "")
    return line, {"line": budget.line(), "advice": budget.advice(), **budget.as_dict()}


def quantisation(config: Any, config_path: Path) -> tuple[str, dict[str, Any] | None]:
    """The codec's quantisation figures (:mod:`dobhil.analysis.quantisation`) when the
    config's drive protocol models one (``DriveProtocol.quantisation``): its text and its
    dict for --json. ("", None) for a protocol without quantisation -- the output is then
    what it always was -- and for a profile that cannot be read (the bus budget line already
    says why). A model the protocol cannot find is said in the text and left out of --json."""
    from dobhil.config import resolve_config
    from dobhil.drives.load import load_drive_profile
    from dobhil.drives.registry import protocol
    from dobhil.errors import ConfigError
    try:
        profile = load_drive_profile(config, resolve_config(str(config_path)).parent)
    except ConfigError:
        return "", None
    try:
        codec = protocol(profile.protocol).quantisation(profile)
    except ConfigError as exc:
        return f"quantisation: not computed ({exc})", None
    if codec is None:
        return "", None
    from dobhil.analysis.quantisation import codec_figures, quantisation_text
    from dobhil.synthesis.params import params_from_config
    figures = codec_figures(params_from_config(config), codec)
    return quantisation_text(figures), figures.as_dict()
