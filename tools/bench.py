#!/usr/bin/env python3
"""dobhil's speed and memory targets: ratios against baselines run in the same process, and
absolute figures of this machine.

``python tools/bench.py --json`` prints one JSON object: every figure by its key, and under
``"targets"`` each measured target with its kind, bound and whether it was met. Targets
(2-core machine) are in TARGETS (lower bounds) and TARGETS_MAX (upper bounds); ``--check``
exits 1 if one is missed. Two kinds (:class:`Kind`, printed beside each target):

- **ratio**: dobhil against a baseline doing the same work in the same run, interleaved
  (dobhil, baseline, dobhil, ...: a load change hits both sides), each side warmed up
  first and repeated the same number of times -- a ratio means about the same on a loaded
  or an idle machine;
- **absolute**: a rate or a time of this machine (``lockstep_cycles_per_s*``,
  ``replay_cycles_per_s``, ``identify_seconds_per_minute_of_log``): it falls with the load,
  so it is comparable only between runs on one machine in one state.

A measured run (real time, CiA 402, MIT, moteus, lockstep, logged, live, Monte-Carlo) counts
only if it lasted its duration (stop reason ``done``): one that did not fails the keys it
feeds (NaN, a missed target) with one line on stderr naming its stop reason. ``--repeat N``
pools N interleaved rounds of the real-time benches (``realtime``, ``rt_axes``) and gives
each per-round figure's spread (``_min``, ``_median``, ``_max``). The ``socketcan_*`` and
``bcm_sync_jitter_p99_us`` keys are absolute figures measured inside the kernel guest of
tools/canvm (``--only socketcan``; under software emulation on a machine where KVM does not
boot): no targets, stated as guest figures.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from enum import IntEnum
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dobhil.analysis.sweep import parse_vary, sweep
from dobhil.config import load_config
from dobhil.config.axes import Axes
from dobhil.recording.layouts import DEFAULT_LAYOUT, LAYOUTS
from dobhil.runtime.deadlines import next_deadline, sleep_until
from dobhil.synthesis.loop import loop
from dobhil.synthesis.params import params_from_config

ROOT = Path(__file__).resolve().parents[1]


class Kind(IntEnum):
    """What a target compares (the module docstring)."""
    RATIO = 1      # against a baseline in the same run
    ABSOLUTE = 2   # a figure of this machine in its state


#: the targets that are absolute figures of this machine; every other target is a ratio
ABSOLUTE_TARGETS = frozenset({
    "lockstep_cycles_per_s", "lockstep_cycles_per_s_cia402", "lockstep_cycles_per_s_mit",
    "lockstep_cycles_per_s_moteus", "replay_cycles_per_s", "identify_seconds_per_minute_of_log",
    "identify_closed_loop_seconds_per_minute_of_log"})


def kind(key: str) -> Kind:
    return Kind.ABSOLUTE if key in ABSOLUTE_TARGETS else Kind.RATIO


TARGETS: dict[str, float] = {
    "sweep_speedup_vs_python_control": 100.0,
    "lockstep_cycles_per_s": 5000.0,
    "lockstep_cycles_per_s_cia402": 3000.0,
    "lockstep_cycles_per_s_mit": 3000.0,
    "lockstep_cycles_per_s_moteus": 3000.0,
    "lockstep_vs_bare_bus_ratio": 0.4,
    # two axes in one lockstep loop: at least 0.45x the single axis' cycles per second
    "lockstep_2axes_vs_1axis_ratio": 0.45,
    "logged_vs_unlogged_ratio": 0.6,
    "replay_cycles_per_s": 20000.0,
    # replay() of a protobuf log at least as fast as of the same run's JSON log (CPU time)
    "replay_protobuf_vs_json": 1.0,
    "live_logged_vs_unlogged_ratio": 0.5,
    # 1 s Monte-Carlo runs on a local cluster of 2 worker processes vs 1 (2 cores)
    "montecarlo_scaling_2_workers": 1.6,
}
#: targets that are upper bounds (smaller is better)
TARGETS_MAX: dict[str, float] = {
    # the log as dobhil run writes it (protobuf, the default layout): at most a third of the
    # bytes per cycle of the same run in JSON, in lockstep and in real time, and less writer
    # CPU per cycle
    "log_bytes_per_cycle_vs_json": 0.33,
    "log_bytes_per_cycle_realtime_vs_json": 0.33,
    "writer_cpu_vs_json": 1.0,
    "rt_logged_vs_unlogged_overrun_ratio": 1.2,
    "rt_vs_bare_period_error_p99_ratio": 2.0,
    # 3 ODrive axes at 1 kHz in real time in one loop: at most 1.5x the single axis' overruns
    "rt_3axes_vs_1axis_overrun_ratio": 1.5,
    # a 60 s, 1 kHz log identified in at most 10 s
    "identify_seconds_per_minute_of_log": 10.0,
    # a 60 s, 1 kHz force run identified in closed loop (its controller simulated) in at most 20 s
    "identify_closed_loop_seconds_per_minute_of_log": 20.0,
    # a 1.4 us median measured on a machine whose controller step measured 0.65 us:
    # 1.4 / 0.65 controller steps, so the bound holds on any machine
    "loop_thread_log_cost_vs_controller_step": 2.15,
}


def timed(fn: Callable[[], object], repeat: int = 3) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


@dataclass(frozen=True)
class Side:
    """One side of a measured pair: ``warm`` once before any clock starts (imports, caches,
    first calls), then ``run`` timed."""
    name: str
    warm: Callable[[], object]
    run: Callable[[], object]


@dataclass(frozen=True)
class Interleaved:
    """Each side's run times in run order, and every call in the order made (``warm:NAME``
    for a warm-up, ``NAME`` for a timed run)."""
    times: dict[str, list[float]]
    order: tuple[str, ...]

    def best(self, name: str) -> float:
        return min(self.times[name])


def interleaved(sides: Sequence[Side], repeat: int, clock: Callable[[], float] = time.perf_counter) -> Interleaved:
    """Every side warmed (untimed), then ``repeat`` rounds of one timed run of each side in
    turn (A, B, A, B, ...): each side runs as often as the other, and a load change hits both."""
    times: dict[str, list[float]] = {side.name: [] for side in sides}
    order: list[str] = []
    for side in sides:
        order.append(f"warm:{side.name}")
        side.warm()
    for _ in range(repeat):
        for side in sides:
            order.append(side.name)
            t0 = clock()
            side.run()
            times[side.name].append(clock() - t0)
    return Interleaved(times, tuple(order))


def sweep_grid(n: int) -> list:  # type: ignore[type-arg]
    return [parse_vary(f"design.identified_inertia=0.05:0.6:{n}"),
            parse_vary(f"environment.stiffness=log:1e3:1e5:{n}")]


def python_control_point(config, ji: float, k: float) -> tuple[bool, bool, float]:  # type: ignore[no-untyped-def]
    """The sweep's question for one point, answered with python-control and numpy."""
    import control
    params = params_from_config(config).replace(identified_inertia=ji, stiffness=k)
    a, b, c, d = loop(params, sampled=False, force_gain=0.0).siso("tau_per", "tau_int_hat")
    sys_ = control.ss(a, b, c, d)
    tf = control.ss2tf(sys_)
    minimum_phase = bool(np.all(np.real(tf.zeros()) < 0))
    cf = float(config.design.force_gain)
    stable = bool(np.all(np.real(control.feedback(cf * sys_).poles()) < 0))
    num, den = np.asarray(tf.num[0][0], float), np.asarray(tf.den[0][0], float)
    gains = sorted(g for g in _crossings(num, den) if g > 1e-9)
    edges = [0.0, *gains]
    kmax = float("inf")
    for lo, hi in zip(edges, [*gains, float("inf")]):
        # a gain inside the interval: above the last crossing, twice it (any positive gain
        # when there is none -- gain 0 would test the open loop, not the closed one)
        test = (2 * lo if lo > 0 else 1.0) if np.isinf(hi) else 0.5 * (lo + hi)
        if not np.all(np.real(control.feedback(test * sys_).poles()) < 0):
            kmax = lo
            break
    return stable, minimum_phase, kmax


def _crossings(num: np.ndarray, den: np.ndarray) -> list[float]:
    n = max(num.size, den.size)
    num, den = np.pad(num, (n - num.size, 0)), np.pad(den, (n - den.size, 0))
    jp = 1j ** np.arange(n - 1, -1, -1)
    prod = np.polymul(den * jp, np.conj(num * jp))
    out = []
    for w in np.roots(prod.imag):
        if abs(w.imag) < 1e-6 * (1 + abs(w.real)) and w.real >= 0:
            dv, nv = np.polyval(den, 1j * w.real), np.polyval(num, 1j * w.real)
            if abs(nv) > 0:
                out.append(float(-(dv * np.conj(nv)).real / abs(nv) ** 2))
    return out


#: the sweep bench: dobhil's vectorised sweep over 60 x 60 points against python-control one
#: point at a time over 6 x 6 (a pass of ~0.1 s), both warmed, best of 3 each, interleaved
SWEEP_N, PYTHON_CONTROL_N, SWEEP_REPEAT = 60, 6, 3


def grid_points(grid: Sequence[Any]) -> list[tuple[float, float]]:
    """The points of a two-axis grid in the sweep's order (first axis slowest)."""
    return [(float(ji), float(k)) for ji in grid[0].values for k in grid[1].values]


