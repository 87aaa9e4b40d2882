"""The stability gate where a command is about to run the force loop (``run``, ``demo``) or to
look at the drive it would run on (``check``): the verdict of :mod:`dobhil.analysis.gate`
on the design on its drive profile, before any bus is opened or any log file created.

An unstable design is refused (:class:`~dobhil.errors.UnstableDesignError`: one line, exit
code 2) unless ``--allow-unstable``; then one line says the gate was overridden and the
run's log records it (:func:`gate_metadata`). A stable design whose margins are below
``analysis.min_gain_margin`` / ``analysis.min_phase_margin`` gets one warning line; a
design the analysis cannot judge gets one note line saying why. Nothing else is printed.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:   # imported when a command runs the gate: every command's --help stays light
    from dobhil.analysis.coupled_gate import CoupledVerdict
    from dobhil.analysis.gate import GateVerdict

#: the ``--allow-unstable`` option's help
ALLOW_HELP = ("run a design the stability gate finds unstable (for experiments: the torque then "
              "chatters between its limits until a safety stop); the override is printed and recorded "
              "in the log")


def add_gate_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--allow-unstable", action="store_true", help=ALLOW_HELP)


def stability_gate(config: Any, config_path: str | os.PathLike[str], *, allow_unstable: bool,
                   prog: str) -> GateVerdict:
    """The gate's verdict on ``config`` run on its drive profile (looked up near
    ``config_path``); raises UnstableDesignError when it refuses, else prints its one line
    (if any) to stderr as ``prog: ...``."""
    from dobhil.analysis.gate import assess
    from dobhil.config import resolve_config
    from dobhil.drives.load import load_drive_profile
    from dobhil.errors import UnstableDesignError
    profile = load_drive_profile(config, resolve_config(os.fspath(config_path)).parent)
    verdict = assess(config, profile)
    if verdict.refuses and not allow_unstable:
        raise UnstableDesignError(verdict.refusal())
    line = gate_line(verdict)
    if line:
        sys.stderr.write(f"{prog}: {line}\n")
    return verdict


def gate_line(verdict: GateVerdict | CoupledVerdict) -> str:
    """The one line a run prints about the gate ("" when the design passed with its margins)."""
    if verdict.refuses:
        return f"warning: {verdict.override_text()}"
    warning = verdict.warning()
    if warning:
        return f"warning: {warning}"
    note = verdict.note()
    return f"note: {note}" if note else ""


def gate_record(verdict: GateVerdict | CoupledVerdict, *, allow_unstable: bool) -> dict[str, Any]:
    """The gate's verdict as ``--summary-json`` gives it (``stability_gate``): the verdict,
    whether ``--allow-unstable`` was given and whether it overrode a refusal, the line."""
    out = dict(verdict.as_dict())
    out["allow_unstable"] = allow_unstable
    out["overridden"] = verdict.refuses and allow_unstable
    out["line"] = verdict.loop_text() if verdict.note() is None else verdict.note()
    return out


def gate_metadata(verdict: GateVerdict | CoupledVerdict, *, allow_unstable: bool) -> dict[str, str]:
    """The ``stability_gate`` metadata record of a run's log: :func:`gate_record`, JSON per key
    (an MCAP metadata record maps strings to strings)."""
    return {k: json.dumps(v) for k, v in gate_record(verdict, allow_unstable=allow_unstable).items()}


def summary_of_records(records: dict[str, dict[str, str]]) -> dict[str, dict[str, Any]]:
    """Metadata records of :func:`gate_metadata` (by axis or coupled group) as ``--summary-json``
    gives them: each value decoded."""
    return {name: {k: json.loads(v) for k, v in record.items()} for name, record in records.items()}


__all__ = ["add_gate_args", "gate_line", "gate_metadata", "gate_record", "stability_gate", "summary_of_records"]
