"""``dobhil montecarlo CONFIG --runs N --vary KEY=DIST [--vary ...] [--seed S] [--duration S]
[--scheduler ADDRESS] [--workers N] [--out DIR] [--format csv|parquet] [--plot]``."""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

from dobhil.cli.axis_option import add_axis_arg, axis_keys
from dobhil.cli.common import add_config_args, output_path
from dobhil.errors import ConfigError

if TYPE_CHECKING:
    from dobhil.campaign.campaign import Campaign, Summary
    from dobhil.campaign.compare import Floors
    from dobhil.campaign.draws import Vary
    from dobhil.campaign.tally import Tally
    from dobhil.config.schema import Config

#: exit code when any run did not succeed (the table is still written)
EXIT_SOME_FAILED = 1

#: --plot files in --out
PLOTS = ("metrics.png", "vary.png")

#: the largest --seed: every row carries it in the table's seed column, a 64-bit integer
#: (dobhil.campaign.table.INTEGER; Parquet's int64), which a larger one overflowed after the
#: whole campaign had run
MAX_SEED = 2**63 - 1


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("montecarlo", help="N lockstep emulated runs over parameter distributions, on Dask",
                       description="Runs the whole stack (codec, quantisation, friction, saturation) N times "
                       "in lockstep against the emulator, each with values drawn for the --vary keys, as "
                       "Dask tasks. The same --seed gives the same table whatever the number of workers. "
                       "Without noise in the config, sensor.encoder_resolution=16384 and "
                       "sensor.velocity_noise=0.01 are set (--set overrides). See docs/montecarlo.md.")
    add_config_args(p)
    add_axis_arg(p)
    p.add_argument("--runs", type=int, required=True, metavar="N", help="number of runs")
    p.add_argument("--draw-from", metavar="OVERLAY.yaml",
                   help="draw the identified keys of an overlay of dobhil identify --out jointly: normal with its "
                        "estimates and covariance, truncated to physical (>= 0) values")
    p.add_argument("--vary", action="append", default=[], metavar="KEY=DIST",
                   help="a drawn numeric key (repeatable); DIST normal:MEAN:STD, uniform:LO:HI or "
                   "loguniform:LO:HI (LO > 0)")
    p.add_argument("--seed", type=int, default=0, metavar="S", help="campaign seed (default 0)")
    p.add_argument("--duration", type=float, metavar="S", help="each run's duration (default loop.duration)")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="tcp://HOST:PORT of a running Dask scheduler (default: a local cluster of processes)")
    p.add_argument("--workers", type=int, metavar="N",
                   help="worker processes of the local cluster (default: one per core)")
    p.add_argument("--out", type=output_path, metavar="DIR", help="write runs.csv (or .parquet) and summary.json here")
    p.add_argument("--format", choices=("csv", "parquet"), default="csv", help="table format (parquet: pyarrow)")
    p.add_argument("--plot", action="store_true", help="also write metrics.png and vary.png to --out")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """The runs stream: each spec drawn when the cluster has room for it, each row into the
    table and the tally as it comes (in run order), so memory does not grow with --runs."""
    drawn: list[str] = []
    campaign, noise = build_campaign(args, drawn)
    scheduler, workers, note = check_execution(args)
    out_dir = check_outputs(args)
    # once every input is checked: bad input stays its one line
    for line in [*drawn, *([f"montecarlo: {note}"] if note else [])]:
        print(line, file=sys.stderr, flush=True)
    started = time.perf_counter()
    with table(out_dir, args, campaign) as write:
        reference, tally = execute(campaign, scheduler, workers, header(campaign, noise, scheduler, workers), write)
    elapsed = time.perf_counter() - started
    from dobhil.campaign.campaign import summary_of
    summary = summary_of(tally, reference, floors(campaign, reference))
    report(summary, campaign, elapsed)
    if out_dir is not None:
        write_outputs(out_dir, args, campaign, tally, summary, elapsed)
    return 0 if summary.succeeded == summary.runs else EXIT_SOME_FAILED


