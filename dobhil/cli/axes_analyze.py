"""``dobhil analyze AXES.yaml``: a config with ``axes:``, each axis on its drive.

An axis no coupling joins to another is analysed as it would be alone (the single-axis
report of :mod:`dobhil.analysis.report`, one section per axis). Axes joined by couplings
(``environment.coupling``) are one closed loop (:mod:`dobhil.analysis.coupled`): its
stability, the largest scale of all their force gains that keeps it stable, the step of
each axis' force reference, and the python-control check of the loop
(:mod:`dobhil.analysis.coupled_check`). First, each bus' budget: the frames all its axes put
on it per period against its bit rate (:func:`dobhil.drives.axes.bus_budgets`).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from dobhil.config.axes import Axes, load_axes

#: the coupled step figure ``--plot DIR`` writes per group of coupled axes
COUPLED_PLOT = "coupled_step_{group}.png"


def run(args: argparse.Namespace, plot_names: tuple[str, ...]) -> int:
    """The command on an axes config; ``plot_names``: the single-axis figures ``--plot``
    writes (per independent axis, in ``DIR/NAME/``)."""
    from dobhil.analysis.coupled import axis_designs, coupled_groups
    axes = load_axes(args.config, args.overrides, args.set_files)
    out = sys.stderr if args.json else sys.stdout
    designs = {d.name: d for d in axis_designs(axes, _profiles(axes, Path(args.config)))}
    for d in designs.values():
        if d.note:
            print(f"axis {d.name}: {d.note}", file=out)
    groups = coupled_groups(axes)
    if args.plot:   # before the analysis: a bad directory fails at once, not after it
        _check_plot_dir(args, groups, plot_names)
    budgets = _budgets(axes, Path(args.config))
    result: dict[str, Any] = {"axes": {}, "coupled": [], "buses": [
        {"line": b.line(), "advice": b.advice(), **b.as_dict()} for b in budgets]}
    texts: list[str] = [b.line() for b in budgets]
    texts += [f"  {b.refusal() or b.advice()}" for b in budgets if b.over]
    for group in groups:
        if len(group) == 1:
            single, text = _single(designs[group[0]].config, args, group[0])
            result["axes"][group[0]] = single
            texts.append(text)
        else:
            coupled, text = _coupled(axes, [designs[n] for n in group], args)
            result["coupled"].append(coupled)
            texts.append(text)
    if args.json:
        json.dump(result, sys.stdout)
        sys.stdout.write("\n")
    else:
        print("\n".join(texts))
    return 0


def _profiles(axes: Axes, config_path: Path) -> dict[str, Any]:
    """Each axis' drive profile (its files checked as its drive reads them, so analyze
    refuses what ``dobhil run`` would)."""
    from dobhil.config.load import resolve_config
    from dobhil.drives.load import load_drive_profile
    from dobhil.drives.registry import protocol
    from dobhil.errors import ConfigError
    base = resolve_config(str(config_path)).parent
    profiles = {}
    for axis in axes.axes:
        try:
            profile = load_drive_profile(axis.config, base)
            protocol(profile.protocol).check_files(profile)
        except ConfigError as exc:
            raise ConfigError(f"axis {axis.name}: {exc}") from None
        profiles[axis.name] = profile
    return profiles


def _budgets(axes: Axes, config_path: Path) -> tuple[Any, ...]:
    """Each bus' budget with the frames of all its axes (:func:`dobhil.drives.axes.bus_budgets`,
    what ``dobhil check`` and ``dobhil run`` refuse over 100 %); said here, not refused."""
    from dobhil.config.load import resolve_config
    from dobhil.drives.axes import axis_drives, bus_budgets
    return bus_budgets(axis_drives(axes, resolve_config(str(config_path)).parent), axes.period)


def _group_name(group: tuple[str, ...]) -> str:
    return "_".join(group)


def _check_plot_dir(args: argparse.Namespace, groups: tuple[tuple[str, ...], ...],
                    plot_names: tuple[str, ...]) -> None:
    from dobhil.files import check_output_dir
    for group in groups:
        if len(group) == 1:
            check_output_dir(args.plot / group[0], plot_names, inputs=[args.config], what="--plot")
        else:
            check_output_dir(args.plot, [COUPLED_PLOT.format(group=_group_name(group))],
                             inputs=[args.config], what="--plot")


def _single(config: Any, args: argparse.Namespace, name: str) -> tuple[dict[str, Any], str]:
    """One independent axis: the single-axis report, its lines indented under its name."""
    from dobhil.analysis.report import analyze, as_json, as_text
    from dobhil.errors import AnalysisError
    try:
        result = analyze(config)
    except AnalysisError as exc:
        raise AnalysisError(f"axis {name}: {exc}") from None
    lines = [f"axis {name} (no coupling):", *("  " + line for line in as_text(result).splitlines())]
    if args.plot:
        from dobhil.plotting.figures import analysis_figures
        paths = analysis_figures(result.continuous, result.discrete, args.plot / name,
                                 f"({Path(args.config).stem}, axis {name})")
        lines.append("  wrote " + ", ".join(str(p) for p in paths))
    # the JSON only where it is printed: its sensitivities are most of the analysis' cost
    return (as_json(result) if args.json else {}), "\n".join(lines)


def _coupled(axes: Axes, designs: list[Any], args: argparse.Namespace) -> tuple[dict[str, Any], str]:
    from dobhil.analysis.coupled_analysis import analyze_coupled
    from dobhil.analysis.coupled_check import CheckUnavailable, LoopCheck, check_loop
    from dobhil.analysis.coupled_report import coupled_json, coupled_text
    names = {d.name for d in designs}
    couplings = [c for c in axes.couplings if c.a in names]
    result = analyze_coupled(designs, couplings)
    checks: dict[str, LoopCheck | str] = {}
    for key, domain in (("continuous", result.continuous), ("discrete", result.discrete)):
        try:
            checks[key] = check_loop(domain.loop, designs, couplings)
        except CheckUnavailable as exc:
            checks[key] = str(exc)
    j = coupled_json(result, checks)
    text = coupled_text(j)
    if args.plot:
        from dobhil.plotting.axes_figures import coupled_step_figure
        path = args.plot / COUPLED_PLOT.format(group=_group_name(tuple(d.name for d in designs)))
        text += f"\n  wrote {coupled_step_figure(result, path, f'({Path(args.config).stem})')}"
    return j, text
