"""Several axes in one lockstep loop: each axis computes exactly what it computes alone,
per protocol (two nodes of one protocol on one bus) and for a mixed pair."""

from __future__ import annotations

from pathlib import Path

import can
import numpy as np
import pytest

from dobhil.runtime.axes_session import AxesSession
from dobhil.runtime.session import RunSession
from dobhil.runtime.stop import StopReason

from .axes_helpers import CONFIGS, FIELDS, load_two

#: two nodes of each protocol, and a mixed pair of drives that both stream their feedback.
#: (A drive that only answers next to one that streams runs its first cycle one period
#: later than alone -- the step that brings the streaming drive's first sample -- so its
#: cycles match alone only while its plant is still at rest then: not asserted here.)
PAIRS = [("odrive", "odrive"), ("cia402", "cia402"), ("mit", "mit"), ("moteus", "moteus"), ("odrive", "cia402")]


@pytest.mark.parametrize("protos", PAIRS, ids=["-".join(p) for p in PAIRS])
def test_each_axis_runs_as_alone(tmp_path: Path, protos: tuple[str, str]) -> None:
    axes = load_two(tmp_path, protos)
    with AxesSession(axes, emulate=True, lockstep=True, config_dir=CONFIGS) as session:
        both = session.run()
    assert both.stop.reason is StopReason.DONE, both.stop.line()
    # each drive confirmed its disable, or (one that cannot by design) noted what it did confirm
    assert not both.warning()
    assert all(p.disabled or (p.safe_stop is not None and p.safe_stop.note()) for p in both.axes.values())
    for axis in axes.axes:
        with RunSession(axis.config, emulate=True, lockstep=True, config_dir=CONFIGS) as alone:
            single = alone.run()
        assert single.stop.reason is StopReason.DONE, single.stop.line()
        mine = both.axes[axis.name]
        assert mine.cycles == single.cycles == both.cycles
        # the last commands act for their whole period: both runs end on the same simulated instant
        assert both.stop.time == pytest.approx(single.stop.time, abs=1e-9), (both.stop.line(), single.stop.line())
        for name in FIELDS:
            a, b = mine.trace[name], single.trace[name]
            assert a.shape == b.shape and np.array_equal(a, b, equal_nan=True), (axis.name, name)
    # the axes differ (not one axis' values twice): the right one's reference is another
    assert not np.array_equal(both.axes["left"].trace["tau_ref"], both.axes["right"].trace["tau_ref"])


def test_axes_on_two_buses_run_as_alone(tmp_path: Path) -> None:
    """Each axis on a bus of its own (one lockstep bus each, stepped together)."""
    axes = load_two(tmp_path, ("cia402", "odrive"), "axes.left.drive.interface=socketcan",
                    "axes.left.drive.channel=can0", "axes.right.drive.interface=socketcan",
                    "axes.right.drive.channel=can1", "axes.right.drive.node_id=5")
    with AxesSession(axes, emulate=True, lockstep=True, config_dir=CONFIGS) as session:
        assert [(g.name, g.axes) for g in session.groups] == [("socketcan:can0", ["left"]),
                                                              ("socketcan:can1", ["right"])]
        both = session.run()
    assert both.stop.reason is StopReason.DONE and both.disabled, both.stop.line()
    for axis in axes.axes:
        with RunSession(axis.config, emulate=True, lockstep=True, config_dir=CONFIGS) as alone:
            single = alone.run()
        for name in FIELDS:
            assert np.array_equal(both.axes[axis.name].trace[name], single.trace[name], equal_nan=True), name


@pytest.mark.parametrize("protos", [("odrive", "moteus"), ("moteus", "odrive")])
def test_a_can_fd_axis_makes_its_emulated_bus_can_fd_in_any_order(tmp_path: Path, protos: tuple[str, str]) -> None:
    """The emulated bus of a classic drive and a CAN FD one is opened as CAN FD whichever
    the config lists first (it was the first axis' kind: listed second, the moteus drive
    was refused a classic bus)."""
    axes = load_two(tmp_path, protos, duration=0.02)
    with AxesSession(axes, emulate=True, lockstep=True, config_dir=CONFIGS) as session:
        (group,) = session.groups
        assert group.spec.kwargs == {"protocol": can.CanProtocol.CAN_FD}
        both = session.run()
    assert both.stop.reason is StopReason.DONE and both.cycles == 20, both.stop.line()
