"""Shared by the tests of several axes in one loop: two-axis configs built from the
shipped single-axis demos, and the per-axis checks of a stopped run."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from dobhil.config.axes import Axes, load_axes
from dobhil.runtime.axes_loop import AxesResult

from .helpers import REPO

CONFIGS = REPO / "configs"
#: protocol -> (shipped demo config, two distinct node ids for one bus)
DEMOS: dict[str, tuple[str, tuple[int, int]]] = {
    "odrive": ("demo.yaml", (1, 2)),
    "cia402": ("cia402-demo.yaml", (5, 6)),
    "mit": ("mit-demo.yaml", (1, 2)),
    "moteus": ("moteus-demo.yaml", (1, 2)),
}
BOUND = 20.0   # s: how long a loaded machine may take, not a measurement
#: two coupled ODrive axes on one bus (``%s``: more keys of the right axis' drive section,
#: e.g. ``", channel: other"``), for the emulators that host several nodes
TWO_AXES = """\
loop: {period: 0.001, duration: 0.5}
axes:
  - name: left
    drive: {profile: odrive-0.6, node_id: 1}
  - name: right
    drive: {profile: odrive-0.6, node_id: 2%s}
    plant: {inertia: 0.3}
environment:
  coupling:
    - {axes: [left, right], stiffness: 2000.0, damping: 20.0}
"""
#: the per-cycle values compared bit for bit
FIELDS = ("t", "q", "dq", "tau_ref", "tau_int_hat", "tau_dis_hat", "tau_per", "u_unsat", "u", "tau_int_true",
          "q_true")


def demo_data(proto: str) -> dict[str, Any]:
    data: dict[str, Any] = yaml.safe_load((CONFIGS / DEMOS[proto][0]).read_text(encoding="utf-8"))
    return data


def axis_entry(proto: str, name: str, node: int, **sections: dict[str, Any]) -> dict[str, Any]:
    """One ``axes:`` entry: the demo's drive section at ``node``, plus ``sections``."""
    drive = dict(demo_data(proto)["drive"], node_id=node)
    return {"name": name, "drive": drive, **sections}


def two_axis_config(tmp_path: Path, protos: tuple[str, str], *, duration: float = 0.3,
                    coupled: bool = False) -> Path:
    """Two axes on one bus: the first protocol's demo at the top level, axis ``left`` as
    it is, axis ``right`` with another inertia and reference (so the axes differ)."""
    base = demo_data(protos[0])
    base["loop"] = dict(base["loop"], duration=duration)
    left_node = DEMOS[protos[0]][1][0]
    right_node = DEMOS[protos[1]][1][1]
    right_base = demo_data(protos[1])
    right: dict[str, Any] = {"plant": dict(right_base["plant"], inertia=1.2 * right_base["plant"]["inertia"]),
                             "reference": dict(right_base["reference"], amplitude=0.5, start=0.15)}
    if protos[1] != protos[0]:   # the other protocol's own sections (its drive's design)
        right.update({k: right_base[k] for k in ("design", "environment") if k in right_base})
    base["axes"] = [axis_entry(protos[0], "left", left_node), axis_entry(protos[1], "right", right_node, **right)]
    if coupled:
        base["environment"] = dict(base.get("environment", {}),
                                   coupling=[{"axes": ["left", "right"], "stiffness": 100.0, "damping": 1.0}])
    path = tmp_path / f"two-{'-'.join(protos)}.yaml"
    path.write_text(yaml.safe_dump(base), encoding="utf-8")
    return path


def load_two(tmp_path: Path, protos: tuple[str, str], *overrides: str, **kwargs: Any) -> Axes:
    return load_axes(two_axis_config(tmp_path, protos, **kwargs), list(overrides), [])


def assert_all_stopped(result: AxesResult, *, confirmable: dict[str, bool]) -> None:
    """Every axis got its zero torque and disable frames; a drive that can confirm its
    disable confirmed it, one that cannot by design answered (its note or loud line says so)."""
    for name, part in result.axes.items():
        report = part.safe_stop
        assert report is not None, name
        assert report.sent, (name, report)
        assert [f.what for f in report.frames][0] == "zero torque", (name, report.frames)
        if confirmable[name]:
            assert part.disabled, (name, report)
        else:
            assert report.confirmation.name == "UNCONFIRMABLE", (name, report)