# -- input ------------------------------------------------------------------

def build_campaign(args: argparse.Namespace, notes: list[str]) -> tuple[Campaign, tuple[str, ...]]:
    """The campaign asked for, every input checked (ConfigError before anything starts); and
    the noise overrides the campaign added (none when the config has noise); what --draw-from
    draws, appended to ``notes`` for the caller to print."""
    from dobhil.campaign.campaign import Campaign
    from dobhil.campaign.draws import parse_vary
    from dobhil.runtime.session import check_duration
    if args.runs is None or args.runs < 1:
        raise ConfigError(f"--runs {args.runs}: expected a whole number of runs >= 1")
    if not 0 <= args.seed <= MAX_SEED:
        raise ConfigError(f"--seed {args.seed}: expected a whole number from 0 to {MAX_SEED} (the table's seed "
                          "column is a 64-bit integer)")
    check_duration(args.duration)
    axis = axis_keys(args, {"vary": "--vary"}) or ""
    varies = tuple(parse_vary(v) for v in args.vary)
    if args.draw_from:
        from dobhil.cli.identified_box import joint_varies
        varies += joint_varies(args.draw_from, notes)
    if not varies:
        raise ConfigError("nothing to draw: give --vary KEY=DIST or --draw-from OVERLAY.yaml")
    _no_twice([v.key for v in varies])
    _no_drawn_duration(varies, args.duration)
    config = _as_path(args.config)
    set_files = tuple(_as_path(f) for f in args.set_files)
    noise = _noise(config, set_files, axis, tuple(args.overrides))
    campaign = Campaign(config=config, set_files=set_files, overrides=(*noise, *args.overrides),
                        varies=varies, runs=args.runs, seed=args.seed, duration=args.duration, axis=axis)
    _check_config(campaign)
    return campaign, noise


def _no_twice(keys: Sequence[str]) -> None:
    twice = sorted({k for k in keys if keys.count(k) > 1})
    if twice:
        raise ConfigError(f"--vary {twice[0]} given twice; give each key one distribution")


def _no_drawn_duration(varies: Sequence[Vary], duration: float | None) -> None:
    """--duration sets every run's length over its config's loop.duration (as ``dobhil run
    --duration`` does), so a drawn loop.duration would change no run while its column shows a
    spread of lengths the runs never had."""
    drawn = [v for v in varies if v.key == "loop.duration"]
    if drawn and duration is not None:
        raise ConfigError(f"--vary {drawn[0].text()} with --duration {duration:g}: --duration sets every run's "
                          "length, so the drawn loop.duration would change nothing; drop one of them")


def _as_path(name: str) -> str:
    """An existing file as an absolute path (worker processes may not share the working
    directory); a shipped config name as it is."""
    return os.path.abspath(name) if Path(name).is_file() else name


def _noise(config: str, set_files: tuple[str, ...], axis: str, overrides: tuple[str, ...] = ()) -> tuple[str, ...]:
    """The campaign's noise defaults when the config (with its --set-file) has neither noise
    nor quantisation; --set items come after them, so they override (an axis' keys: as its own).
    A default whose key a --set item sets is left out: never used, it would be said to be on
    (the header, each worst run's command)."""
    from dobhil.campaign.campaign import NOISE_DEFAULTS
    from dobhil.campaign.runner import load_run_config
    sensor = load_run_config(config, (), set_files, axis).sensor
    if sensor.velocity_noise or sensor.encoder_resolution:
        return ()
    defaults = tuple(f"axes.{axis}.{item}" for item in NOISE_DEFAULTS) if axis else NOISE_DEFAULTS
    given = {item.partition("=")[0].strip() for item in overrides}
    return tuple(item for item in defaults if item.partition("=")[0] not in given)


