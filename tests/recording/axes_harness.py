"""Several single-axis lockstep loops recorded into one :class:`AxesLog`, one after the other,
each axis' ``ForceLoop`` calling its own sink (``AxesLog.sink``) and its session's bus
wrapped under the bus name the axis is on -- what the several-axis loop does with one sink
per axis -- so the log holds real controller outputs of every axis for replay to verify."""

from __future__ import annotations

from collections.abc import Mapping
from contextlib import ExitStack
from pathlib import Path

from dobhil.cli.recording import AxisRun, abort_axes, begin_axes, end_axes
from dobhil.config.axes import load_axes
from dobhil.recording.axeslog import AxesLog
from dobhil.runtime.loop import RunResult
from dobhil.runtime.session import RunSession

#: three axes: two ODrives on one bus (node ids 1 and 2), a CiA 402 drive on another
CONFIG = """\
loop: {period: 0.001, duration: 0.3, timing: lockstep}
reference: {kind: step, offset: 0.2, amplitude: 0.8, start: 0.1}
axes:
  - name: left
    drive: {profile: odrive-0.6, node_id: 1}
  - name: right
    drive: {profile: odrive-0.6, node_id: 2}
    plant: {inertia: 0.3, initial_position: -0.002}
    reference: {amplitude: 0.5}
  - name: wrist
    drive: {profile: cia402-emulated}
    design: {dob_bandwidth: 250.0, rtob_bandwidth: 250.0, delay_samples: 1, input_delay: 0.0}
"""
#: the bus each axis is on
BUSES: Mapping[str, str] = {"left": "can0", "right": "can0", "wrist": "can1"}


def write_config(directory: Path, text: str = CONFIG) -> Path:
    path = directory / "axes.yaml"
    path.write_text(text)
    return path


def record_axes(path: Path, config: Path, buses: Mapping[str, str] = BUSES,
                overrides: tuple[str, ...] = (), lockstep: bool = True) -> dict[str, RunResult]:
    """Each axis of ``config`` run on its own (in lockstep, or in real time against the
    emulator process), all recorded into ``path``; in lockstep the log clock goes on from one
    axis' run to the next (one time line), in real time it is the wall clock."""
    axes = load_axes(config, overrides)
    log = AxesLog.open(path, axes.names, fsync=False)
    offset, clock = [0.0], [lambda: 0.0]
    results: dict[str, RunResult] = {}
    try:
        with ExitStack() as stack:
            sessions = {a.name: stack.enter_context(RunSession(
                a.config, emulate=True, lockstep=lockstep, sink=log.sink(a.name),
                bus_wrapper=lambda bus, name=buses[a.name]: log.wrap_bus(bus, name))) for a in axes.axes}
            runs = [AxisRun.of(name, s, buses[name]) for name, s in sessions.items()]
            timing = next(iter(sessions.values())).timing
            begin_axes(log, runs, timing=timing, period=axes.period,
                       duration=axes.axes[0].config.loop.duration, emulated=True,
                       sim_clock=(lambda: offset[0] + clock[0]()) if lockstep else None,
                       couplings=axes.couplings, config_file=config)
            for name, session in sessions.items():
                clock[0] = session.sim_clock or clock[0]
                results[name] = session.run()
                offset[0] += clock[0]() + axes.period
                clock[0] = lambda: 0.0
        stop = next((r.stop for r in results.values() if r.stop.reason.name != "DONE"),
                    results[axes.names[-1]].stop)
        end_axes(log, stop, {n: r.disabled for n, r in results.items()})
    except BaseException as exc:
        abort_axes(log, exc)
        raise
    return results
