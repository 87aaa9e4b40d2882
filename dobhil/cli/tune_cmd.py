"""``dobhil tune CONFIG --range KEY=LO:HI [--range ...] [--uncertainty KEY=±P%] [--objective
rise_time|bandwidth] [--bound KEY=LO:HI] [--margin gm=DB,pm=DEG,ms=DB,os=PCT,noise=X] [--grid N]
[--seed S] [--out tuned.yaml] [--plot DIR] [--json]``."""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from dobhil.cli.axis_option import add_axis_arg, axis_keys
from dobhil.cli.common import add_config_args, config_from_args, design_on_drive, files_read, output_path
from dobhil.errors import ConfigError

if TYPE_CHECKING:
    from collections.abc import Callable, Sequence

    from dobhil.config.schema import Config
    from dobhil.tune.evaluate import Quanta
    from dobhil.tune.optimise import Generation, Objective, TuneResult
    from dobhil.tune.problem import Margins, Range, Uncertainty
    from dobhil.tune.report import Baseline

#: the files ``--plot DIR`` writes (:func:`dobhil.plotting.tune_figures.tune_figures`)
PLOT_NAMES = ("stability_map.png", "worst_step.png", "margins.png")

#: limits of --grid (values per range key) and of the whole fine grid
MAX_GRID = 400
MAX_GRID_POINTS = 250_000
#: the largest --seed: scipy's differential evolution seeds numpy's 32-bit RandomState
MAX_SEED = 2**32 - 1

#: the step is simulated over analysis.step_duration, or this long when it is 0 (automatic) [s]
DEFAULT_HORIZON = 0.2
MAX_HORIZON_SAMPLES = 5000

EXIT_INFEASIBLE = 1


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("tune", help="robust gains: the fastest force loop that keeps its margins over "
                       "an environment range", description=(
                           "Chooses design.dob_bandwidth, rtob_bandwidth, identified_inertia and force_gain "
                           "(scipy differential evolution, log scale) to minimise the worst-case rise time "
                           "(or maximise the worst-case bandwidth) of the force step on the sampled, "
                           "delayed loop, subject to stability and margins at every point of the --range "
                           "grid times the --uncertainty box; then checks the design on a --grid fine grid."))
    add_config_args(p)
    add_axis_arg(p)
    p.add_argument("--range", dest="ranges", action="append", default=[], metavar="KEY=LO:HI",
                   help="a plant or environment key's range (repeatable); log spaced when HI/LO >= 10")
    p.add_argument("--uncertainty", action="append", default=[], metavar="KEY=±P%",
                   help="a plant or environment key known to ±P %% (its ends and centre are checked)")
    p.add_argument("--uncertainty-from", metavar="OVERLAY.yaml",
                   help="the identified 95 %% intervals of an overlay of dobhil identify --out as the box (each "
                        "interval's ends and estimate are checked; keys outside the linear loop left out)")
    p.add_argument("--objective", choices=("rise_time", "bandwidth"), default="rise_time",
                   help="minimise the worst 10-90 %% rise time (default) or maximise the worst -3 dB "
                   "bandwidth of reference -> true force")
    p.add_argument("--bound", action="append", default=[], metavar="KEY=LO:HI",
                   help="search bounds of a design key (default: bandwidths 0.01/T..1.5/T, "
                   "identified_inertia 0.5..2x, force_gain 1/20..20x the config's)")
    p.add_argument("--margin", action="append", default=[], metavar="gm=DB,pm=DEG,ms=DB,os=PCT,noise=X",
                   help="constraints at every point (default gm=6 dB, pm=30 deg, ms=6 dB, os=20 %%; "
                   "noise: RMS of the estimate from the drive's quantisation [N m], no default)")
    p.add_argument("--grid", type=int, default=50, metavar="N", help="values per range key of the final check")
    p.add_argument("--seed", type=int, default=0, metavar="S", help="optimiser seed (same seed, same result)")
    p.add_argument("--generations", type=int, default=100, metavar="N", help="most generations per search")
    p.add_argument("--out", type=output_path, metavar="TUNED.yaml", help="write the config with the tuned design")
    p.add_argument("--plot", type=output_path, metavar="DIR", help="write the stability map, worst step, margins")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from dobhil.tune.optimise import Objective, tune
    from dobhil.tune.problem import parse_bounds, parse_margins
    axis_keys(args, {"ranges": "--range", "uncertainty": "--uncertainty", "bound": "--bound"})
    config = design_on_drive(config_from_args(args), args, sys.stderr if args.json else None)
    _check_outputs(args, files_read(config, args))
    notes: list[str] = []   # said once every input is checked: a refusal stays its one line
    ranges, uncertainties = _robust_keys(args, notes)
    _check_uncertain_values(config, uncertainties)
    _check_contact(config, ranges, uncertainties)
    margins, bounds = parse_margins(args.margin), parse_bounds(config, args.bound)
    _check_numbers(args, len(ranges), len(uncertainties))
    quanta = quantisation(config, Path(args.config))
    if margins.noise is not None and quanta is None:
        raise ConfigError("--margin noise: nothing quantises here (the drive profile has no codec model "
                          "and sensor.encoder_resolution is 0)")
    objective = Objective(args.objective)
    for line in notes:
        print(line, file=sys.stderr)
    horizon = _horizon(config)
    result = _with_progress(lambda cb: tune(config, ranges, uncertainties, bounds, margins, objective,
                                            seed=args.seed, grid=args.grid, horizon=horizon, quanta=quanta,
                                            maxiter=args.generations, progress=cb), args.json)
    base = _baseline(config, result, margins, objective, horizon, quanta)
    certificate = _certificate(config, result, ranges, uncertainties)
    _print(args, result, base, margins, ranges, uncertainties, certificate)
    if args.out and result.feasible:
        _write_config(args, result)
    if args.plot:
        _plots(args, config, result, base, horizon)
    if not result.feasible:
        from dobhil.tune.report import infeasible_line
        print(f"dobhil tune: {infeasible_line(result, (horizon - 1) * config.loop.period)}", file=sys.stderr)
        return EXIT_INFEASIBLE
    return 0