def _check_config(campaign: Campaign) -> None:
    """The reference run's session builds as each run's will (the shared config with --set,
    nothing drawn: its drive profile, its reference and that reference's file, the run's
    length in cycles): else every run would fail alike, and the campaign would be a table of
    errors with exit 1 for what is bad input. Nothing runs: an in-process emulator on a
    private bus is set up and closed (milliseconds)."""
    from dobhil.config import resolve_config
    from dobhil.runtime.session import RunSession
    spec = campaign.reference_spec()
    config = spec.load()
    with RunSession(config, emulate=True, lockstep=True, duration=spec.duration,
                    config_dir=resolve_config(spec.config).parent):
        pass
    _check_drawn_period(campaign)
    _check_drawn_read(campaign, config)


def _check_drawn_read(campaign: Campaign, config: Config) -> None:
    """A drawn key the controller never reads with this config's structure (a model's
    frequency unless that model is the sinusoid, the velocity filter's bandwidth unless the
    velocity is estimated: :func:`dobhil.synthesis.params.unused_keys`) is refused as the
    keys a lockstep run never reads are (docs/montecarlo.md): every run would run the same
    loop, and the table would show a spread of draws that changed nothing."""
    from dobhil.synthesis.params import first_unused
    u = first_unused(config, (v.key for v in campaign.varies))
    if u is not None:
        text = next(v.text() for v in campaign.varies if v.key == u.key)
        raise ConfigError(f"--vary {text}: the controller does not read {u.key} ({u.choice} is {u.value}, "
                          f"not {u.wanted}), so every draw would run the same loop; --set {u.choice}={u.wanted} to "
                          "draw it")


def _check_drawn_period(campaign: Campaign) -> None:
    """A drawn ``loop.period`` that almost surely refuses every run: every run is a
    single-axis lockstep one, whose bus sends a frame the drive sends periodically (a SYNC)
    only every whole number of loop periods (:func:`~dobhil.runtime.session.check_lockstep`),
    and whose loop takes one cycle per frame of a drive whose feedback streams
    (:func:`~dobhil.runtime.session.check_lockstep_feedback`); a period drawn from a spread
    distribution is almost surely neither a divisor of the one nor equal to the other
    (a point, normal with a standard deviation of 0, is the reference's period)."""
    from dobhil.campaign.draws import Kind
    from dobhil.config import resolve_config
    from dobhil.drives.load import load_drive_profile
    from dobhil.drives.registry import protocol
    drawn = [v for v in campaign.varies if v.key == "loop.period" and not (v.kind is Kind.NORMAL and v.b == 0)]
    if not drawn:
        return
    config = campaign.reference_spec().load()
    profile = load_drive_profile(config, resolve_config(campaign.config).parent)
    name, drive = profile.name or profile.protocol, protocol(profile.protocol)
    head = f"--vary {drawn[0].text()}: each run is lockstep"
    keep = f"keep loop.period fixed (the config's {config.loop.period:g} s runs)"
    for send in drive.periodic_sends(profile):
        raise ConfigError(
            f"{head}, whose bus sends a periodic frame only every whole number of loop periods, and drive profile "
            f"{name!r} sends {send.what} every {send.period:g} s ({send.key}), which a drawn loop.period almost "
            f"never divides; {keep}")
    if drive.feedback_streams and profile.feedback_period is not None:
        raise ConfigError(
            f"{head}, one cycle per feedback frame, and drive profile {name!r} sends its feedback every "
            f"{profile.feedback_period:g} s (feedback_period), which a drawn loop.period almost never equals; {keep}")


def check_execution(args: argparse.Namespace) -> tuple[str | None, int | None, str | None]:
    """The scheduler's address (None: a local cluster), the local cluster's workers and the
    note when --workers was capped at the usable cores (:func:`dobhil.cluster.local_workers`);
    --workers only for a local cluster."""
    from dobhil.cluster import check_address, local_workers
    if args.workers is not None and args.workers < 1:
        raise ConfigError(f"--workers {args.workers}: expected a whole number >= 1")
    if args.scheduler is None or args.scheduler == "local":
        return None, *local_workers(args.workers)
    if args.workers is not None:
        raise ConfigError("--workers sizes the local cluster; a --scheduler has its own workers")
    return check_address(args.scheduler), None, None


