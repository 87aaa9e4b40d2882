"""``dobhil demo``: the main job on a fresh clone -- a force-control run of ``configs/demo.yaml``
(the paper's Fig. 3 servo touching its environment, then a force step) over an emulated
ODrive on a CAN bus, in lockstep; prints a summary and writes a PNG."""

from __future__ import annotations

import argparse
from pathlib import Path

from dobhil.cli.common import add_config_args


def demo_config_path() -> Path:
    return Path(__file__).resolve().parents[2] / "configs" / "demo.yaml"


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("demo", help="emulated force-control run of configs/demo.yaml, with a plot")
    add_config_args(p, required=False)
    p.add_argument("--out", type=Path, default=Path("out/demo"), help="output directory")
    p.add_argument("--realtime", action="store_true", help="real time instead of lockstep")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from dobhil.cli.run_cmd import EXIT_STOPPED, report
    from dobhil.config import load_config
    from dobhil.plotting.run_plot import run_figure
    from dobhil.runtime.session import RunSession, summary
    path = Path(args.config) if args.config else demo_config_path()
    config = load_config(path, args.overrides)
    with RunSession(config, emulate=True, lockstep=not args.realtime,
                    config_dir=path.parent) as session:
        result = session.run()
        info = summary(session, result)
    report(info, result.stop.line(), as_json=False)
    png = run_figure(result.trace, args.out / "demo_run.png",
                     "dobhil demo: contact, then a force step (emulated ODrive, 1 kHz)")
    print(f"wrote {png}")
    return 0 if result.stop.reason.name == "DONE" else EXIT_STOPPED