def _robust_keys(args: argparse.Namespace, notes: list[str]) -> tuple[list[Range], list[Uncertainty]]:
    from dobhil.tune.problem import parse_range, parse_uncertainty
    ranges = [parse_range(s) for s in args.ranges]
    uncertainties = [parse_uncertainty(s) for s in args.uncertainty]
    if args.uncertainty_from:
        from dobhil.cli.identified_box import identified_box
        uncertainties += identified_box(args.uncertainty_from, notes)
    if not ranges and not uncertainties:
        raise ConfigError("no robust set: give --range KEY=LO:HI, --uncertainty KEY=±P% or --uncertainty-from "
                          "OVERLAY.yaml")
    keys = [r.key for r in ranges] + [u.key for u in uncertainties]
    for k in keys:
        if keys.count(k) > 1:
            raise ConfigError(f"{k}: given more than once in --range / --uncertainty; give each key once")
    if args.uncertainty_from and notes:
        # a loop key the overlay did not identify (a pressed record tells the friction and
        # the damping only as their sum) and no --range gives is held at the config's value:
        # the box does not hold its truth, and its line says so beside the keys it took
        from dobhil.synthesis.params import PARAM_KEYS
        from dobhil.tune.problem import UNCERTAIN_PREFIXES
        held = [k for k in PARAM_KEYS if k.startswith(UNCERTAIN_PREFIXES) and k not in keys]
        if held:
            notes[-1] += f"; not identified, at the config's value: {', '.join(held)}"
    return ranges, uncertainties


def _check_uncertain_values(config: Config, uncertainties: Sequence[Uncertainty]) -> None:
    """±P % of a key whose config value is 0 is the one value 0: the box would add no
    point and the robust-set line would still claim the key's ends (paper/fig3 has no
    viscous friction). An identified interval (--uncertainty-from) has its own ends."""
    from dobhil.tune.problem import IntervalUncertainty
    flat = config.flat()
    for u in uncertainties:
        if not isinstance(u, IntervalUncertainty) and float(flat[u.key]) == 0.0:
            raise ConfigError(f"--uncertainty {u.key}=±{u.fraction * 100:g}%: the config's {u.key} is 0, so "
                              f"±P % of it is no range; give --range {u.key}=LO:HI instead")