def check_outputs(args: argparse.Namespace) -> Path | None:
    """--out DIR before the campaign starts: writable, and none of its files there already."""
    from dobhil.campaign.table import check_format, table_name
    from dobhil.files import OutputError, check_output_dir
    check_format(args.format)
    if args.out is None:
        if args.plot:
            raise ConfigError("--plot writes its figures into --out DIR; give --out")
        if args.format != "csv":   # the default: nothing asked for; another would be silently not written
            raise ConfigError(f"--format {args.format} writes the table into --out DIR; give --out")
        return None
    names = [table_name(args.format), "summary.json", *(PLOTS if args.plot else ())]
    out = check_output_dir(args.out, names, inputs=[args.config, *args.set_files], what="--out")
    for name in names:
        if (out / name).exists():
            raise OutputError(f"--out {out}: {name} exists; refusing to overwrite a campaign's results "
                              "(give a new directory)")
    return out


# -- running ----------------------------------------------------------------

def header(campaign: Campaign, noise: tuple[str, ...], scheduler: str | None, workers: int | None) -> str:
    where = (f"scheduler {scheduler}" if scheduler else
             f"a local cluster of {_count(workers or os.cpu_count() or 1, 'worker process')}")
    # a drawn loop.duration (refused with --duration) gives each run its own length: the
    # config's would be no run's
    drawn = next((v for v in campaign.varies if v.key == "loop.duration"), None)
    length = (f"{campaign.duration:g} s each" if campaign.duration is not None
              else f"each its drawn loop.duration, {drawn.text().partition('=')[2]}" if drawn is not None
              else f"{_config_duration(campaign):g} s each, from loop.duration")
    said = (f"noise on: {', '.join(noise)} (the config had none; --set overrides)" if noise
            else "noise: the config's")
    of = f"{campaign.config} axis {campaign.axis}" if campaign.axis else campaign.config
    return (f"montecarlo: {campaign.runs} runs of {of} ({length}, lockstep, emulated), "
            f"seed {campaign.seed}, on {where}; {said}")


def _count(n: int, what: str) -> str:
    return f"{n} {what}" + ("" if n == 1 else "es" if what.endswith("s") else "s")


def _config_duration(campaign: Campaign) -> float:
    """The runs' length without --duration: the config's (with the campaign's overrides)."""
    return float(campaign.load().loop.duration)


def execute(campaign: Campaign, scheduler: str | None, workers: int | None, said: str,
            write: Callable[[dict[str, Any]], None] | None = None) -> tuple[dict[str, Any], Tally]:
    """The reference run and the runs on the cluster, streamed (:func:`dobhil.campaign.campaign.stream`):
    each row to ``write`` (the table) and the tally in run order. ``said`` (the header line)
    is printed once the cluster is there, so that a scheduler that does not answer ends in
    its one error line alone. Progress on stderr from the first run back: runs done,
    failed, rate, time left."""
    from dobhil.campaign.campaign import WORST, execute as run_all, stream
    from dobhil.campaign.tally import Tally, succeeded
    from dobhil.cli.progress import progress
    from dobhil.cluster import open_client
    tally = Tally([v.key for v in campaign.varies], campaign.seed, worst=WORST)
    with open_client(scheduler, workers=workers) as client:
        print(said, flush=True)
        reference = run_all(client, [campaign.reference_spec()])[0]
        failed = [0]
        with progress("montecarlo", total=campaign.runs, unit="run") as shown:
            def one(row: dict[str, Any]) -> None:
                failed[0] += not succeeded(row)
                shown.update(1, f"{failed[0]} failed")
            for row in stream(client, campaign.specs(), progress=one):
                tally.add(row)
                if write is not None:
                    write(row)
    return reference, tally


@contextmanager
def table(out: Path | None, args: argparse.Namespace,
          campaign: Campaign) -> Iterator[Callable[[dict[str, Any]], None] | None]:
    """The table's writer (None without --out): rows go to disk as they come."""
    if out is None:
        yield None
        return
    from dobhil.campaign.table import table_name, table_writer
    integer_keys = [v.key for v in campaign.varies if v.integer]
    with table_writer(campaign.columns(), out / table_name(args.format), args.format, integer_keys) as write:
        yield write