def sweep_sides(config: Any, n: int = SWEEP_N, n_base: int = PYTHON_CONTROL_N) -> tuple[Side, Side]:
    """The pair: dobhil's sweep of an ``n`` x ``n`` grid, warmed by a sweep of the small grid;
    python-control answering the same question for each point of an ``n_base`` x ``n_base``
    grid, warmed by one point (``import control`` included: the clock starts after it)."""
    big, small = sweep_grid(n), sweep_grid(n_base)
    points = grid_points(small)
    ours = Side("dobhil", warm=lambda: sweep(config, small, sampled=False),
                run=lambda: sweep(config, big, sampled=False))
    base = Side("python-control", warm=lambda: python_control_point(config, *points[0]),
                run=lambda: [python_control_point(config, ji, k) for ji, k in points])
    return ours, base


def sweep_disagreements(config: Any, n_base: int = PYTHON_CONTROL_N) -> list[str]:
    """The points of the small grid where dobhil's sweep and python-control answer the
    question differently (stable at C_f, minimum phase, the largest stable C_f to 1e-6):
    the pair is only a speed-up if both answer the same question."""
    small = sweep_grid(n_base)
    result = sweep(config, small, sampled=False)
    out = []
    for i, (ji, k) in enumerate(grid_points(small)):
        idx = np.unravel_index(i, result.shape)
        stable, mp, kmax = python_control_point(config, ji, k)
        ours = (bool(result.stable[idx]), bool(result.minimum_phase[idx]), float(result.max_stable_gain[idx]))
        same_gain = (np.isinf(kmax) and np.isinf(ours[2])) or abs(kmax - ours[2]) <= 1e-6 * max(1.0, abs(kmax))
        if (stable, mp) != ours[:2] or not same_gain:
            out.append(f"J={ji:g}, K={k:g}: dobhil {ours}, python-control {(stable, mp, kmax)}")
    return out


def bench_sweep(repeat: int = SWEEP_REPEAT) -> dict[str, float]:
    """Points per second of dobhil's sweep and of python-control on the same question
    (:func:`python_control_point`), both warmed, best of ``repeat`` runs each, interleaved.
    The speed-up fails (NaN, one line) when the two answer any point differently."""
    config = load_config(ROOT / "configs/paper/fig2b.yaml")
    pair = interleaved(sweep_sides(config), repeat)
    ours = SWEEP_N ** 2 / pair.best("dobhil")
    base = PYTHON_CONTROL_N ** 2 / pair.best("python-control")
    ratios = [(SWEEP_N ** 2 / a) / (PYTHON_CONTROL_N ** 2 / b)
              for a, b in zip(pair.times["dobhil"], pair.times["python-control"])]
    speedup = ours / base
    differ = sweep_disagreements(config)
    if differ:
        print(f"bench: sweep_speedup_vs_python_control not counted: the two answer {len(differ)} "
              f"points differently, first {differ[0]}", file=sys.stderr)
        speedup = float("nan")
    t_sampled = timed(lambda: sweep(config, sweep_grid(SWEEP_N), sampled=True), repeat=1)
    return {"sweep_points_per_s": ours, "sweep_sampled_points_per_s": SWEEP_N ** 2 / t_sampled,
            "python_control_points_per_s": base, "sweep_speedup_vs_python_control": speedup,
            "sweep_speedup_vs_python_control_min": min(ratios), "sweep_speedup_vs_python_control_max": max(ratios)}


def bench_controller() -> dict[str, float]:
    """Median time of one ForceController.step (the paper's design, measured velocity)."""
    return {"controller_step_us_median": _controller_step_us()}


def _controller_step_us() -> float:
    from dobhil.drives.load import load_drive_profile
    from dobhil.runtime.session import build_controller
    config = load_config(ROOT / "configs/demo.yaml")
    ctrl = build_controller(config, load_drive_profile(config))
    step = ctrl.step
    samples = []
    for _ in range(31):
        t0 = time.perf_counter()
        for _ in range(2000):
            step(1e-4, 0.0, 1.0)
        samples.append((time.perf_counter() - t0) / 2000)
    return float(np.median(samples)) * 1e6


def _bare_bus_cycles_per_s(cycles: int) -> float:
    """The lockstep run's frames (one feedback, one command per cycle) on bare virtual buses."""
    import can
    from dobhil.drives.emulated import private_virtual_channel
    ch = private_virtual_channel()
    drive_side = can.Bus(interface="virtual", channel=ch)
    host_side = can.Bus(interface="virtual", channel=ch)
    feedback = can.Message(arbitration_id=0x069, data=bytes(8), is_extended_id=False)
    command = can.Message(arbitration_id=0x06E, data=bytes(4), is_extended_id=False)
    try:
        t0 = time.perf_counter()
        for _ in range(cycles):
            drive_side.send(feedback)
            host_side.recv(1.0)
            host_side.send(command)
            drive_side.recv(1.0)
        return cycles / (time.perf_counter() - t0)
    finally:
        drive_side.shutdown()
        host_side.shutdown()


def bench_lockstep(rounds: int = 5) -> dict[str, float]:
    """Lockstep emulated runs against the same frames on bare virtual buses: one short run
    of each side first (not counted), then interleaved pairs (a load change hits both
    sides of a pair). A run that did not last its duration fails the keys (NaN, a line)."""
    _lockstep_1axis_cycles_per_s(0.3)
    _bare_bus_cycles_per_s(500)
    ours, bare = [], []
    for _ in range(rounds):
        ours.append(_lockstep_1axis_cycles_per_s(4.0))
        bare.append(_bare_bus_cycles_per_s(8000))
    ratios = [o / b for o, b in zip(ours, bare)]
    return {"lockstep_cycles_per_s": _median_or_nan(ours),
            "bare_bus_cycles_per_s": float(np.median(bare)),
            "lockstep_vs_bare_bus_ratio": _median_or_nan(ratios)}


def _axes_config(axes: int, overrides: list[str]) -> Axes:
    """The demo's ODrive axis ``axes`` times on one bus (nodes 1..N, axes a1..aN)."""
    import yaml

    from dobhil.config.axes import load_axes
    data = yaml.safe_load((ROOT / "configs/demo.yaml").read_text(encoding="utf-8"))
    data["axes"] = [{"name": f"a{i + 1}", "drive": {"node_id": i + 1}} for i in range(axes)]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"demo-{axes}-axes.yaml"
        path.write_text(yaml.safe_dump(data), encoding="utf-8")
        return load_axes(path, overrides)


def _ran_whole(result: Any, duration: float, what: str) -> bool:
    """Whether a bench run lasted its ``duration`` (stopped ``done``); one line on stderr
    when it did not: such a run is not a measurement of the loop's speed and never counts."""
    from dobhil.runtime.stop import StopReason
    if result.stop.reason is StopReason.DONE:
        return True
    print(f"bench: {what} ({duration:g} s) did not last its duration, not counted: {result.stop.line()}",
          file=sys.stderr)
    return False


def _axes_lockstep_cycles_per_s(duration: float, axes: int) -> float:
    """The demo's ODrive axis ``axes`` times on one emulated bus (nodes 1..N), one loop;
    NaN (and a line) when the run did not last its duration."""
    from dobhil.runtime.axes_session import AxesSession
    config = _axes_config(axes, [f"loop.duration={duration}"])
    with AxesSession(config, emulate=True, lockstep=True, config_dir=ROOT / "configs") as session:
        t0 = time.perf_counter()
        result = session.run()
        rate = result.cycles / (time.perf_counter() - t0)
    return rate if _ran_whole(result, duration, f"lockstep run of {axes} axes") else float("nan")


def _lockstep_1axis_cycles_per_s(duration: float) -> float:
    """The single-axis lockstep demo run; NaN (and a line) when it did not last its duration."""
    from dobhil.runtime.session import RunSession
    config = load_config(ROOT / "configs/demo.yaml", [f"loop.duration={duration}"])
    with RunSession(config, emulate=True, lockstep=True) as session:
        t0 = time.perf_counter()
        result = session.run()
        rate = result.cycles / (time.perf_counter() - t0)
    return rate if _ran_whole(result, duration, "lockstep run of 1 axis") else float("nan")


def _median_or_nan(values: list[float]) -> float:
    """The median; NaN when any value is (a run that failed fails its key)."""
    return float("nan") if any(v != v for v in values) else float(np.median(values))


def bench_axes(rounds: int = 3, seconds: float = 2.0) -> dict[str, float]:
    """Several axes in one lockstep loop against the single axis, interleaved in rounds of
    1, 2 and 4 axes (a load change hits every member of a round), the order turned each
    round (no side always runs first, after the same one); one short run of each side
    first, not counted (imports, caches). A run that did not last its duration fails its
    keys (NaN, one line on stderr)."""
    sides: dict[int, Callable[[float], float]] = {
        1: _lockstep_1axis_cycles_per_s,
        2: lambda d: _axes_lockstep_cycles_per_s(d, 2),
        4: lambda d: _axes_lockstep_cycles_per_s(d, 4)}
    for run in sides.values():
        run(0.3)
    rates: dict[int, list[float]] = {n: [] for n in sides}
    order = list(sides)
    for i in range(rounds):
        for n in (order if i % 2 == 0 else order[::-1]):
            rates[n].append(sides[n](seconds))
    ratios = [t / o for t, o in zip(rates[2], rates[1])]
    return {"lockstep_cycles_per_s_2axes": _median_or_nan(rates[2]),
            "lockstep_cycles_per_s_4axes": _median_or_nan(rates[4]),
            "lockstep_2axes_vs_1axis_ratio": _median_or_nan(ratios),
            "lockstep_2axes_vs_1axis_ratio_min": float(min(ratios)),
            "lockstep_2axes_vs_1axis_ratio_max": float(max(ratios))}


