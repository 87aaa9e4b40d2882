"""``dobhil paper --out DIR``: regenerate Fig. 2 and Fig. 3 and check the paper's claims."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from dobhil.cli.common import output_path


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("paper", help="reproduce the paper's Fig. 2 and Fig. 3 and check its claims")
    p.add_argument("--out", type=output_path, default=Path("out/paper"), help="output directory")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    return reproduce(args.out)


def _outputs(out: Path) -> tuple[Path, Path]:
    """The two figure paths in ``out``, checked before any work (one line if unwritable)."""
    from dobhil.files import OutputError, check_output
    if out.exists() and not out.is_dir():
        raise OutputError(f"--out {out}: exists and is not a directory")
    return (check_output(out / "fig2_root_locus.png", suffix=".png", what="--out"),
            check_output(out / "fig3_step.png", suffix=".png", what="--out"))


def reproduce(out: Path) -> int:
    from dobhil import paper
    from dobhil.plotting.paper_figures import fig2, fig3
    targets = _outputs(out)
    cases2, cases3 = paper.fig2_cases(), paper.fig3_cases()
    facts = paper.fig2_facts(cases2) + paper.fig3_facts(cases3)
    paths = [fig2({case: paper.continuous(cfg) for case, cfg in cases2.items()}, targets[0]),
             fig3({ratio: paper.continuous(cfg) for ratio, cfg in cases3.items()}, targets[1])]
    print("Section IV claims, checked:")
    for f in facts:
        print(f"  [{'ok' if f.holds else 'FAILS'}] {f.claim} -- {f.evidence}")
    print("wrote " + ", ".join(str(p) for p in paths))
    failed = [f for f in facts if not f.holds]
    if failed:  # a failed check, not bad input: exit 1 (see dobhil --help)
        print(f"dobhil paper: {len(failed)} claim(s) of the paper not reproduced: "
              + "; ".join(f.claim for f in failed), file=sys.stderr)
        return 1
    return 0