def floors(campaign: Campaign, reference: dict[str, Any]) -> Floors:
    """The tolerance floors of the comparison with the reference: the loop period, and the
    command at the reference run's end."""
    from dobhil.campaign.compare import Floors
    period = float(campaign.load().loop.period)
    return Floors.of(period, reference.get("final_tau_ref"))


# -- output -----------------------------------------------------------------

def report(summary: Summary, campaign: Campaign, elapsed: float) -> None:
    print(f"{summary.runs} runs in {elapsed:.1f} s: {summary.succeeded} succeeded "
          f"({100 * summary.rate:.1f} %, 95 % CI {100 * summary.ci_low:.1f}-{100 * summary.ci_high:.1f} %, "
          f"Clopper-Pearson); {summary.retried} retried")
    for line in metric_lines(summary):
        print(line)
    print(f"worst {len(summary.worst)} runs (each alone: the command below it):")
    from dobhil.campaign.campaign import reproduce_command
    for row in summary.worst_rows:
        print(f"  {describe_row(row, campaign)}")
        print(f"    {reproduce_command(campaign.spec(int(row['run'])))}")


def metric_lines(summary: Summary) -> list[str]:
    """The reference run, each metric's percentiles over the runs that have it (how many,
    and why the others have none), its median against the reference, and the flags."""
    from dobhil.campaign.compare import RELATIVE, RULES, SYMBOL, Unit, Worse
    from dobhil.campaign.runner import METRICS
    ref = summary.reference or {}
    compared = {c.metric: c for c in summary.comparisons}
    lines = [_reference_line(ref)] if summary.reference is not None else []
    if summary.sampled:
        lines.append(f"  (percentiles of a uniform sample of {summary.sampled} of the {summary.runs} runs; "
                     "counts and max over all of them)")
    for name in METRICS:
        p = summary.percentiles.get(name)
        if p is None:
            lines.append(f"  {name}: none of {summary.runs} runs has one{_missing(name, 0, summary)}")
            continue
        unit = SYMBOL[RULES.get(name, (Worse.LARGER, Unit.TORQUE))[1]]
        text = (f"  {name}: p5 {p['p5']:.4g}, p50 {p['p50']:.4g}, p95 {p['p95']:.4g}, max {p['max']:.4g} {unit} "
                f"over {int(p['n'])} of {summary.runs} runs{_missing(name, int(p['n']), summary)}")
        c = compared.get(name)
        if c is not None:
            how = "off" if RULES.get(name, (Worse.LARGER,))[0] is Worse.OFF else None
            text += (f"; reference {c.reference:.4g}, p50 {_past_text(c.past, how)} (tolerance {c.tolerance:.3g})"
                     + (": WORSE than the reference" if c.worse else ""))
        lines.append(text)
    lines += _settling_lines(summary, ref) + _command_lines(summary)
    if summary.reference is not None:
        lines.append(f"  (tolerance: {100 * RELATIVE:g} % of the reference's value, at least 1 % of the "
                     "command for torques, 2 loop periods for times, 1 point for overshoot)")
    return lines


def _reference_line(ref: dict[str, Any]) -> str:
    from dobhil.campaign.runner import METRICS
    if ref.get("error"):
        return f"reference run (the config as given, nothing drawn): error {ref['error']}"
    values = ", ".join(f"{m} {'-' if ref.get(m) is None else format(ref[m], '.4g')}" for m in METRICS)
    settled = {True: "settled", False: "never settled", None: ""}[ref.get("settled")]
    return (f"reference run (the config as given, nothing drawn): stop {ref.get('stop_reason')}; {values}"
            + (f"; {settled}" if settled else ""))