#: real-time runs of several axes: the single-axis runs' overrides (host timing, the
#: feedback timeout bench_realtime uses)
_RT_AXES_SETS = ("loop.timing=host", "loop.feedback_timeout=0.05")


def _rt_axes_run(duration: float, axes: int) -> Any:
    """A real-time 1 kHz run of the demo's ODrive axis, emulated in the emulator process:
    ``axes`` == 1 the single-axis run (:class:`RunSession`), else ``axes`` nodes on one bus
    in one loop (:class:`AxesSession`, one emulator process hosting every node)."""
    overrides = [f"loop.duration={duration}", *_RT_AXES_SETS]
    if axes == 1:
        from dobhil.runtime.session import RunSession
        with RunSession(load_config(ROOT / "configs/demo.yaml", overrides), emulate=True, lockstep=False,
                        config_dir=ROOT / "configs") as session:
            return session.run()
    from dobhil.runtime.axes_session import AxesSession
    with AxesSession(_axes_config(axes, overrides), emulate=True, lockstep=False,
                     config_dir=ROOT / "configs") as session:
        return session.run()


def bench_rt_axes(rounds: int = 6, seconds: float = 5.0, axes: int = 3) -> dict[str, float]:
    """3 ODrive axes at 1 kHz in real time (one loop, host timing, one emulator process
    hosting the three nodes) against the single ODrive axis, in one run: rounds of 1 then
    3 axes, the order turned each round (1, 3, 3, 1, ...: a load change hits both sides
    of a round), after one warm-up run of each side, not counted. Overruns per 10,000
    deadlines (cycles run and skipped), over all rounds; the ratio compares them at the
    same number of deadlines, a zero single-axis count counting as 1 (as
    ``rt_logged_vs_unlogged_overrun_ratio``). The spread: the rounds' smallest and
    largest per-10k figures and ratios. A run that did not last its duration (a feedback
    timeout, a fault) is not a measurement: one line on stderr, and the keys are NaN."""
    import os
    load_before = os.getloadavg()[0]   # the spread follows the machine's load: printed with it
    for n in (1, axes):
        _rt_axes_run(1.0, n)
    counts = {1: [0, 0], axes: [0, 0]}
    per_round: dict[int, dict[int, float]] = {1: {}, axes: {}}   # round -> overruns per 10k
    failed = False
    for i in range(rounds):
        for n in ((1, axes) if i % 2 == 0 else (axes, 1)):
            result = _rt_axes_run(seconds, n)
            what = f"real-time run of {n} ax{'is' if n == 1 else 'es'}, round {i + 1}"
            if not _ran_whole(result, seconds, what):
                failed = True
                continue
            deadlines = result.cycles + result.skipped
            counts[n][0] += result.overruns
            counts[n][1] += deadlines
            per_round[n][i] = 1e4 * result.overruns / max(deadlines, 1)

    def per_10k(n: int) -> float:
        return float("nan") if failed else 1e4 * counts[n][0] / max(counts[n][1], 1)

    # a round's ratio, of the rounds whose two runs both counted; a zero single-axis
    # count counts as one overrun
    ratios = [per_round[axes][i] / max(per_round[1][i], 1e4 / (seconds * 1e3))
              for i in per_round[axes] if i in per_round[1]]
    one_at_many = counts[1][0] * counts[axes][1] / max(counts[1][1], 1)
    key = f"rt_{axes}axes"
    return {f"{key}_overruns_per_10k": per_10k(axes),
            f"{key}_overruns_per_10k_min": min(per_round[axes].values(), default=float("nan")),
            f"{key}_overruns_per_10k_max": max(per_round[axes].values(), default=float("nan")),
            "rt_1axis_overruns_per_10k": per_10k(1),
            "rt_1axis_overruns_per_10k_min": min(per_round[1].values(), default=float("nan")),
            "rt_1axis_overruns_per_10k_max": max(per_round[1].values(), default=float("nan")),
            f"{key}_vs_1axis_overrun_ratio": (float("nan") if failed
                                              else counts[axes][0] / max(one_at_many, 1.0)),
            f"{key}_vs_1axis_overrun_ratio_min": min(ratios, default=float("nan")),
            f"{key}_vs_1axis_overrun_ratio_max": max(ratios, default=float("nan")),
            "rt_axes_load_average_1min_before": load_before, "rt_axes_load_average_1min_after": os.getloadavg()[0]}


def _logged_run(duration: float, path: Path | None) -> float:
    """Cycles/s of a lockstep demo run, recorded to ``path`` (None: not recorded); the
    time includes finishing the file. NaN (and a line) when it did not last its duration."""
    from dobhil.cli.recording import open_run_log, record_run
    from dobhil.runtime.session import RunSession
    config = load_config(ROOT / "configs/demo.yaml", [f"loop.duration={duration}"])
    if path is not None:
        path.unlink(missing_ok=True)
    log = open_run_log(path, fsync=False)
    hooks = {} if log is None else {"sink": log, "bus_wrapper": log.wrap_bus}
    with RunSession(config, emulate=True, lockstep=True, **hooks) as session:
        t0 = time.perf_counter()
        result = record_run(session, log)
        rate = result.cycles / (time.perf_counter() - t0)
    what = f"lockstep run {'logged' if path is not None else 'unlogged'}"
    return rate if _ran_whole(result, duration, what) else float("nan")


def bench_logging() -> dict[str, float]:
    """Recorder alone; lockstep runs with and without full logging, interleaved pairs.

    ``logged_vs_unlogged_ratio`` (the target) is the steady state: 20 s (simulated)
    runs, ~0.7 s of wall time each. Run logging writes from a separate process whose
    start (~0.1 s: a fresh interpreter importing mcap) is paid once per run, like
    opening the file; on very short runs it dominates, so
    ``logged_vs_unlogged_ratio_4s_run`` (no target) shows a 4 s run with it included.
    Both include finishing the file."""
    import tempfile
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "bench.mcap"
        _logged_pairs(1.0, path, 1)   # warm-up, not counted: imports, the writer's first start
        short_logged, short_plain = _logged_pairs(4.0, path, 3)
        logged, plain = _logged_pairs(20.0, Path(tmp) / "bench20.mcap", 3)
        msgs = _recorder_msgs_per_s(path)
        replay_rate = _replay_cycles_per_s(path)
    return {"mcap_log_msgs_per_s": msgs, "lockstep_logged_cycles_per_s": _median_or_nan(logged),
            "lockstep_unlogged_cycles_per_s": _median_or_nan(plain),
            "logged_vs_unlogged_ratio": _median_or_nan([a / b for a, b in zip(logged, plain)]),
            "logged_vs_unlogged_ratio_4s_run": _median_or_nan(
                [a / b for a, b in zip(short_logged, short_plain)]),
            "replay_cycles_per_s": replay_rate}


def _logged_pairs(duration: float, path: Path, pairs: int) -> tuple[list[float], list[float]]:
    """Cycles/s of ``pairs`` interleaved (unlogged, logged) runs: a load change hits both."""
    logged, plain = [], []
    for _ in range(pairs):
        plain.append(_logged_run(duration, None))
        logged.append(_logged_run(duration, path))
    return logged, plain


def _bench_records(cycles: int) -> list[tuple[Any, ...]]:
    """Records like a recorded run's: per cycle a received frame, the cycle (truth
    included) and a sent frame, values moving as a run's do."""
    from dobhil.recording.schemas import CYCLE
    records: list[tuple[Any, ...]] = []
    for k in range(cycles):
        t, x = 1_000_000_000 + k * 1_000_000, math.sin(k * 1e-3)
        records.append((1, t, 0x069, *(False,) * 6, 8, bytes(range(8)), 1.5 + k * 1e-3, "bench"))
        records.append((CYCLE, t, k, 1e-4 * x, 0.1 * x, k, 0.2, 0.19 + x / 7, 0.01 * x, 0.02, 0.03 + x / 3,
                        0.03 + x / 3, 1e-6 * x, 3e-5, False, math.nan, 1, 8, 0, 1e-4 * x, 0.1 * x, 0.03, 0.19))
        records.append((2, t, 0x06E, *(False,) * 6, 4, bytes(4), 1.5 + k * 1e-3, "bench"))
    return records


def _recorder_msgs_per_s(recorded: Path) -> float:
    """Messages/s the one writer (LogWriter) encodes and writes on its own: records like a
    recorded run's cycles and frames, without the loop."""
    from dobhil.recording.writer import LogWriter
    records = _bench_records(20000)
    best = 0.0
    for _ in range(3):
        t0 = time.perf_counter()
        log = LogWriter(open(recorded.with_suffix(".rec.mcap"), "wb"), metadata={}, fsync=False)
        log.write(records)
        log.finish(None)
        best = max(best, log.written / (time.perf_counter() - t0))
    return best


#: the log encodings compared: dobhil's and the JSON it wrote before
LOG_ENCODINGS = ("protobuf", "json")
#: the log formats measured: name -> (encoding, layout): protobuf in each layout
#: (dobhil/recording/layouts.py: ``cycle``, one message per control cycle; ``topics``, one
#: per topic and frame) and the JSON dobhil wrote before 0.2 (one per topic and frame)
LOG_FORMATS: dict[str, tuple[str, str]] = {layout: ("protobuf", layout) for layout in LAYOUTS}
LOG_FORMATS["json"] = ("json", "topics")
#: the format ``dobhil run --log`` writes: the unsuffixed keys are its figures
DEFAULT_FORM = DEFAULT_LAYOUT
#: the other protobuf layouts: their keys end ``_<layout>_layout``
OTHER_FORMS = tuple(f for f in LAYOUTS if f != DEFAULT_FORM)


