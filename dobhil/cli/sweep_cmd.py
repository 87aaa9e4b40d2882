"""``dobhil sweep CONFIG --vary key=start:stop:num [--vary ...] [--sampled] [--out F.csv] [--plot F.png]
[--scheduler ADDRESS|local [--workers N]]``."""

from __future__ import annotations

import argparse
import csv
import sys
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

from dobhil.cli.axis_option import add_axis_arg, axis_keys
from dobhil.cli.common import add_config_args, config_from_args, design_on_drive, files_read, output_path
from dobhil.errors import ConfigError

if TYPE_CHECKING:
    import numpy as np

    from dobhil.analysis.sweep import ChunkMap, SweepResult
    from dobhil.config.schema import Config

Progress = Callable[[int], None]

#: grids at least this large show their progress (smaller ones take a few seconds)
PROGRESS_MIN_POINTS = 20_000

#: --plot formats (matplotlib picks the format from the suffix)
PLOT_SUFFIXES = (".png", ".svg", ".pdf")


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("sweep", help="stability, minimum phase and max stable C_f over a grid")
    add_config_args(p)
    add_axis_arg(p)
    p.add_argument("--vary", action="append", required=True, metavar="KEY=START:STOP:NUM",
                   help="a swept key: NUM values (a whole number, 1 or more) from START to STOP (repeatable); "
                   "KEY=log:START:STOP:NUM for log spacing")
    p.add_argument("--sampled", action="store_true", help="the sampled loop (loop.period, delay)")
    p.add_argument("--out", type=output_path, metavar="FILE.csv", help="write every grid point")
    p.add_argument("--plot", type=output_path, metavar="FILE.png", help="heat-map of max stable C_f")
    p.add_argument("--scheduler", metavar="ADDRESS|local",
                   help="run the grid's chunks as Dask tasks: on the scheduler at tcp://HOST:PORT, or on a "
                   "new local cluster of processes (local); the result is the same as without (see docs/cluster.md)")
    p.add_argument("--workers", type=int, metavar="N",
                   help="with --scheduler local: number of worker processes (default: one per core)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from dobhil.analysis.sweep import parse_vary, sweep
    axis_keys(args, {"vary": "--vary"})
    config = design_on_drive(config_from_args(args), args)   # the protocol's command delay
    axes = [parse_vary(v) for v in args.vary]
    if args.plot and len(axes) > 2:
        raise ConfigError("--plot draws one or two swept keys; got " + str(len(axes)))
    _check_outputs(args, files_read(config, args))
    _check_cluster_args(args)
    total = 1
    for a in axes:
        total *= a.values.size
    with _chunk_map(args) as map_chunks:
        result = _run_with_progress(
            lambda cb: sweep(config, axes, sampled=args.sampled, progress=cb, map_chunks=map_chunks), total)
    _summary(result, _drifting(config, result), result.drifting)
    if args.out:
        _write_csv(result, args.out)
        print(f"wrote {args.out}")
    if args.plot:
        from dobhil.plotting.sweep_plot import heatmap
        print(f"wrote {heatmap(result, args.plot)}")
    return 0


def _check_outputs(args: argparse.Namespace, inputs: list[Path]) -> None:
    """--out and --plot before the sweep runs (it can take minutes); ``inputs``: the files
    the command reads (:func:`dobhil.cli.common.files_read`)."""
    from dobhil.files import check_output
    if args.out:
        check_output(args.out, inputs=inputs, suffix=".csv", what="--out")
    if args.plot:
        check_output(args.plot, inputs=inputs, suffix=PLOT_SUFFIXES, what="--plot")
        if args.out and Path(args.out).absolute() == Path(args.plot).absolute():
            raise ConfigError("--out and --plot name the same file; give two names")


def _check_cluster_args(args: argparse.Namespace) -> None:
    """--scheduler and --workers before anything starts (a bad address: one line, exit 2)."""
    from dobhil.cluster import check_address
    if args.workers is not None and args.scheduler != "local":
        raise ConfigError("--workers N goes with --scheduler local (an existing scheduler has its own workers)")
    if args.workers is not None and args.workers < 1:
        raise ConfigError(f"--workers {args.workers}: must be at least 1")
    if args.scheduler not in (None, "local"):
        args.scheduler = check_address(args.scheduler)


@contextmanager
def _chunk_map(args: argparse.Namespace) -> Iterator[ChunkMap | None]:
    """None (the chunks one by one, here) or, with --scheduler, each chunk a Dask task on a
    cluster that is closed (or left, if it is the user's) when the sweep ends."""
    if args.scheduler is None:
        yield None
        return
    from dobhil.cluster import local_workers, map_values, open_client
    from dobhil.analysis.sweep import Chunk, ChunkAnswer

    workers = args.workers
    if args.scheduler == "local":   # the same cap as montecarlo's, said in one line
        workers, note = local_workers(args.workers)
        if note:
            print(f"sweep: {note}", file=sys.stderr, flush=True)
    with open_client(None if args.scheduler == "local" else args.scheduler, workers=workers) as client:
        def on_cluster(fn: Callable[[Chunk], ChunkAnswer], chunks: Sequence[Chunk],
                       done: Callable[[int], None]) -> list[ChunkAnswer]:
            # every chunk must come back: one that raised is what the local sweep would raise
            return map_values(client, fn, chunks, progress=done, key_prefix="dobhil-sweep")
        yield on_cluster


def _run_with_progress(work: Callable[[Progress], SweepResult], total: int) -> SweepResult:
    from dobhil.cli.progress import progress
    with progress("sweep", total=total, unit="point", quiet=total < PROGRESS_MIN_POINTS) as shown:
        return work(shown.update)


def _drifting(config: Config, result: SweepResult) -> np.ndarray:
    """The grid's points at K_env = 0 (swept there, or the config's): the position, held by
    no spring, drifts at every C_f -- a pole at s = 0 / z = 1 no gain moves, so the exact map
    has no stable C_f there (the stability gate does not judge such a loop, README "The
    stability gate")."""
    import numpy as np
    key = "environment.stiffness"
    keys = [a.key for a in result.axes]
    if key in keys:
        grids = np.meshgrid(*(a.values for a in result.axes), indexing="ij")
        return np.asarray(grids[keys.index(key)] == 0.0)
    return np.full(result.stable.shape, config.environment.stiffness == 0.0)


def _summary(result: SweepResult, at_zero: np.ndarray, unresolved: np.ndarray) -> None:
    """The grid's counts and the largest C_f safe at every point; points at K_env = 0
    (``at_zero``) have none, nor those where the stiffness is so small that the position's
    pole is within the analysis' resolution of the boundary (``unresolved``), so they are
    said apart and left out of it, else one such point makes it 0 whatever the rest allow."""
    import numpy as np
    drifting = at_zero | unresolved
    n = result.stable.size
    gains = result.max_stable_gain[~drifting]
    finite = gains[np.isfinite(gains)]
    n_unbounded = int(np.isinf(gains).sum())
    kind = "sampled" if result.sampled else "continuous"
    print(f"{n} point{'s' if n != 1 else ''} ({kind}): {int(result.stable.sum())} stable at "
          f"{'their' if n != 1 else 'its'} C_f, "
          f"{int(result.minimum_phase.sum())} minimum phase, "
          f"{n_unbounded} with unbounded C_f, "
          f"{int((result.interval_count > 1).sum())} conditionally stable")
    if result.unanswered:
        one = result.unanswered == 1
        print(f"{result.unanswered} point{'' if one else 's'} could not be analysed "
              f"({'its' if one else 'their'} matrices overflow or numpy cannot decompose them); "
              f"{'it is' if one else 'they are'} left empty in --out")
    drift = int(drifting.sum())
    pole = "z = 1" if result.sampled else "s = 0"
    only_zero = not (unresolved & ~at_zero).any()
    if drift:
        where_ = ("at environment.stiffness = 0" if only_zero else
                  "where environment.stiffness is 0 or too small to hold the position")
        within = "" if only_zero else ", or one within the analysis' resolution of it,"
        print(f"{drift} point{'s' if drift > 1 else ''} {where_}: the position drifts at every "
              f"C_f (a pole at {pole}{within} no C_f moves), so none is stable there"
              + ("; the largest safe C_f below is over the other points" if drift < n else ""))
    where = ("the whole grid" if not drift else "the points with environment.stiffness > 0" if only_zero
             else "the other points")
    if finite.size:
        print(f"largest C_f safe over {where}: {float(finite.min()):.6g}")
    elif n_unbounded:
        print(f"largest C_f safe over {where}: unbounded")


def _write_csv(result: SweepResult, path: Path) -> None:
    from dobhil.files import atomic_path
    rows = result.rows()
    with atomic_path(path) as tmp, tmp.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        for row in rows:
            writer.writerow({k: ("" if v is None else v) for k, v in row.items()})
