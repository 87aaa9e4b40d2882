"""The stability gate of a config that lists ``axes:``, where ``run``, ``demo`` and ``check``
are about to open its buses: each axis no coupling joins to another through the single-axis
gate (:func:`dobhil.cli.stability_gate.stability_gate`), each group of coupled axes through
the coupled gate (:func:`dobhil.analysis.coupled_gate.assess_coupled`: the loop ``dobhil
analyze`` shows for the group, each axis with its protocol's command delay).

A refusal is one line (:class:`~dobhil.errors.UnstableDesignError`, exit 2) naming the axis
or the coupled axes, unless ``--allow-unstable``; a stable loop whose margin is below
``analysis.min_gain_margin`` gets one warning line, as for one axis.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Mapping
from typing import Any

__all__ = ["axes_gate", "axes_gate_metadata"]


def axes_gate(axes: Any, config_path: str | os.PathLike[str], profiles: Mapping[str, Any], *,
              allow_unstable: bool, prog: str) -> dict[str, Any]:
    """Each group's verdict, keyed by the group's axes joined by ``+`` (one axis: its name);
    ``profiles``: each axis' drive profile (:class:`~dobhil.drives.axes.AxisDrive`'s)."""
    from dobhil.analysis.coupled import axis_designs, coupled_groups
    from dobhil.analysis.coupled_gate import assess_coupled
    from dobhil.cli.stability_gate import gate_line, stability_gate
    from dobhil.errors import UnstableDesignError
    designs = {d.name: d for d in axis_designs(axes, profiles)}
    out: dict[str, Any] = {}
    for group in coupled_groups(axes):
        if len(group) == 1:
            name = group[0]
            try:
                out[name] = stability_gate(axes.axis(name).config, config_path, allow_unstable=allow_unstable,
                                           prog=f"{prog}: axis {name}")
            except UnstableDesignError as exc:
                raise UnstableDesignError(f"axis {name}: {exc}") from None
            continue
        members = set(group)
        verdict = assess_coupled([designs[n] for n in group], [c for c in axes.couplings if c.a in members])
        if verdict.refuses and not allow_unstable:
            raise UnstableDesignError(verdict.refusal())
        line = gate_line(verdict)
        if line:
            sys.stderr.write(f"{prog}: {line}\n")
        out["+".join(group)] = verdict
    return out


def axes_gate_metadata(verdicts: Mapping[str, Any], *, allow_unstable: bool) -> dict[str, dict[str, str]]:
    """What the gate decided, per group (:func:`~dobhil.cli.stability_gate.gate_metadata`'s
    record for each), for a run's log or summary."""
    from dobhil.cli.stability_gate import gate_metadata
    return {key: gate_metadata(v, allow_unstable=allow_unstable) for key, v in verdicts.items()}