def _encoded_run(duration: float, path: Path, form: str, lockstep: bool = True) -> tuple[float, float]:
    """(file bytes, message bytes before compression) per cycle of a demo run (lockstep, or
    in real time) recorded in the log format ``form`` (:data:`LOG_FORMATS`); NaN (and a
    line) when it did not last its duration."""
    from dobhil.cli.recording import open_run_log, record_run
    from dobhil.recording.reader import open_log
    from dobhil.runtime.session import RunSession
    encoding, layout = LOG_FORMATS[form]
    config = load_config(ROOT / "configs/demo.yaml", [f"loop.duration={duration}"])
    path.unlink(missing_ok=True)
    log = open_run_log(path, fsync=False, encoding=encoding, layout=layout)
    assert log is not None
    with RunSession(config, emulate=True, lockstep=lockstep, sink=log, bus_wrapper=log.wrap_bus) as session:
        result = record_run(session, log)
    timing = "lockstep" if lockstep else "real-time"
    if not _ran_whole(result, duration, f"{timing} run logged as {form}"):
        return math.nan, math.nan
    payload = sum(len(data) for _, _, data in open_log(path).iter_payloads())
    return path.stat().st_size / result.cycles, payload / result.cycles


def _writer_cpu_us(records: list[tuple[Any, ...]], form: str, path: Path) -> float:
    """CPU seconds (this process) LogWriter spends encoding and writing ``records`` in the
    log format ``form``, in us."""
    from dobhil.recording.writer import LogWriter
    encoding, layout = LOG_FORMATS[form]
    t0 = time.process_time()
    log = LogWriter(open(path, "wb"), metadata={}, fsync=False, encoding=encoding, layout=layout)
    log.write(records)
    log.finish(None)
    return (time.process_time() - t0) * 1e6


def bench_log_encoding(pairs: int = 3, seconds: float = 4.0, cycles: int = 20000,
                       realtime_seconds: float = 4.0) -> dict[str, float]:
    """The log's size and its writer's CPU per control cycle in each format of
    :data:`LOG_FORMATS` -- protobuf in each layout (the unsuffixed keys: the default layout,
    what ``dobhil run --log`` writes), JSON (what dobhil wrote before 0.2) -- interleaved (the
    order turned each round), each warmed up first.

    ``log_bytes_per_cycle`` (file bytes, zstd chunks and MCAP's indexes included) is the
    median of ``pairs`` recordings of one lockstep demo run (deterministic: the same records
    every way), each checked to have lasted; ``log_payload_bytes_per_cycle_vs_json`` the
    messages' own bytes before compression. The ``_realtime`` keys: the same of a
    ``realtime_seconds`` real-time run (wall-clock stamps and timings: more to compress).
    ``writer_cpu_us_per_cycle``: the writer's CPU (LogWriter in this process: encoding,
    chunking, zstd) per cycle of ``cycles`` run-like cycles (a frame received, the cycle's
    five messages, a frame sent), median of ``pairs``. ``replay_protobuf_vs_json``:
    :func:`replay_by_encoding` of one such run recorded each way."""
    forms = tuple(LOG_FORMATS)
    sizes: dict[str, list[tuple[float, float]]] = {f: [] for f in forms}
    realtime: dict[str, list[tuple[float, float]]] = {f: [] for f in forms}
    cpu: dict[str, list[float]] = {f: [] for f in forms}
    records = _bench_records(cycles)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "encoded.mcap"
        for form in forms:   # warm-up, not counted: imports, the writer's first start
            _encoded_run(0.5, path, form)
            _writer_cpu_us(records[:3000], form, path)
        for i in range(pairs):
            for form in forms[i % len(forms):] + forms[:i % len(forms)]:
                sizes[form].append(_encoded_run(seconds, path, form))
                cpu[form].append(_writer_cpu_us(records, form, path) / cycles)
                if realtime_seconds > 0:
                    realtime[form].append(_encoded_run(realtime_seconds, path, form, lockstep=False))
        replayed = replay_by_encoding(seconds, Path(tmp))
    return {**log_encoding_figures(sizes, cpu, realtime), **replayed}


#: replay rounds of :func:`replay_by_encoding` (a 4 s log replays in ~0.15 s of CPU): best of 15
REPLAY_REPEAT = 15


def replay_by_encoding(seconds: float, folder: Path, repeat: int = REPLAY_REPEAT, *,
                       clock: Callable[[], float] = time.process_time) -> dict[str, float]:
    """``replay()`` (the file read, decoded and the controller re-run, as ``dobhil replay``)
    of one lockstep demo run recorded in each log format of :data:`LOG_FORMATS`
    (deterministic: the same records), each side warmed, then ``repeat`` interleaved rounds,
    best of each. Timed in CPU time of this process (``time.process_time``): replay is one
    thread, and a shared machine's other jobs are not counted against either side. Each
    replay checked bit for bit against its recording (:func:`_replayed`).
    ``replay_protobuf_vs_json``: JSON's time over the default layout's (above 1: what dobhil
    writes replays faster); ``replay_cycle_layout_vs_topics``: the topics layout's time over
    the cycle layout's (below 1: a cycle log replays slower); NaN when a run did not last its
    duration."""
    forms = tuple(LOG_FORMATS)
    paths = {f: folder / f"replay-{f}.mcap" for f in forms}
    recorded = [_encoded_run(seconds, paths[f], f)[0] for f in forms]   # NaN: did not last
    if any(math.isnan(v) for v in recorded):
        return {"replay_protobuf_vs_json": math.nan, "replay_cycle_layout_vs_topics": math.nan}
    cycles: dict[str, int] = {}

    def run(form: str) -> None:
        cycles[form] = _replayed(paths[form])
    sides = [Side(f, lambda f=f: run(f), lambda f=f: run(f)) for f in forms]
    times = interleaved(sides, repeat, clock=clock)
    return {"replay_cycles_per_cpu_s": cycles[DEFAULT_FORM] / times.best(DEFAULT_FORM),
            "replay_cycles_per_cpu_s_json": cycles["json"] / times.best("json"),
            **{f"replay_cycles_per_cpu_s_{f}_layout": cycles[f] / times.best(f) for f in OTHER_FORMS},
            "replay_protobuf_vs_json": times.best("json") / times.best(DEFAULT_FORM),
            "replay_cycle_layout_vs_topics": times.best("topics") / times.best("cycle")}


def _replayed(path: Path) -> int:
    """Cycles of ``replay()`` of ``path``, checked to reproduce the recording bit for bit."""
    from dobhil.replay import replay
    result = replay(path)
    mismatch = result.first_mismatch()
    if mismatch is not None:
        raise AssertionError(f"replay of {path} differs from its recording: {mismatch.line()}")
    return result.recording.cycles


def log_encoding_figures(sizes: dict[str, list[tuple[float, float]]], cpu: dict[str, list[float]],
                         realtime: dict[str, list[tuple[float, float]]] | None = None) -> dict[str, float]:
    """The keys of :func:`bench_log_encoding` from its measured (file, payload) bytes per
    cycle and CPU per cycle of each format (``realtime``: the real-time runs' bytes, none
    measured when empty); a run that did not last (NaN) fails them."""
    def median(values: list[float]) -> float:
        return float("nan") if any(math.isnan(v) for v in values) else _median_or_nan(values)
    file = {f: median([b for b, _ in sizes[f]]) for f in sizes}
    payload = {f: median([p for _, p in sizes[f]]) for f in sizes}
    used = {f: median(cpu[f]) for f in cpu}
    def keys(form: str) -> dict[str, float]:
        """One protobuf layout's keys: unsuffixed for the default, ``_<layout>_layout`` else."""
        tail = "" if form == DEFAULT_FORM else f"_{form}_layout"
        out = {f"log_bytes_per_cycle{tail}": file[form],
               f"log_bytes_per_cycle{tail}_vs_json": file[form] / file["json"],
               f"log_payload_bytes_per_cycle{tail}_vs_json": payload[form] / payload["json"],
               f"writer_cpu_us_per_cycle{tail}": used[form], f"writer_cpu{tail}_vs_json": used[form] / used["json"]}
        if rt:
            out.update({f"log_bytes_per_cycle_realtime{tail}": rt[form],
                        f"log_bytes_per_cycle_realtime{tail}_vs_json": rt[form] / rt["json"]})
        return out
    file = {f: median([b for b, _ in sizes[f]]) for f in sizes}
    payload = {f: median([p for _, p in sizes[f]]) for f in sizes}
    used = {f: median(cpu[f]) for f in cpu}
    rt = ({f: median([b for b, _ in realtime[f]]) for f in realtime}
          if realtime and all(realtime.get(f) for f in sizes) else {})
    out = {"log_bytes_per_cycle_json": file["json"], "writer_cpu_us_per_cycle_json": used["json"]}
    if rt:
        out["log_bytes_per_cycle_realtime_json"] = rt["json"]
    for form in (DEFAULT_FORM, *OTHER_FORMS):
        out.update(keys(form))
    return out


def _replay_cycles_per_s(recorded: Path) -> float:
    """Cycles/s of ``replay()`` of a recorded 4 s run, reading the file included."""
    from dobhil.replay import replay
    best = 0.0
    for _ in range(3):
        t0 = time.perf_counter()
        result = replay(recorded)
        best = max(best, result.recording.cycles / (time.perf_counter() - t0))
    assert result.first_mismatch() is None
    return best