def _missing(name: str, n: int, summary: Summary) -> str:
    left = summary.runs - n
    if not left:
        return ""
    if name == "settling_time" and summary.never_settled:
        others = left - summary.never_settled
        return f"; {summary.never_settled} never settled" + (f", {others} without a step response" if others else "")
    return f"; {left} without one"


def _past_text(past: float, how: str | None) -> str:
    """``worse by 0.01`` / ``better by ..`` (``off by`` for a level, off either way)."""
    if not past:
        return "equal"
    return f"{how or ('worse' if past > 0 else 'better')} by {abs(past):.3g}"


def _settling_lines(summary: Summary, ref: dict[str, Any]) -> list[str]:
    if not summary.never_settled:
        return []
    if ref.get("settled") is False:
        return ["  settling: the reference never settles into the 2 % band within the run either"]
    if ref.get("settled"):
        return [f"  settling: WORSE than the reference: {summary.never_settled} of {summary.runs} runs never "
                "settle into the 2 % band within the run; the reference does"]
    return []


def _command_lines(summary: Summary) -> list[str]:
    c = summary.command
    if c is None:
        return []
    lines = []
    if c.runs_off:
        lines.append(f"  final_tau_int_true: runs end at {c.p5:.4g}..{c.p95:.4g} N m (p5..p95), OFF the command "
                     f"{c.command:.4g} N m by more than the tolerance {c.tolerance:.3g} N m")
    if c.reference_off and c.reference is not None:
        lines.append(f"  final_tau_int_true: the reference itself ends at {c.reference:.4g} N m, OFF the command "
                     f"{c.command:.4g} N m by more than {c.tolerance:.3g} N m")
    return lines


def describe_row(row: dict[str, Any], campaign: Campaign) -> str:
    drawn = ", ".join(f"{v.key}={row[v.key]:.6g}" for v in campaign.varies)
    rms = row["force_rms_error"]
    how = f"error {row['error']}" if row["error"] else f"stop {row['stop_reason']}"
    return (f"run {row['run']}: {how}; force_rms_error {'-' if rms is None else f'{rms:.4g}'}; {drawn}"
            + ("; retried" if row["retried"] else ""))


def write_outputs(out: Path, args: argparse.Namespace, campaign: Campaign, tally: Tally,
                  summary: Summary, elapsed: float) -> None:
    """The table is already written (it streamed); the summary, and the plots of the tally's sample."""
    from dobhil.campaign.table import table_name
    print(f"wrote {out / table_name(args.format)}")
    print(f"wrote {_write_summary(out / 'summary.json', campaign, summary, elapsed)}")
    if args.plot:
        for path in plot(out, campaign, tally):
            print(f"wrote {path}")


def _write_summary(path: Path, campaign: Campaign, summary: Summary, elapsed: float) -> Path:
    from dobhil.campaign.campaign import reproduce_command
    from dobhil.files import atomic_path
    data = {"config": campaign.config, "axis": campaign.axis or None, "seed": campaign.seed,
            "duration": campaign.duration,
            "vary": [v.text() for v in campaign.varies], "overrides": list(campaign.overrides),
            "set_files": list(campaign.set_files), "wall_time_s": elapsed, **summary.as_dict(),
            "reference_command": reproduce_command(campaign.reference_spec()),
            "worst": [{"run": r["run"], "error": r["error"], "stop_reason": r["stop_reason"],
                       "force_rms_error": r["force_rms_error"],
                       "command": reproduce_command(campaign.spec(int(r["run"])))}
                      for r in summary.worst_rows]}
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2) + "\n")
    return path


def plot(out: Path, campaign: Campaign, tally: Tally) -> list[Path]:
    """The figures of the tally's rows: every run up to its sample size, a uniform sample past it."""
    from dobhil.campaign.runner import METRICS
    from dobhil.plotting.campaign_figures import metric_histograms, vary_scatter
    return [metric_histograms({m: tally.column(m) for m in METRICS}, tally.kept, out / PLOTS[0]),
            vary_scatter({v.key: tally.column(v.key) for v in campaign.varies}, tally.column("force_rms_error"),
                         tally.ok(), out / PLOTS[1])]
