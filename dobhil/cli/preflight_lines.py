"""What ``dobhil run`` says of a preflight (:mod:`dobhil.drives.preflight`): the lines of a
passed one and of one that refuses the run, for one axis or for each axis of a config
that lists axes (``prog``: ``dobhil run`` or ``dobhil run: axis NAME``)."""

from __future__ import annotations

import sys
from typing import Any

__all__ = ["report_preflight", "tell_refusal"]


def report_preflight(report: Any, prog: str = "dobhil run") -> None:
    """A passed preflight on stderr: its mismatches and notes, and one line per node
    measured (nothing when it was skipped). A mismatch here is one the run does not refuse
    on: its line says the run goes on, whatever the finding's own words."""
    if report is None:
        return
    for finding in report.findings:
        kind = "mismatch (not refused: the run goes on)" if finding.severity.name == "MISMATCH" else "note"
        sys.stderr.write(f"{prog}: preflight: {kind}: {finding.text}\n")
    for node in report.nodes:
        if node.node == report.node_id:
            sys.stderr.write(f"{prog}: preflight: node {node.node}: {node.summary}\n")


def tell_refusal(report: Any, prog: str) -> None:
    """A refusing preflight's lines: its other mismatches, then the one it refuses on
    (``prog``: ``dobhil run`` or ``dobhil run: axis NAME``)."""
    from dobhil.drives.preflight import Severity
    found = [f for f in report.findings if f.severity is Severity.MISMATCH]
    refusing = [f for f in found if f.stale_feedback] + [f for f in found if f.refuses_run]
    for finding in [f for f in found if not f.refuses] + refusing[1:]:
        sys.stderr.write(f"{prog}: mismatch: {finding.text}\n")
    sys.stderr.write(f"{prog}: refused to enable: {refusing[0].text if refusing else 'preflight'} "
                     "(dobhil check CONFIG shows all it measured; --no-preflight skips)\n")