def _bare_loop_period_errors(duration: float, period: float = 1e-3, spin: float | None = None) -> list[float]:
    """A Python loop doing nothing but wait for 1 kHz deadlines exactly as host timing waits:
    the runtime's own :func:`~dobhil.runtime.deadlines.next_deadline` (missed deadlines
    skipped) and :func:`~dobhil.runtime.deadlines.sleep_until` (sleep to ``spin`` s before the
    deadline, the demo's ``loop.spin`` by default, then spin). |wake - deadline| per cycle,
    as the runtime measures its period error: what waiting alone costs on this machine now,
    the yardstick for the loop's own figure."""
    if spin is None:
        spin = float(load_config(ROOT / "configs/demo.yaml").loop.spin)
    clock, stop = time.perf_counter, threading.Event()   # nothing stops it before its last deadline
    errors = []
    t0 = clock()
    k, n = 0, int(round(duration / period))
    while k < n:
        errors.append(abs(clock() - (t0 + k * period)))
        k = next_deadline(k, clock(), t0, period)
        sleep_until(t0 + k * period, spin=spin, clock=clock, stop=stop)
    return errors


def _realtime_run(duration: float, timing: str, path: Path | None):  # type: ignore[no-untyped-def]
    """An emulated real-time demo run (``loop.timing``), recorded to ``path`` or not."""
    from dobhil.cli.recording import open_run_log, record_run
    from dobhil.cli.run_cmd import log_hooks, lower_writer
    from dobhil.runtime.session import RunSession
    config = load_config(ROOT / "configs/demo.yaml", [
        f"loop.duration={duration}", f"loop.timing={timing}", "loop.feedback_timeout=0.05"])
    log = open_run_log(path, fsync=False)
    lower_writer(log)  # as dobhil run does: the writer below the loop
    with RunSession(config, emulate=True, lockstep=False, **log_hooks(log)) as session:
        return record_run(session, log)


#: the real-time bench's runs: name -> loop.timing, recorded or not
_RT_RUNS = {"plain": ("host", False), "logged": ("host", True), "feedback": ("feedback", False)}
#: each real-time key and the runs it is made of (a run that did not last fails these keys)
_RT_KEYS = {"rt_overruns_per_10k": ("plain",), "rt_logged_overruns_per_10k": ("logged",),
            "rt_feedback_overruns_per_10k": ("feedback",), "rt_period_error_p99_us": ("plain",),
            "rt_feedback_latency_p99_us": ("feedback",), "rt_logged_vs_unlogged_overrun_ratio": ("plain", "logged"),
            "rt_unlogged_overruns": ("plain",), "rt_logged_overruns": ("logged",), "rt_deadlines_each": ("plain",),
            "rt_vs_bare_period_error_p99_ratio": ("plain",)}


@dataclass
class _RtTally:
    """What the real-time rounds measured: pooled overruns and deadlines per run name, each
    round's figures, the run names that failed."""
    counts: dict[str, list[int]] = field(default_factory=lambda: {n: [0, 0] for n in _RT_RUNS})
    rounds: dict[str, list[float]] = field(default_factory=dict)
    failed: set[str] = field(default_factory=set)
    order: list[str] = field(default_factory=list)

    def add(self, key: str, value: float) -> None:
        self.rounds.setdefault(key, []).append(value)


def _realtime_round(i: int, seconds: float, tmp: Path, tally: _RtTally) -> None:
    """One round: the bare loop, then host-timed runs without and with logging (in turn
    first), then a feedback-timed run; each run's figures only when it lasted its duration."""
    tally.order.append("bare")
    bare_p99 = float(np.percentile(_bare_loop_period_errors(seconds), 99))
    tally.add("bare_loop_period_error_p99_us", bare_p99 * 1e6)
    pair = ["plain", "logged"] if i % 2 == 0 else ["logged", "plain"]
    for name in [*pair, "feedback"]:
        tally.order.append(name)
        timing, logged = _RT_RUNS[name]
        result = _realtime_run(seconds, timing, tmp / f"rt{i}.mcap" if logged else None)
        if not _ran_whole(result, seconds, f"real-time run ({name}), round {i + 1}"):
            tally.failed.add(name)
            continue
        deadlines = result.cycles + result.skipped
        tally.counts[name][0] += result.overruns
        tally.counts[name][1] += deadlines
        key = "rt_overruns_per_10k" if name == "plain" else f"rt_{name}_overruns_per_10k"
        tally.add(key, 1e4 * result.overruns / max(deadlines, 1))
        if name == "plain":
            p99 = result.timing.period_error_p99
            tally.add("rt_period_error_p99_us", p99 * 1e6)
            tally.add("rt_vs_bare_period_error_p99_ratio", p99 / bare_p99 if bare_p99 > 0 else float("inf"))
        if name == "feedback":
            tally.add("rt_feedback_latency_p99_us", result.timing.latency_p99 * 1e6)


def bench_realtime(rounds: int = 6, seconds: float = 6.0) -> dict[str, float]:
    """Real-time quality, in one run: one short run of each side first (not counted), then
    ``rounds`` interleaved rounds of the bare loop (:func:`_bare_loop_period_errors`: it waits
    as the runtime waits), host-timed emulated runs without and with logging (in turn first)
    and a feedback-timed run.

    Overruns are counted per 10,000 deadlines, pooled over the rounds; period errors are
    |wake - deadline| (host timing). ``rt_logged_vs_unlogged_overrun_ratio`` compares the
    pooled overrun counts at the same number of deadlines, a zero unlogged count counting
    as 1; ``rt_vs_bare_period_error_p99_ratio`` is the median of the rounds' ratios of the
    loop's p99 period error to the bare loop's (a load change hits both sides of a round):
    what the loop's own work (poll, compute, send, record) adds to waiting alone. Every
    per-round figure's spread: ``_min``, ``_median``, ``_max``. A run that did not last its
    duration fails the keys it feeds (NaN, one line)."""
    import os
    load_before = os.getloadavg()[0]
    tally = _RtTally()
    with tempfile.TemporaryDirectory() as tmp:
        _bare_loop_period_errors(0.5)
        for timing, logged in _RT_RUNS.values():
            _realtime_run(1.0, timing, Path(tmp) / "warm.mcap" if logged else None)
        for i in range(rounds):
            _realtime_round(i, seconds, Path(tmp), tally)
    out = _realtime_figures(tally)
    out.update(rt_load_average_1min_before=load_before, rt_load_average_1min_after=os.getloadavg()[0])
    return out


def _realtime_figures(tally: _RtTally) -> dict[str, float]:
    """The pooled figures, each round's spread, NaN for every key a failed run feeds."""
    def per_10k(name: str) -> float:
        overruns, deadlines = tally.counts[name]
        return 1e4 * overruns / max(deadlines, 1)

    def median(key: str) -> float:
        return float(np.median(tally.rounds[key])) if tally.rounds.get(key) else float("nan")

    plain, logged = tally.counts["plain"], tally.counts["logged"]
    out = {"rt_overruns_per_10k": per_10k("plain"), "rt_logged_overruns_per_10k": per_10k("logged"),
           "rt_feedback_overruns_per_10k": per_10k("feedback"),
           "rt_period_error_p99_us": median("rt_period_error_p99_us"),
           "bare_loop_period_error_p99_us": median("bare_loop_period_error_p99_us"),
           "rt_feedback_latency_p99_us": median("rt_feedback_latency_p99_us"),
           "rt_logged_vs_unlogged_overrun_ratio": logged[0] * plain[1] / max(logged[1], 1) / max(plain[0], 1),
           "rt_unlogged_overruns": float(plain[0]), "rt_logged_overruns": float(logged[0]),
           "rt_deadlines_each": float(plain[1]),
           "rt_vs_bare_period_error_p99_ratio": median("rt_vs_bare_period_error_p99_ratio")}
    for key, values in tally.rounds.items():
        out.update({f"{key}_min": min(values), f"{key}_median": float(np.median(values)), f"{key}_max": max(values)})
    for key, runs in _RT_KEYS.items():
        if tally.failed.intersection(runs):
            out[key] = float("nan")
    return out


class _StubBus:
    """The cheapest bus there is: ``recv`` returns one prebuilt frame, ``send`` does nothing."""

    def __init__(self) -> None:
        import can
        self.channel_info = "stub"
        self.channel = "stub"
        self.frame = can.Message(arbitration_id=0x069, data=bytes(8), is_extended_id=False)

    def send(self, msg: object, timeout: float | None = None) -> None:
        return None

    def recv(self, timeout: float | None = None) -> object:
        return self.frame


def _handover_us(cycles: int, log: object | None, period: float = 2e-4, sleep: bool = False) -> tuple[float, float]:
    """Loop-thread time per cycle [us] spent in one received and one sent frame plus, when
    ``log`` is given, the recording's tap and cycle sink handing records over; and the CPU
    time per cycle [us] of the whole process (every thread: what a helper thread costs shows
    here, not in the first figure). Each cycle is padded to ``period`` (the loop's own work),
    spinning, or with ``sleep`` sleeping (so the CPU figure counts the work only)."""
    import can
    from types import SimpleNamespace

    from dobhil.runtime.controller import ControlOutput
    stub = _StubBus()
    bus = stub if log is None else log.wrap_bus(stub)  # type: ignore[attr-defined]
    cycle = None if log is None else log.cycle  # type: ignore[attr-defined]
    fb = SimpleNamespace(position=1e-4, velocity=0.0, seq=1)
    out = ControlOutput(1.0, 0.99, 0.01, 0.02, 0.03, 0.03)
    cmd = can.Message(arbitration_id=0x06E, data=bytes(4), is_extended_id=False)
    clock = time.perf_counter
    spent = []
    cpu0 = time.process_time()
    for k in range(cycles):
        t0 = clock()
        bus.recv(0.0)
        bus.send(cmd)
        if cycle is not None:
            cycle(k, k * 1e-3, fb, out, 0.0, 3e-5, False)
        t1 = clock()
        spent.append(t1 - t0)
        if sleep:
            time.sleep(period)
        else:
            while clock() - t0 < period:
                pass
    cpu = (time.process_time() - cpu0) / cycles * 1e6
    # the mean over blocks of 850 cycles: the batch hand-over is paid once per ~40 cycles
    blocks = [sum(spent[i:i + 850]) / 850 for i in range(0, cycles - 849, 850)]
    return float(np.median(blocks)) * 1e6, cpu