def _check_contact(config: Config, ranges: Sequence[Range], uncertainties: Sequence[Uncertainty]) -> None:
    """A point of the set at K_env = 0 has no design that is stable there: the position, no
    longer held by a spring, drifts at every C_f (a closed-loop pole at z = 1 that no gain
    moves; the stability gate does not judge such a loop, README "The stability gate"). The
    search would run its generations to report that no design meets stability and to widen
    --bound or relax --margin, which cannot help."""
    key = "environment.stiffness"
    drift = "at K_env = 0 the position drifts at every C_f, so no design is stable there"
    for r in ranges:
        if r.key == key and r.lo == 0.0:
            raise ConfigError(f"--range {key}={r.lo:g}:{r.hi:g}: {drift}; start the range above 0")
    for u in uncertainties:
        if u.key == key and float(min(u.values(float(config.environment.stiffness)))) == 0.0:
            raise ConfigError(f"--uncertainty-from: the {key} interval reaches 0: {drift}; give --range {key}=LO:HI "
                              "with LO > 0 instead")
    if key not in [r.key for r in ranges] + [u.key for u in uncertainties] and config.environment.stiffness == 0.0:
        raise ConfigError(f"{key} is 0 in the config: {drift}; --set {key} above 0 or give --range {key}=LO:HI "
                          "with LO > 0")


def _check_numbers(args: argparse.Namespace, n_ranges: int, n_uncertain: int) -> None:
    if not 2 <= args.grid <= MAX_GRID:
        raise ConfigError(f"--grid {args.grid}: expected 2 .. {MAX_GRID} values per range key")
    total = args.grid ** n_ranges * 3 ** n_uncertain
    if total > MAX_GRID_POINTS:
        raise ConfigError(f"--grid {args.grid}: the check grid would have {total} points; at most "
                          f"{MAX_GRID_POINTS} (fewer values per key, or fewer keys)")
    if not 1 <= args.generations <= 10_000:
        raise ConfigError(f"--generations {args.generations}: expected 1 .. 10000")
    if not 0 <= args.seed <= MAX_SEED:
        raise ConfigError(f"--seed {args.seed}: expected a whole number from 0 to {MAX_SEED}")


def _check_outputs(args: argparse.Namespace, inputs: list[Path]) -> None:
    """--out and --plot before the search runs (it takes tens of seconds); ``inputs``: the
    files the command reads (:func:`dobhil.cli.common.files_read`)."""
    from dobhil.files import check_output, check_output_dir
    if args.out:
        check_output(args.out, inputs=inputs, suffix=(".yaml", ".yml"), what="--out")
    if args.plot:
        check_output_dir(args.plot, PLOT_NAMES, inputs=inputs, what="--plot")


def _horizon(config: Config) -> int:
    duration = config.analysis.step_duration or DEFAULT_HORIZON
    return max(20, min(MAX_HORIZON_SAMPLES, int(round(duration / config.loop.period)) + 1))   # t = 0 .. duration


def quantisation(config: Config, config_path: Path) -> Quanta | None:
    """The steps the drive quantises with: its protocol's codec's (position, velocity, torque;
    ``DriveProtocol.quantisation``) and/or the emulated encoder's count
    (``sensor.encoder_resolution``); None when neither."""
    import dataclasses
    from dobhil.config import resolve_config
    from dobhil.drives.load import load_drive_profile
    from dobhil.drives.registry import protocol
    from dobhil.tune.evaluate import Quanta
    quanta = Quanta(0.0, 0.0, 0.0)
    profile = load_drive_profile(config, resolve_config(str(config_path)).parent)
    steps = protocol(profile.protocol).quantisation(profile)
    if steps is not None:
        quanta = Quanta(steps.position, steps.velocity, steps.torque)
    counts = config.sensor.encoder_resolution
    if counts:
        quanta = dataclasses.replace(quanta, position=max(quanta.position, 2.0 * math.pi / counts))
    return None if quanta == Quanta(0.0, 0.0, 0.0) else quanta


