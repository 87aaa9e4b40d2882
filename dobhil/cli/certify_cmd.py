"""``dobhil certify CONFIG [--axis NAME] --range KEY=LO:HI [--range ...] [--loop both|continuous|sampled]
[--refinements N] [--json]``: stability over the whole box, not only at grid points."""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from dobhil.cli.axis_option import add_axis_arg, axis_keys
from dobhil.cli.common import add_config_args, config_from_args, design_on_drive
from dobhil.errors import ConfigError

if TYPE_CHECKING:
    from dobhil.analysis.certify import Box, ContinuousCertificate
    from dobhil.analysis.certify_sampled import SampledCertificate
    from dobhil.config.schema import Config

#: exit code when a loop asked for is not certified (refuted, or undecided)
EXIT_NOT_CERTIFIED = 1

MAX_REFINEMENTS = 1_000_000


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("certify", help="decide stability over a whole box of plant and environment values",
                       description=(
                           "Continuous loop: exact, by the edge theorem (every edge of the box an exact "
                           "one-parameter stability interval); with the gain margin in C_f over the box and "
                           "the smallest disk margin a search of the box meets. Sampled loop: interval "
                           "enclosures of the sampled plant and a Lyapunov bound, refined by bisection. Each answer is "
                           "certified, refuted at a point, or (sampled) undecided after N refinements. "
                           "See docs/certify.md."))
    add_config_args(p)
    add_axis_arg(p)
    p.add_argument("--range", dest="ranges", action="append", required=True, metavar="KEY=LO:HI",
                   help="environment.stiffness, environment.damping, plant.inertia or "
                   "plant.viscous_friction over [LO, HI] (repeatable)")
    p.add_argument("--loop", choices=("both", "continuous", "sampled"), default="both",
                   help="which loop to certify (default both)")
    p.add_argument("--refinements", type=int, default=None, metavar="N",
                   help="most bisections of the sampled certificate before it answers undecided "
                   "(default 20000)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from dobhil.analysis.certify import box_from_specs
    from dobhil.analysis.certify_sampled import DEFAULT_REFINEMENTS
    # an axes config: one axis' whole config, as tune certifies it (--axis, or the axis a
    # --range key names)
    axis_keys(args, {"ranges": "--range"})
    box = box_from_specs(args.ranges)
    refinements = DEFAULT_REFINEMENTS if args.refinements is None else args.refinements
    if not 0 <= refinements <= MAX_REFINEMENTS:
        raise ConfigError(f"--refinements {refinements}: expected 0 .. {MAX_REFINEMENTS}")
    config = design_on_drive(config_from_args(args), args, sys.stderr if args.json else None)
    answer = _answered(config, box, args.loop, refinements)
    if args.json:
        json.dump(answer, sys.stdout)
        sys.stdout.write("\n")
    else:
        print("\n".join(text_lines(answer)))
    return 0 if answer["certified"] else EXIT_NOT_CERTIFIED


def _answered(config: Config, box: Box, loops: str, refinements: int) -> dict[str, Any]:
    """:func:`certify`, or one line when the numbers of a box within the keys' ranges still
    overflow (an inertia of 1e-300: the polynomial's coefficients are not finite)."""
    from dobhil.analysis.stability import answered
    return answered(lambda: certify(config, box, loops=loops, refinements=refinements),
                    what="the certificate", of="this box")


def certify(config: Config, box: Box, *, loops: str = "both", refinements: int | None = None) -> dict[str, Any]:
    """The certificates asked for, as one JSON-able mapping (also what ``dobhil tune`` prints);
    ``refinements`` None: the sampled certificate's default budget."""
    from dobhil.analysis.certify import Verdict, certify_continuous
    from dobhil.analysis.certify_sampled import DEFAULT_REFINEMENTS, certify_sampled
    refinements = DEFAULT_REFINEMENTS if refinements is None else refinements
    out: dict[str, Any] = {"box": {k: [lo, hi] for k, lo, hi in zip(box.keys, box.lo, box.hi)},
                           "force_gain": float(config.design.force_gain)}
    # each loop's disk margin where it is unstable when refuted (at the refuting point), else
    # the smallest a search of the box meets, started also where the gain margin is worst
    refuting: dict[str, Mapping[str, float]] = {}
    starts: list[Mapping[str, float]] = []
    if loops in ("both", "continuous"):
        cont = certify_continuous(config, box)
        out["continuous"] = _continuous(cont)
        if cont.point is not None and cont.verdict is Verdict.REFUTED:
            refuting["continuous"] = cont.point
        elif cont.gain_margin is not None and cont.gain_margin.worst_at:
            starts.append(cont.gain_margin.worst_at)
    if loops in ("both", "sampled"):
        samp = certify_sampled(config, box, refinements=refinements)
        out["sampled"] = _sampled(samp)
        if samp.point is not None:
            refuting["sampled"] = samp.point
    out["disk_margin"] = {name: _disk(config, box, name == "sampled", refuting.get(name), starts)
                          for name in ("continuous", "sampled") if name in out}
    out["certified"] = all(out[name]["verdict"] == "certified" for name in ("continuous", "sampled")
                           if name in out)
    return out


def _continuous(c: ContinuousCertificate) -> dict[str, Any]:
    gm = c.gain_margin
    return {"verdict": c.verdict.word, "point": dict(c.point) if c.point else None,
            "spectral_abscissa": c.spectral_abscissa,
            "boundaries": [dict(b) for b in c.boundaries], "edges": len(c.edges),
            "edges_unstable": sum(not e.stable for e in c.edges),
            "gain_margin": None if gm is None else {
                "up": _num(gm.up), "down": _num(gm.down), "db": _num(gm.db),
                "up_at": dict(gm.up_at), "down_at": dict(gm.down_at)}}


def _sampled(s: SampledCertificate) -> dict[str, Any]:
    return {"verdict": s.verdict.word, "point": dict(s.point) if s.point else None,
            "spectral_radius": s.spectral_radius, "refinements": s.refinements,
            "sub_boxes_closed": s.closed}


def _disk(config: Config, box: Box, sampled: bool, refuting: Mapping[str, float] | None,
          starts: list[Mapping[str, float]]) -> dict[str, Any]:
    """The balanced disk margin at the refuting point (there: unstable), or the smallest
    :func:`dobhil.analysis.worst_disk.smallest_disk_margin` meets over the box."""
    from dobhil.analysis.worst_disk import disk_margin_at, smallest_disk_margin
    if refuting is not None:
        point, margin, where, points = dict(refuting), disk_margin_at(config, refuting, sampled), "refuting point", 1
    else:
        worst = smallest_disk_margin(config, box, sampled=sampled, starts=starts)
        point, margin, points = worst.point, worst.margin, worst.points
        where = f"the smallest of {points} points searched; not a bound"
    out: dict[str, Any] = {"at": point, "where": where, "points": points, "stable": margin is not None}
    if margin is None:   # unstable, or a pole the analysis cannot place on either side
        from dobhil.analysis.worst_disk import unresolved_at
        out["unresolved"] = unresolved_at(config, point, sampled)
    if margin is not None:
        out.update(alpha=_num(margin.alpha), gain_db=_num(margin.gain_db), phase_deg=margin.phase_deg,
                   frequency=margin.frequency)
    return out


def _num(x: float) -> float | None:
    """JSON has no infinity: None stands for an unbounded margin."""
    return x if math.isfinite(x) else None


def text_lines(answer: Mapping[str, Any]) -> list[str]:
    lines = ["box: " + ", ".join(f"{k} {lo:g}..{hi:g}" for k, (lo, hi) in answer["box"].items())]
    if "continuous" in answer:
        lines.append("continuous loop (edge theorem): " + _continuous_text(answer["continuous"]))
    if "sampled" in answer:
        lines.append("sampled loop (interval enclosure + Lyapunov bound): " + _sampled_text(answer["sampled"]))
    for name, dm in answer["disk_margin"].items():
        at = f"{_point_text(dm['at'])} ({dm['where']})"
        if not dm["stable"] and dm.get("unresolved"):
            lines.append(f"disk margin ({name}) at {at}: none: a pole lies within the analysis' resolution of the "
                         "stability boundary there, shown neither stable nor unstable")
        elif not dm["stable"]:
            lines.append(f"disk margin ({name}) at {at}: the loop is unstable there")
        else:
            gain = "inf" if dm["gain_db"] is None else f"{dm['gain_db']:.3g}"
            lines.append(f"disk margin ({name}) at {at}: ±{gain} dB, ±{dm['phase_deg']:.3g} deg "
                         f"(alpha {dm['alpha']:.3g} at {dm['frequency']:.3g} rad/s; Seiler et al. 2020)")
    return lines


def _continuous_text(c: Mapping[str, Any]) -> str:
    if c["verdict"] == "refuted":
        return (f"refuted at {_point_text(c['point'])} (max Re(s) = {c['spectral_abscissa']:+.4g} 1/s; "
                f"{c['edges_unstable']} of {c['edges']} edges unstable" + "".join(
                    f"; an edge leaves stability at {_point_text(b)}" for b in c["boundaries"]) + ")")
    if c["verdict"] == "undecided":
        return (f"undecided at {_point_text(c['point'])} (max Re(s) = {c['spectral_abscissa']:+.4g} 1/s: a pole "
                f"within the analysis' tolerance of the axis, shown neither stable nor unstable; "
                f"{c['edges_unstable']} of {c['edges']} edges not shown stable)")
    gm = c["gain_margin"]
    up = "unbounded" if gm["up"] is None else f"x{gm['up']:.4g} (at {_point_text(gm['up_at'])})"
    down = "unbounded" if gm["down"] is None else f"/{gm['down']:.4g} (at {_point_text(gm['down_at'])})"
    db = "inf" if gm["db"] is None else f"{gm['db']:.3g}"
    return (f"certified ({c['edges']} edges stable); gain margin over the box {db} dB: C_f up {up}, "
            f"down {down}")


def _sampled_text(s: Mapping[str, Any]) -> str:
    if s["verdict"] == "refuted":
        return f"refuted at {_point_text(s['point'])} (spectral radius {s['spectral_radius']:.6g})"
    seen = f"largest spectral radius met {s['spectral_radius']:.6g}"
    if s["verdict"] == "certified":
        return f"certified ({s['sub_boxes_closed']} sub-boxes closed, {s['refinements']} refinements; {seen})"
    return f"undecided after {s['refinements']} refinements ({s['sub_boxes_closed']} sub-boxes closed; {seen})"


def _point_text(point: Mapping[str, float]) -> str:
    return ", ".join(f"{k}={v:.6g}" for k, v in point.items())


def tuned_certificate(config: Config, design: Mapping[str, float], ranges: list[Any],
                      uncertainties: list[Any]) -> tuple[dict[str, Any] | None, list[str]]:
    """``dobhil tune``'s design certified over its set taken as a box (each --range key's LO..HI,
    each --uncertainty key's ends): the JSON answer (None when a key is one the certificate
    cannot treat) and its text lines."""
    import dataclasses
    from dobhil.analysis.certify import CERTIFY_KEYS, Box
    flat = config.flat()
    keys = [r.key for r in ranges] + [u.key for u in uncertainties]
    others = [k for k in keys if k not in CERTIFY_KEYS]
    if others or not keys:
        why = f"{', '.join(others)} is not a key it treats" if others else "no range"
        return None, [f"certificate over the box: not computed ({why}; it treats {', '.join(CERTIFY_KEYS)})"]
    # each uncertainty's own ends: an identified interval (--uncertainty-from) is where it was
    # identified, asymmetric or cut at 0, not the config's value +- its wider half
    ends = [u.values(float(flat[u.key])) for u in uncertainties]
    lo = [r.lo for r in ranges] + [float(min(e)) for e in ends]
    hi = [r.hi for r in ranges] + [float(max(e)) for e in ends]
    values: dict[str, Any] = {k.split(".", 1)[1]: float(v) for k, v in design.items()}
    tuned = config.replace(design=dataclasses.replace(config.design, **values))
    answer = certify(tuned, Box(tuple(keys), tuple(lo), tuple(hi)))
    return answer, ["certificate over the whole box (dobhil certify, docs/certify.md):",
                    *("  " + line for line in text_lines(answer)[1:])]