def bench_handover() -> dict[str, float]:
    """What logging costs the loop thread per cycle: the tap's two frame records and the cycle
    record, with batches handed to a live writer process, against the same frames unlogged;
    that cost in controller steps measured in the same run (the machine-free figure); and
    the CPU time logging adds to the loop's whole process, at 1 kHz with sleeps between cycles."""
    import tempfile

    from dobhil.recording.process import WriterProcess
    from dobhil.recording.runlog import RunLog
    with tempfile.TemporaryDirectory() as tmp:
        costs, cpu = [], []
        for i in range(3):
            for sleep in (False, True):
                log = RunLog(WriterProcess(Path(tmp) / f"h{i}{sleep}.mcap", fsync=False))
                log.begin(metadata={}, attachments=[], lossy=sleep, truth=lambda: (0.0, 0.0, 0.0, 0.0),
                          own_ids={0x069})  # the stub's frame is the drive's, as in a run
                period = 1e-3 if sleep else 2e-4
                plain = _handover_us(3000 if sleep else 8500, None, period, sleep)
                logged = _handover_us(3000 if sleep else 8500, log, period, sleep)
                log.end("done")
                log.tap.shutdown()  # type: ignore[union-attr]
                if sleep:
                    cpu.append(logged[1] - plain[1])
                else:
                    costs.append(logged[0] - plain[0])
    cost, step = float(np.median(costs)), _controller_step_us()
    return {"loop_thread_log_cost_us_median": cost, "loop_thread_log_cost_vs_controller_step": cost / step,
            "loop_process_log_cpu_us_per_cycle": float(np.median(cpu))}


_LIVE_CLIENT = """
import sys
sys.path.insert(0, sys.argv[2])
from live_client import LiveClient
with LiveClient(sys.argv[1]) as client:
    topics = ["/can/rx", "/can/tx", "/drive/feedback", "/drive/command", "/controller", "/loop", "/emulator/truth"]
    client.wait_for_channels(topics)   # advertised at once: the cycle layout's /cycle with them
    client.subscribe(topics + [t for t in client.channels if t.endswith("/cycle")])
    print("subscribed", flush=True)
    try:
        client.drain(quiet=5.0)
    except Exception:
        pass
"""


def _live_run(duration: float, path: Path, live: bool) -> float:
    """Cycles/s of a logged lockstep demo run, with ``live``: served to a client subscribed to
    every topic and, in the cycle layout, to ``/cycle`` (a separate process, so its work is
    not this process's)."""
    import subprocess

    from dobhil.cli.recording import open_run_log, record_run
    from dobhil.runtime.session import RunSession
    config = load_config(ROOT / "configs/demo.yaml", [f"loop.duration={duration}"])
    path.unlink(missing_ok=True)
    from dobhil.live import LiveServer
    from dobhil.recording.writer import LiveView
    log = open_run_log(path, live=LiveView(LiveServer, "127.0.0.1", 0) if live else None, fsync=False)
    assert log is not None
    clients: list[subprocess.Popen[str]] = []

    def connect(log: object) -> None:
        url = f"ws://127.0.0.1:{log.live_port}"  # type: ignore[attr-defined]
        client = subprocess.Popen([sys.executable, "-c", _LIVE_CLIENT, url, str(ROOT / "tests")],
                                  stdout=subprocess.PIPE, text=True)
        clients.append(client)
        assert client.stdout is not None and client.stdout.readline().strip() == "subscribed"

    with RunSession(config, emulate=True, lockstep=True, sink=log, bus_wrapper=log.wrap_bus) as session:
        t0 = time.perf_counter()
        result = record_run(session, log, on_begin=connect if live else None)
        rate = result.cycles / (time.perf_counter() - t0)
    for client in clients:
        client.wait(30)
    what = "logged lockstep run" + (" served live" if live else "")
    return rate if _ran_whole(result, duration, what) else float("nan")


def bench_live() -> dict[str, float]:
    """Logged lockstep runs served live to a connected client over the same runs not served:
    one short run of each first (not counted), then interleaved pairs."""
    import tempfile
    try:
        import foxglove  # noqa: F401
        import websockets  # noqa: F401
    except ImportError:
        return {}
    served, plain = [], []
    with tempfile.TemporaryDirectory() as tmp:
        _live_run(1.0, Path(tmp) / "warm.mcap", live=False)   # warm-ups, not counted: imports,
        _live_run(1.0, Path(tmp) / "warm.mcap", live=True)    # the writer's and the server's first start
        for _ in range(3):
            plain.append(_live_run(10.0, Path(tmp) / "plain.mcap", live=False))
            served.append(_live_run(10.0, Path(tmp) / "live.mcap", live=True))
    return {"lockstep_live_cycles_per_s": _median_or_nan(served),
            "live_logged_vs_unlogged_ratio": _median_or_nan([a / b for a, b in zip(served, plain)])}


def _killed_run_loss_s(tmp: Path, i: int, seconds: float) -> float:
    """A real-time emulated ``dobhil run --log`` SIGKILLed with its writer (the process group)
    ``seconds`` into the run: the kill time minus the newest ``/loop`` record ``recover`` salvages."""
    import os
    import signal
    import subprocess

    from dobhil.recording.reader import open_log
    from dobhil.recording.recover import recover
    path = tmp / f"kill{i}.mcap"
    run = subprocess.Popen([sys.executable, "-m", "dobhil", "run", str(ROOT / "configs/demo.yaml"), "--emulate",
                            "--duration", "60", "--log", str(path), "--set", "loop.feedback_timeout=0.2"],
                           env={**os.environ, "PYTHONPATH": str(ROOT)}, stdout=subprocess.DEVNULL,
                           stderr=subprocess.DEVNULL, start_new_session=True)
    while not path.exists() or path.stat().st_size < 20000:  # the run has begun
        time.sleep(0.05)
    time.sleep(seconds)
    killed_ns = time.time_ns()
    os.killpg(run.pid, signal.SIGKILL)
    run.wait()
    time.sleep(0.3)  # the writer is gone too (same group)
    saved = tmp / f"kill{i}.recovered.mcap"
    recover(path, saved)
    return (killed_ns - max(t for _, t, _ in open_log(saved).iter_messages(["/loop"]))) / 1e9


def bench_kill(runs: int = 12) -> dict[str, float]:
    """Log lost to a SIGKILL of a real-time run and its writer, pooled over ``runs`` runs
    (killed 2 to 3 s in); every sample printed to stderr."""
    import tempfile
    with tempfile.TemporaryDirectory() as tmp:
        losses = [_killed_run_loss_s(Path(tmp), i, 2.0 + 0.09 * i) for i in range(runs)]
    print("sigkill loss samples [s]:", " ".join(f"{x:.3f}" for x in losses), file=sys.stderr)
    return {"sigkill_loss_s_median": float(np.median(losses)), "sigkill_loss_s_max": max(losses),
            "sigkill_loss_over_0.25s_fraction": sum(x > 0.25 for x in losses) / runs}


#: the CiA 402 demo (the emulated node of drivers/cia402-emulated.yaml, SYNC every 1 ms)
CIA402_CONFIG = ROOT / "configs/cia402-demo.yaml"


def _protocol_run(config_file: Path, duration: float, lockstep: bool, timing: str) -> tuple[float, object]:
    """A demo run of one protocol's config, lockstep or real time in ``timing``; its cycles
    per second of wall time (NaN, and a line, when it did not last its duration) and its result."""
    from dobhil.runtime.session import RunSession
    overrides = [f"loop.duration={duration}"] + ([] if lockstep else [f"loop.timing={timing}",
                                                                      "loop.feedback_timeout=0.05"])
    config = load_config(config_file, overrides)
    with RunSession(config, emulate=True, lockstep=lockstep, config_dir=config_file.parent) as session:
        t0 = time.perf_counter()
        result = session.run()
        rate = result.cycles / (time.perf_counter() - t0)
    what = f"{config_file.stem} {'lockstep' if lockstep else 'real-time'} run"
    return (rate if _ran_whole(result, duration, what) else float("nan")), result


def _cia402_run(duration: float, lockstep: bool) -> tuple[float, object]:
    """A CiA 402 demo run; real time in feedback timing: each cycle on the node's TPDOs,
    the SYNC sent by the emulator's process as a kernel's broadcast manager would."""
    return _protocol_run(CIA402_CONFIG, duration, lockstep, "feedback")


