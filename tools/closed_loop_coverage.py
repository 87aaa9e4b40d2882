"""Coverage of the closed-loop fit's 95 % intervals over seeded synthetic force runs: the
records of tests/identify/test_closedloop.py (tests/identify/closed_synthetic.py: the demo's
force run in contact, design ``design.identified_inertia=0.125``, a 1-60 Hz chirp around
1 N m, the hidden plant J 0.37, b 0.05, K 15000, D 60, 0.3 ms, a 14-bit encoder, 0.05 rad/s
of velocity noise), one per seed, each fitted by :func:`dobhil.identify.closedloop.identify_closed_loop`.

    python tools/closed_loop_coverage.py --seeds 0:50 --samples 4000

Prints, per seed, each parameter's error, standard error and z = (estimate - truth) /
standard error, then per parameter: how many intervals held the truth, the RMS and mean of z
(1 and 0 for calibrated, unbiased errors), the median error and standard error. The delay's
interval is the profile likelihood's, asymmetric: its standard error is the interval's width
over 2 z, and "held" (the interval holds the truth) is the figure to read for it. Those of J,
K and D are taken on the log scale (dobhil/identify/closedloop.py, _interval), also
asymmetric: "held" counts them, z is still (estimate - truth) / standard error.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dobhil.identify.closedloop import identify_closed_loop
from tests.identify.closed_synthetic import Hidden, chirp, record

TRUTH = {"inertia": 0.37, "stiffness": 15000.0, "damping": 60.0, "delay": 0.3e-3}


def seeds(text: str) -> range:
    lo, _, hi = text.partition(":")
    return range(int(lo), int(hi))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=seeds, default=range(0, 50), help="LO:HI (default 0:50)")
    parser.add_argument("--samples", type=int, default=4000, help="cycles per record (default 4000)")
    parser.add_argument("--noise", type=float, default=Hidden.velocity_noise,
                        help=f"velocity noise [rad/s] (default {Hidden.velocity_noise})")
    args = parser.parse_args()
    z: dict[str, list[float]] = {k: [] for k in TRUTH}
    err: dict[str, list[float]] = {k: [] for k in TRUTH}
    se: dict[str, list[float]] = {k: [] for k in TRUTH}
    held = dict.fromkeys(TRUTH, 0)
    cpu = 0.0
    for seed in args.seeds:
        run = record(Hidden(velocity_noise=args.noise), seed, chirp(args.samples, 1, 60, 1.0, 0.9),
                     "design.identified_inertia=0.125")
        t0 = time.process_time()
        estimates = identify_closed_loop(run).estimates
        cpu += time.process_time() - t0
        line = [f"{seed:3d}"]
        for k, truth in TRUTH.items():
            e = estimates[k]
            if not e.identifiable:
                line.append(f"{k} not identifiable")
                continue
            held[k] += e.low <= truth <= e.high
            z[k].append((e.value - truth) / e.stderr)
            err[k].append(abs(e.value / truth - 1.0))
            se[k].append(e.stderr / truth)
            line.append(f"{k} {100 * (e.value / truth - 1):+6.1f} % se {100 * e.stderr / truth:5.1f} % "
                        f"z {z[k][-1]:+5.2f}")
        print(" | ".join(line), flush=True)
    n = len(args.seeds)
    for k in TRUTH:
        if not z[k]:
            print(f"{k}: never identifiable")
            continue
        rms = math.sqrt(sum(v * v for v in z[k]) / len(z[k]))
        print(f"{k}: held in {held[k]} of {n} ({len(z[k])} identifiable); z RMS {rms:.2f}, mean "
              f"{sum(z[k]) / len(z[k]):+.2f}; median error {100 * sorted(err[k])[len(err[k]) // 2]:.1f} %, "
              f"median standard error {100 * sorted(se[k])[len(se[k]) // 2]:.1f} %")
    print(f"fit CPU {cpu:.1f} s for {n} records")
    return 0


if __name__ == "__main__":
    sys.exit(main())