def _with_progress(work: Callable[[Callable[[Generation], object]], TuneResult], quiet: bool) -> TuneResult:
    """The search with a line (or bar) per generation on stderr: its best worst case and its
    tightest constraint; nothing with --json."""
    from dobhil.cli.progress import progress
    with progress("tune", unit="generation", quiet=quiet) as shown:
        return work(lambda g: shown.update(1, generation_text(g)))


def generation_text(g: Generation) -> str:
    """``round 1 generation 12: best worst-case rise time 35.1 ms; overshoot active``."""
    from dobhil.tune.report import CONSTRAINT_TEXT, objective_text
    label, _, unit, _ = CONSTRAINT_TEXT[g.tightest]
    objective = "rise time" if g.objective == "rise_time" else "bandwidth"
    if g.active:
        limit = f"{label} active (at its limit)"
    elif g.slack < 0:
        limit = f"{label} broken by {-g.slack:.3g}{unit}"
    else:
        limit = f"tightest {label}, {g.slack:.3g}{unit} to spare"
    worst = math.inf if g.worst >= 1e6 else g.worst   # the optimiser's cap on an unstable candidate
    return (f"round {g.round} generation {g.generation}: best worst-case {objective} "
            f"{objective_text(g.objective, worst)}; {limit}")


def _baseline(config: Config, result: TuneResult, margins: Margins, objective: Objective, horizon: int,
              quanta: Quanta | None) -> Baseline:
    """The config's own design on the same fine grid."""
    import numpy as np
    from dobhil.realtime import one_blas_thread
    from dobhil.tune.evaluate import evaluate
    from dobhil.tune.optimise import worsts
    from dobhil.tune.problem import DECISION_KEYS
    from dobhil.tune.report import baseline
    flat = config.flat()
    design = {k: float(flat[k]) for k in DECISION_KEYS}
    with one_blas_thread():
        m = evaluate(config, np.array([[design[k] for k in DECISION_KEYS]]), result.grid.points,
                     horizon=horizon, quanta=quanta, bandwidth=objective.name == "bandwidth")
    return baseline(design, m, result.grid, objective, worsts(m, result.grid, margins, where=m.stable[0]))


def _certificate(config: Config, result: TuneResult, ranges: list[Range],
                 uncertainties: list[Uncertainty]) -> tuple[dict[str, Any] | None, list[str]]:
    """The chosen design certified over the whole box, not only the grid (dobhil certify)."""
    if not result.feasible:
        return None, []
    from dobhil.cli.certify_cmd import tuned_certificate
    return tuned_certificate(config, result.design, ranges, uncertainties)


def _print(args: argparse.Namespace, result: TuneResult, base: Baseline, margins: Margins, ranges: list[Range],
           uncertainties: list[Uncertainty], certificate: tuple[dict[str, Any] | None, list[str]]) -> None:
    from dobhil.tune.report import as_json, as_text, set_text
    if args.json:
        json.dump({**as_json(result, base, margins), "certificate": certificate[0]}, sys.stdout)
        sys.stdout.write("\n")
    else:
        print(as_text(result, base, set_text(ranges, uncertainties, args.grid)))
        for line in certificate[1]:
            print(line)


def _write_config(args: argparse.Namespace, result: TuneResult) -> None:
    from dobhil.config.load import read_set_file, read_yaml, resolve_config
    config_dir = resolve_config(args.config).parent
    if args.axis:   # the axis alone: a single-axis config of every key it runs with
        _write_tuned(args, _anchor_files(_sections(config_from_args(args).flat()), config_dir, args.out), result)
        return
    source: dict[str, Any] = read_yaml(resolve_config(args.config))
    flat_overrides: dict[str, Any] = {}
    for extra in args.set_files:
        flat_overrides.update(read_set_file(extra))
    flat_overrides.update(dict(_override(item) for item in args.overrides))
    for key, value in flat_overrides.items():
        section, name = key.split(".", 1)
        source.setdefault(section, {})[name] = value
    _write_tuned(args, _anchor_files(source, config_dir, args.out), result)