def bench_cia402(rounds: int = 3, seconds: float = 6.0) -> dict[str, float]:
    """CiA 402: lockstep cycles per second (median of runs), and real-time
    1 kHz runs in feedback timing: overruns per 10,000 cycles and the SYNC-to-TPDO
    latency (``sample_latency``: the SYNC's echo to the TPDO received, both bus stamps),
    the median of the runs' p99. A run that did not last its duration fails its keys."""
    lockstep = [_cia402_run(3.0, True)[0] for _ in range(rounds)]
    rt = [_cia402_run(seconds, False) for _ in range(rounds)]
    overruns, deadlines, lasted = _pooled_overruns(rt)
    sync_p99 = [r.timing.sample_latency_p99 for _, r in rt]  # type: ignore[attr-defined]
    sync = [p for p in sync_p99 if p is not None]
    return {"lockstep_cycles_per_s_cia402": _median_or_nan(lockstep),
            "rt_cia402_overruns_per_10k": 1e4 * overruns / max(deadlines, 1) if lasted else float("nan"),
            "rt_cia402_sync_to_tpdo_p99_us": float(np.median(sync)) * 1e6 if sync and lasted else float("nan")}


def _pooled_overruns(runs: list[tuple[float, Any]]) -> tuple[int, int, bool]:
    """Overruns and deadlines (cycles run and skipped) over ``runs`` (``(rate, result)``, a
    NaN rate for a run that did not last), and whether every run lasted."""
    overruns = sum(r.overruns for _, r in runs)
    deadlines = sum(r.cycles + r.skipped for _, r in runs)
    return overruns, deadlines, all(rate == rate for rate, _ in runs)


#: the MIT demo (configs/mit-demo.yaml: an emulated AK80-9, host timing, one period of delay)
MIT_CONFIG = ROOT / "configs/mit-demo.yaml"


def _host_timed_bench(config: Path, name: str, rounds: int, seconds: float) -> dict[str, float]:
    """A protocol whose drive answers each command with one reply and streams nothing (so
    real time is host timing, the config's own): lockstep cycles per second (median of
    runs), and real-time 1 kHz runs: overruns per 10,000 deadlines (cycles run and
    skipped), and the median of the runs' p99 period error. A run that did not last its
    duration fails its keys."""
    lockstep = [_protocol_run(config, 3.0, True, "host")[0] for _ in range(rounds)]
    rt = [_protocol_run(config, seconds, False, "host") for _ in range(rounds)]
    overruns, deadlines, lasted = _pooled_overruns(rt)
    p99 = [r.timing.period_error_p99 for _, r in rt]  # type: ignore[attr-defined]
    return {f"lockstep_cycles_per_s_{name}": _median_or_nan(lockstep),
            f"rt_{name}_overruns_per_10k": 1e4 * overruns / max(deadlines, 1) if lasted else float("nan"),
            f"rt_{name}_period_error_p99_us": float(np.median(p99)) * 1e6 if lasted else float("nan")}


def bench_mit(rounds: int = 3, seconds: float = 6.0) -> dict[str, float]:
    """MIT mode (configs/mit-demo.yaml), host-timed."""
    return _host_timed_bench(MIT_CONFIG, "mit", rounds, seconds)


#: the moteus demo (configs/moteus-demo.yaml: an emulated r4.11 over CAN FD, host timing)
MOTEUS_CONFIG = ROOT / "configs/moteus-demo.yaml"


def bench_moteus(rounds: int = 3, seconds: float = 6.0) -> dict[str, float]:
    """moteus over CAN FD (configs/moteus-demo.yaml), host-timed."""
    return _host_timed_bench(MOTEUS_CONFIG, "moteus", rounds, seconds)


#: the shipped excitation run in contact
IDENTIFY_CONFIG = ROOT / "configs/identify-contact.yaml"
#: what a real rig's log has (sensor quantisation, noise and Coulomb friction on), as
#: tests/identify/test_workflow.py runs it: a 20-bit encoder, 1 mrad/s velocity noise, Coulomb
#: friction, a 0.4 ms input delay
IDENTIFY_SETS = ("plant.coulomb_friction=0.05", "sensor.encoder_resolution=1048576", "sensor.velocity_noise=0.001",
                 "design.input_delay=0.0004", "sensor.seed=1")
_IDENTIFY_FALLBACK = ("reference.kind=chirp", "reference.start=0", "reference.offset=0.5", "reference.amplitude=0.4",
                      "reference.frequency=1", "reference.frequency_end=30")


def _identify_log(path: Path, seconds: float) -> Path:
    """A lockstep emulated excitation run of ``seconds`` (identify-contact: the most
    parameters: inertia, friction, environment, delay), recorded to ``path``."""
    from dobhil.cli.main import main as dobhil
    config, sets = ((str(IDENTIFY_CONFIG), IDENTIFY_SETS) if IDENTIFY_CONFIG.is_file()
                    else ("demo", _IDENTIFY_FALLBACK))
    args = ["run", config, "--emulate", "--lockstep", "--log", str(path), "--set", f"loop.duration={seconds}"]
    for item in sets:
        args += ["--set", item]
    if dobhil(args) not in (0, 1) or not path.is_file():
        raise RuntimeError(f"the excitation run for the identify bench failed: {' '.join(args)}")
    return path


def bench_identify(seconds: float = 60.0) -> dict[str, float]:
    """Wall time of reading, segmenting and identifying a ``seconds`` long 1 kHz log
    (the best of two: a minute of log is long enough to be steady), per minute of log; the
    reading and segmenting alone as well."""
    from dobhil.identify.data import find_segments, read_log
    from dobhil.identify.fit import identify
    with tempfile.TemporaryDirectory() as tmp:
        log = _identify_log(Path(tmp) / "identify.mcap", seconds)
        minutes = seconds / 60.0
        data_only = timed(lambda: find_segments(read_log(log)), repeat=2)
        whole = timed(lambda: identify(data := read_log(log), find_segments(data)), repeat=2)
    return {"identify_seconds_per_minute_of_log": whole / minutes,
            "identify_data_seconds_per_minute_of_log": data_only / minutes}


#: the closed-loop bench's force run: the demo in contact under a 1-30 Hz chirp around 0.8 N m,
#: the hidden plant and sensor of docs/identify.md's closed-loop example (within the 2 N m limit:
#: around 1 N m the noise drove it to the instability watch's saturation stop at 53 s)
CLOSED_LOOP_SETS = ("reference.kind=chirp", "reference.start=0", "reference.offset=0.8", "reference.amplitude=0.5",
                    "reference.frequency=1", "reference.frequency_end=30", "plant.inertia=0.37",
                    "plant.viscous_friction=0.05", "environment.stiffness=15000", "environment.damping=60",
                    "sensor.encoder_resolution=16384", "sensor.velocity_noise=0.05", "sensor.seed=1",
                    "design.input_delay=0.0003")


def _closed_loop_log(path: Path, seconds: float) -> Path:
    """A lockstep emulated force run of ``seconds`` (:data:`CLOSED_LOOP_SETS`) recorded to ``path``."""
    from dobhil.cli.main import main as dobhil
    args = ["run", "demo", "--emulate", "--lockstep", "--log", str(path), "--set", f"loop.duration={seconds}"]
    for item in CLOSED_LOOP_SETS:
        args += ["--set", item]
    if dobhil(args) != 0 or not path.is_file():
        raise RuntimeError(f"the force run for the closed-loop identify bench did not last: {' '.join(args)}")
    return path


def bench_identify_closed_loop(seconds: float = 60.0) -> dict[str, float]:
    """Wall time of reading a ``seconds`` long 1 kHz force run and identifying it in closed
    loop (its controller simulated from the reference), per minute of log: the best of two,
    the first warmed untimed (numba's compilation, cached on disk, is no minute of log)."""
    from dobhil.identify.closedloop import closed_loop_record, identify_closed_loop
    from dobhil.runtime.session import build_controller
    with tempfile.TemporaryDirectory() as tmp:
        log = _closed_loop_log(Path(tmp) / "force.mcap", seconds)
        short = _closed_loop_log(Path(tmp) / "warm.mcap", 0.2)
        identify_closed_loop(closed_loop_record(str(short), build_controller))
        whole = timed(lambda: identify_closed_loop(closed_loop_record(str(log), build_controller)), repeat=2)
    return {"identify_closed_loop_seconds_per_minute_of_log": whole / (seconds / 60.0)}


#: the design ``dobhil tune paper/fig3 --range environment.stiffness=1e3:1e5 --range
#: environment.damping=10:200`` chose (docs/tune.md), and the box it was tuned over
CERTIFY_SETS = ["design.dob_bandwidth=40.6673", "design.rtob_bandwidth=29.2889",
                "design.identified_inertia=0.125154", "design.force_gain=0.623056"]
CERTIFY_RANGES = ["environment.stiffness=1e3:1e5", "environment.damping=10:200"]


def bench_certify(repeat: int = 3, grid: int = 50) -> dict[str, float]:
    """Wall time of the exact continuous certificate of a 2-key box (the tuned Fig. 3 design
    over its box: 4 edges, each an exact gain map, and the gain margin over the box), and of
    the eigenvalues of the same loop on a ``grid`` x ``grid`` grid of that box (what a grid
    check pays, and it decides only its points), interleaved, each warmed untimed first."""
    from dobhil.analysis.certify import box_from_specs, certify_continuous, closed_loop
    config = load_config(ROOT / "configs/paper/fig3.yaml", CERTIFY_SETS)
    box = box_from_specs(CERTIFY_RANGES)
    k, d = np.meshgrid(np.geomspace(1e3, 1e5, grid), np.geomspace(10.0, 200.0, grid))
    points = {"environment.stiffness": k.ravel(), "environment.damping": d.ravel()}
    sides = [Side("certify", lambda: certify_continuous(config, box), lambda: certify_continuous(config, box)),
             Side("grid", lambda: np.linalg.eigvals(closed_loop(config, points, sampled=False)),
                  lambda: np.linalg.eigvals(closed_loop(config, points, sampled=False)))]
    runs = interleaved(sides, repeat)
    return {"certify_seconds_continuous_2d": runs.best("certify"),
            f"certify_grid_{grid}x{grid}_eigenvalue_seconds": runs.best("grid")}


