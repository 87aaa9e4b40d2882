"""The instability watch's figures: detection delays and the margins of stable runs.

    python tools/instability_margins.py [--json]

Runs each shipped force config (``configs/``: the demo on an ODrive, on CiA 402 and on an
AK80-9 in MIT mode, the paper's Fig. 2 and 3 designs) with ``--emulate --lockstep`` through
:class:`dobhil.runtime.session.RunSession` at multiples of the sampled loop's max stable
C_f (``dobhil analyze``, the design on its drive), plus the demo designs started at rest in
contact with a 0.02 N m reference (the slow-growth case). One line per run: the sampled and
continuous verdicts, the stop, the cycles from the first clipped command (or, for a stop below
the limit, from the command's first move of the hysteresis' size) to the stop, and the watch's
peaks. Then, over every run the sampled analysis calls stable, the largest value of each
statistic against its threshold.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from dobhil.analysis.report import analyze
from dobhil.config import load_config
from dobhil.config.load import resolve_config
from dobhil.drives.load import load_drive_profile
from dobhil.drives.timing import effective_config
from dobhil.runtime.session import RunSession

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
FORCE = ("demo", "cia402-demo", "mit-demo", "paper/fig2a", "paper/fig2b", "paper/fig2c",
         "paper/fig2d", "paper/fig3")
FACTORS = (0.3, 0.5, 0.8, 0.9, 0.95, 1.05, 1.1, 1.25, 1.5, 2.0, 5.0)
AT_REST = ("plant.initial_position=0", "reference.offset=0.02", "reference.amplitude=0")
REST_FACTORS = (0.5, 0.8, 0.95, 1.01, 1.02, 1.05, 1.1)


def max_gains(path: Path, sets: tuple[str, ...]) -> tuple[float, float]:
    config = load_config(path, list(sets))
    design, _ = effective_config(config, load_drive_profile(config, resolve_config(path).parent))
    a = analyze(design)
    return float(a.discrete.gains.max_stable_gain), float(a.continuous.gains.max_stable_gain)


def one_run(name: str, factor: float, sets: tuple[str, ...]) -> dict[str, Any]:
    path = CONFIGS / f"{name}.yaml"
    kmax, _ = max_gains(path, sets)
    config = load_config(path, [*sets, f"design.force_gain={factor * kmax!r}"])
    with RunSession(config, emulate=True, lockstep=True, config_dir=path.parent) as session:
        a = analyze(session.design_config)
        result = session.run()
        assert session.loop is not None and session.loop.watch is not None
        watch = session.loop.watch
    u, limit = result.trace["u_unsat"], session.controller.torque_limit
    clipped = np.flatnonzero(np.abs(u) >= limit)
    moved = np.flatnonzero(np.abs(np.diff(u)) >= watch.s.hysteresis * limit)
    onset = int(clipped[0]) if clipped.size else (int(moved[0]) if moved.size else None)
    stopped = result.stop.reason.name.lower()
    return {"config": name, "at_rest": bool(sets), "factor": factor, "force_gain": factor * kmax,
            "stable": bool(a.discrete.stable), "continuous_stable": bool(a.continuous.stable),
            "stop": stopped, "cycle": result.stop.cycle,
            "delay": result.stop.cycle - onset if stopped == "unstable" and onset is not None else None,
            "from": "clip" if clipped.size else "move", "rule": result.stop.detail.split(" ")[0],
            "peaks": vars(watch.peaks).copy(), "window": watch.s.window,
            "thresholds": {"chatter": 1.0, "saturation": watch.s.saturation, "limit_reversals": watch.s.limit_reversals,
                           "growth_swings": watch.s.growth_swings, "growth": watch.s.growth}}


def runs() -> list[dict[str, Any]]:
    out = [one_run(name, f, ()) for name in FORCE for f in FACTORS]
    out += [one_run(name, f, AT_REST) for name in ("demo", "cia402-demo", "mit-demo") for f in REST_FACTORS]
    return out


def margins(rows: list[dict[str, Any]]) -> dict[str, Any]:
    stable = [r for r in rows if r["stable"]]
    t = rows[0]["thresholds"]
    return {k: {"largest_stable": max(r["peaks"][k] for r in stable), "threshold": t[k]}
            for k in ("saturation", "limit_reversals", "chatter", "growth_swings")}


def line(r: dict[str, Any]) -> str:
    p = r["peaks"]
    delay = "-" if r["delay"] is None else f"{r['delay']} from {r['from']}"
    return (f"{r['config']:<12} {'rest ' if r['at_rest'] else '     '}x{r['factor']:<5g} C_f {r['force_gain']:8.4g} "
            f"{'stable  ' if r['stable'] else 'UNSTABLE'} (cont. {'stable' if r['continuous_stable'] else 'unstable'}) "
            f"stop {r['stop']:<9} at {r['cycle']:>5} delay {delay:<15} "
            f"peaks: clipped {p['saturation']:.3f}, turns from limit {p['limit_reversals']:.3f}/cycle, "
            f"growth streak {p['growth_swings']} (x{p['growth']:.3g})")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="one JSON object")
    args = parser.parse_args()
    rows = runs()
    if args.json:
        json.dump({"runs": rows, "margins": margins(rows)}, sys.stdout)
        print()
        return 0
    for r in rows:
        print(line(r))
    for k, m in margins(rows).items():
        print(f"stable runs: largest {k} {m['largest_stable']:.4g}, threshold {m['threshold']:g}")
    missed = [r for r in rows if not r["stable"] and r["stop"] != "unstable"]
    false = [r for r in rows if r["stable"] and r["stop"] == "unstable"]
    print(f"{len(rows)} runs: {len(false)} stable stopped unstable, {len(missed)} unstable not stopped"
          + (" (" + ", ".join(f"{r['config']} x{r['factor']:g}{' rest' if r['at_rest'] else ''}" for r in missed) + ")"
             if missed else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