def _override(item: str) -> tuple[str, Any]:
    """A --set item as load_config reads it: a file typed on the command line is from the
    working directory (dobhil.config.load.CWD_PATH_KEYS)."""
    from dobhil.config.load import CWD_PATH_KEYS, parse_override
    name, value = parse_override(item)
    if name in CWD_PATH_KEYS and isinstance(value, str) and value:
        value = os.path.abspath(value)
    return name, value


def _anchor_files(sections: dict[str, Any], config_dir: Path, out: Path) -> dict[str, Any]:
    """``sections`` with the files the tuned run reads named so that they resolve from --out's
    directory as they did from the input config's: a relative ``reference.file`` is taken from
    the config's directory, and ``drive.profile`` from a ``drivers/`` near it (docs/config.md),
    so written unchanged beside another directory they would name another file, or none (an
    edited profile of ``dobhil init`` silently replaced by the shipped one)."""
    from dobhil.config.load import CWD_PATH_KEYS
    from dobhil.config.schema import Config
    from dobhil.drives.load import drive_profile_file
    out_dir = Path(out).resolve().parent
    for key in CWD_PATH_KEYS:
        section, name = key.split(".", 1)
        values = sections.get(section)
        if isinstance(values, dict) and isinstance(values.get(name), str) and values[name] \
                and not os.path.isabs(values[name]):
            values[name] = str((config_dir / values[name]).resolve())
    drive = sections.get("drive")
    profile = drive.get("profile") if isinstance(drive, dict) else None
    profile = Config().drive.profile if profile is None else profile
    if isinstance(profile, str) and profile:
        here = drive_profile_file(profile, config_dir).resolve()
        try:
            there: Path | None = drive_profile_file(profile, out_dir).resolve()
        except ConfigError:
            there = None
        if there != here:
            sections.setdefault("drive", {})["profile"] = str(here)
    return sections


def _write_tuned(args: argparse.Namespace, source: dict[str, Any], result: TuneResult) -> None:
    from dobhil.files import atomic_path
    from dobhil.tune.report import tuned_yaml
    command = "dobhil tune " + " ".join(shlex.quote(a) for a in sys.argv[2:]) if len(sys.argv) > 2 else "dobhil tune"
    with atomic_path(args.out) as tmp:
        tmp.write_text(tuned_yaml(source, result, command))
    if not args.json:
        print(f"wrote {args.out}")


def _sections(flat: dict[str, Any]) -> dict[str, Any]:
    """``{"plant.inertia": 0.3}`` -> ``{"plant": {"inertia": 0.3}}``."""
    out: dict[str, dict[str, Any]] = {}
    for key, value in flat.items():
        section, name = key.split(".", 1)
        out.setdefault(section, {})[name] = value
    return out


def _plots(args: argparse.Namespace, config: Config, result: TuneResult, base: Baseline, horizon: int) -> None:
    from dobhil.plotting.tune_figures import TunePlotData, tune_figures
    from dobhil.tune.evaluate import force_step
    from dobhil.tune.problem import DECISION_KEYS
    import numpy as np
    tuned = np.array([result.design[k] for k in DECISION_KEYS])
    config_design = np.array([base.design[k] for k in DECISION_KEYS])
    data = TunePlotData(
        keys=result.grid.keys, points={k: np.asarray(v) for k, v in result.grid.points.items()},
        gm_db=result.metrics.gm_db[0], baseline_stable=base.stable,
        worst_at=dict(result.worst_at), tuned_step=force_step(config, tuned, result.worst_at, horizon),
        config_step=force_step(config, config_design, result.worst_at, horizon),
        constraints=[(w.name, w.value, w.limit) for w in result.constraints if math.isfinite(w.limit)],
        tuned_stable=result.metrics.stable[0])
    paths = tune_figures(data, args.plot)
    if not args.json:
        print("wrote " + ", ".join(str(p) for p in paths))