def _montecarlo_campaign(runs: int) -> Any:
    """The bench's campaign: 1 s lockstep runs of the demo, inertia and stiffness drawn."""
    from dobhil.campaign.campaign import Campaign
    from dobhil.campaign.draws import parse_vary
    vary = (parse_vary("plant.inertia=normal:0.25:0.02"), parse_vary("environment.stiffness=loguniform:1e3:1e5"))
    return Campaign(config="demo", set_files=(), overrides=(), varies=vary, runs=runs, seed=0, duration=1.0)


def _montecarlo_batch(client: Any, specs: Sequence[Any], what: str) -> float:
    """Runs per second of ``specs`` on ``client``; NaN (and a line naming the first failed
    run's stop reason or error) unless every run lasted its duration."""
    from dobhil.campaign.campaign import execute
    t0 = time.perf_counter()
    rows = execute(client, specs)
    elapsed = time.perf_counter() - t0
    bad = [r for r in rows if r["error"] or r["stop_reason"] != "done"]
    if bad:
        print(f"bench: {what}: {len(bad)} of {len(rows)} runs did not last their duration, not counted: "
              f"stop reason {bad[0]['stop_reason']!r}, error {bad[0]['error']!r}", file=sys.stderr)
        return float("nan")
    return len(rows) / elapsed


def bench_montecarlo(rounds: int = 3, runs_per_worker: int = 8) -> dict[str, float]:
    """1 s lockstep runs per second on a local cluster of 1 worker process and one of 2,
    both started first and warmed (one run per worker: the workers' imports are start-up,
    not throughput), then ``rounds`` interleaved batches of ``runs_per_worker`` runs per
    worker (1 worker, 2 workers, 1, 2, ...: a load change hits both). Rates pooled over the
    rounds; the rounds' ratios give the spread. A run that failed fails the keys."""
    import contextlib

    from dobhil.cluster import open_client
    per_round = {1: runs_per_worker, 2: 2 * runs_per_worker}
    specs = iter(_montecarlo_campaign(3 + rounds * sum(per_round.values())).plan())
    rates: dict[int, list[float]] = {1: [], 2: []}
    with contextlib.ExitStack() as stack:
        clients = {n: stack.enter_context(open_client(workers=n)) for n in per_round}
        for n, client in clients.items():
            _montecarlo_batch(client, [next(specs) for _ in range(n)], f"warm-up on {n} workers")
        for i in range(rounds):
            for n, client in clients.items():
                batch = [next(specs) for _ in range(per_round[n])]
                rates[n].append(_montecarlo_batch(client, batch, f"round {i + 1} on {n} worker(s)"))
    one, two = _pooled_rate(rates[1], per_round[1]), _pooled_rate(rates[2], per_round[2])
    ratios = [b / a for a, b in zip(rates[1], rates[2])]
    return {"montecarlo_runs_per_s_1_worker": one, "montecarlo_runs_per_s_2_workers": two,
            "montecarlo_scaling_2_workers": two / one,
            "montecarlo_scaling_2_workers_min": min(ratios), "montecarlo_scaling_2_workers_max": max(ratios)}


def _pooled_rate(rates: list[float], runs: int) -> float:
    """Runs per second over batches of ``runs`` runs each (NaN if a batch failed)."""
    return len(rates) * runs / sum(runs / r for r in rates)


def _load_canvm():  # type: ignore[no-untyped-def]
    import importlib.util
    spec = importlib.util.spec_from_file_location("dobhil_canvm_bench", ROOT / "tools" / "canvm" / "canvm.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def bench_socketcan() -> dict[str, float]:
    """Guest figures: the kernel guest of tools/canvm booted once (its boot time and which
    accelerator ran), and in it tools/canvm/figures.py's ``rt_guest`` (a 10 s, 1 kHz MIT run
    over vcan with SCHED_FIFO, next to a bare loop that waits as the runtime waits, before and
    after) and ``bcm_sync_jitter`` (the kernel's broadcast-manager SYNC against a loop-sent
    one, candump's kernel stamps). Under software emulation (TCG) they describe this
    machine's emulated kernel, not a real one; the run's overruns are reported only when it
    lasted its duration (else its stop reason). Skipped, with the reason, without the guest."""
    canvm = _load_canvm()
    try:
        canvm.find_requirements()
    except canvm.Missing as exc:
        print(f"bench: socketcan skipped: {exc}", file=sys.stderr)
        return {}
    with tempfile.TemporaryDirectory(prefix="bench-canvm-") as tmp:
        run = canvm.run_in_guest([sys.executable, str(ROOT / "tools" / "canvm" / "figures.py"),
                                  "rt_guest", "bcm_sync_jitter"], job_dir=Path(tmp), cwd=ROOT, timeout=1800)
        text = (Path(tmp) / "console.log").read_text(errors="replace")
    lines = [line.split("figures: ", 1)[1] for line in text.splitlines() if line.startswith("figures: ")]
    if run.exit_status != 0 or not lines:
        raise RuntimeError(f"bench socketcan: the guest's figures failed ({run.reason or run.exit_status}): "
                           f"{text[-500:]}")
    figures = json.loads(lines[-1])
    rt, bare = figures["rt_guest"]["run"], figures["rt_guest"]["bare_before"]
    out: dict[str, float] = {"socketcan_guest_boot_s": float(run.boot_s),
                             "socketcan_guest_kvm": float(run.accel == "kvm"),
                             "socketcan_bare_overruns_per_10k": float(bare["overruns_per_10k"]),
                             "socketcan_bare_period_error_p99_us": float(bare["period_error_p99_us"])}
    if rt.get("lasted"):
        out["socketcan_rt_overruns_per_10k"] = float(rt["overruns_per_10k"])
        out["socketcan_rt_period_error_p99_us"] = float(rt["period_error_p99_us"])
    else:
        print(f"bench: socketcan_rt_overruns_per_10k not measured: the 1 kHz run in the guest stopped "
              f"({rt.get('stop_reason')}: {rt.get('stop_detail') or rt.get('error')})", file=sys.stderr)
    jitter = figures["bcm_sync_jitter"]
    out["bcm_sync_jitter_p99_us"] = float(jitter["p99_us"])
    print(f"bench: socketcan: {run.summary()}; figures {json.dumps(figures)}", file=sys.stderr)
    return out


BENCHES: dict[str, Callable[[], dict[str, float]]] = {
    "sweep": bench_sweep,
    "controller": bench_controller,
    "lockstep": bench_lockstep,
    "axes": bench_axes,
    "rt_axes": bench_rt_axes,
    "logging": bench_logging,
    "log_encoding": bench_log_encoding,
    "realtime": bench_realtime,
    "handover": bench_handover,
    "live": bench_live,
    "kill": bench_kill,
    "cia402": bench_cia402,
    "mit": bench_mit,
    "moteus": bench_moteus,
    "identify": bench_identify,
    "certify": bench_certify,
    "identify_closed_loop": bench_identify_closed_loop,
    "montecarlo": bench_montecarlo,
    "socketcan": bench_socketcan,
}


#: the benches ``--repeat N`` gives N rounds (the real-time ones: their figures move the most)
REPEATABLE = ("realtime", "rt_axes")


def targets_met(results: dict[str, float]) -> dict[str, dict[str, Any]]:
    """Each measured target: its kind, its bound and whether the figure meets it (NaN -- a
    run that did not last -- never does)."""
    out: dict[str, dict[str, Any]] = {}
    for key, value in results.items():
        if key in TARGETS:
            out[key] = {"kind": kind(key).name.lower(), "min": TARGETS[key], "met": bool(value >= TARGETS[key])}
        elif key in TARGETS_MAX:
            out[key] = {"kind": kind(key).name.lower(), "max": TARGETS_MAX[key], "met": bool(value <= TARGETS_MAX[key])}
    return out


def _line(key: str, value: float, target: dict[str, Any] | None) -> str:
    """One printed figure; a target with its kind and MISSED when missed."""
    text = f"{key:44s} {value:>14,.3f}"
    if target is not None:
        bound = f">= {target['min']:g}" if "min" in target else f"<= {target['max']:g}"
        text += f"   ({target['kind']} target {bound}{'' if target['met'] else ': MISSED'})"
    return text


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--check", action="store_true", help="exit 1 when a target is missed")
    ap.add_argument("--only", choices=sorted(BENCHES), action="append")
    ap.add_argument("--repeat", type=int, metavar="N",
                    help=f"rounds of the real-time benches ({', '.join(REPEATABLE)}), pooled, with their spread")
    args = ap.parse_args(argv)
    if args.repeat is not None and args.repeat < 1:
        ap.error(f"--repeat: expected a whole number >= 1, got {args.repeat}")
    results: dict[str, float] = {}
    # what the measured runs print (a run's stop line, its log) goes to stderr: with --json,
    # stdout is the one JSON object a script parses
    with contextlib.redirect_stdout(sys.stderr):
        for name in args.only or BENCHES:
            bench = BENCHES[name]
            results.update(bench(rounds=args.repeat) if args.repeat and name in REPEATABLE  # type: ignore[call-arg]
                           else bench())
    rounded = {k: round(v, 3) for k, v in results.items()}
    targets = targets_met(results)
    if args.json:
        print(json.dumps({**rounded, "targets": targets}))
    else:
        for k, v in rounded.items():
            print(_line(k, v, targets.get(k)))
    missed = [k for k, t in targets.items() if not t["met"]]
    return 1 if args.check and missed else 0


if __name__ == "__main__":
    raise SystemExit(main())
