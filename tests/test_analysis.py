"""Stability map, analysis report, sweep and the paper's claims."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from dobhil.analysis.stability import gain_map, is_stable
from dobhil.analysis.sweep import parse_vary, sweep
from dobhil.cli.main import main
from dobhil.plotting.figures import _plt
from dobhil.config import load_config
from dobhil.synthesis.loop import loop
from dobhil.synthesis.params import params_from_config


def brute_force_changes(a, b, c, sampled: bool, lo=-3, hi=4, num=30001):  # type: ignore[no-untyped-def]
    ks = np.logspace(lo, hi, num)
    st = is_stable(np.linalg.eigvals(a[None] - ks[:, None, None] * (b @ c)[None]), sampled)
    return st[0], ks[1:][st[1:] != st[:-1]]


def open_loop(overrides: list[str], sampled: bool, path: str = "configs/paper/fig2c.yaml"):  # type: ignore[no-untyped-def]
    cfg = load_config(path, overrides)
    a, b, c, _ = loop(params_from_config(cfg), sampled=sampled, force_gain=0.0).siso(
        "tau_per", "tau_int_hat")
    return a, b, c


CASES = [
    ([], False), ([], True), (["design.delay_samples=2"], True),
    (["design.identified_inertia=0.24191919191919192", "environment.stiffness=95454.8"], False),
    (["design.identified_inertia=0.13636363636363635", "environment.stiffness=83021.76"], True),
    (["design.velocity_source=estimated", "design.velocity_filter_bandwidth=3000"], True),
    (["design.interaction_model=ramp", "design.disturbance_model=sinusoid"], False),
    (["plant.viscous_friction=0.5", "design.identified_inertia=0.2"], True),
]


@pytest.mark.parametrize("overrides,sampled", CASES)
def test_stable_gain_intervals_agree_with_a_dense_gain_scan(overrides: list[str], sampled: bool) -> None:
    a, b, c = open_loop(overrides, sampled)
    g = gain_map(a, b, c, sampled=sampled)
    first, changes = brute_force_changes(a, b, c, sampled)
    edges = sorted({e for iv in g.intervals() for e in iv if 0 < e < np.inf})
    assert len(edges) == len(changes)
    for e, ch in zip(edges, changes):
        assert e == pytest.approx(ch, rel=1e-3)
    assert bool(first) == (g.intervals()[0][0] == 0.0 if g.intervals() else False)
    # exactness: just inside each bound is stable, just outside is not
    for _lo, hi in g.intervals():
        if np.isfinite(hi):
            inside, outside = hi * (1 - 1e-6), hi * (1 + 1e-6)
            st = is_stable(np.linalg.eigvals(np.stack([a - inside * b @ c, a - outside * b @ c])),
                           sampled)
            assert st.tolist() == [True, False]


def test_a_crossing_the_roots_place_exactly_costs_two_eigenvalue_problems(monkeypatch: pytest.MonkeyPatch) -> None:
    """L = 1 / (s (s + 1) (s + 2)): s^3 + 3 s^2 + 2 s + k crosses the axis at k = 6 exactly.
    Given 6, polishing brackets it at once (two eigenvalue problems, not the bracket and
    iterations: 6 and more); given 6 (1 + 1e-4), it still finds 6."""
    from dobhil.analysis import stability
    a0 = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, -2.0, -3.0]])[None]
    bc = np.outer([0.0, 0.0, 1.0], [1.0, 0.0, 0.0])[None]
    solved = [0]
    margin = stability._spectral_margin

    def counted(a: np.ndarray, sampled: bool) -> np.ndarray:
        solved[0] += a.shape[0]
        return margin(a, sampled)
    monkeypatch.setattr(stability, "_spectral_margin", counted)
    exact = stability._polish(a0, bc, np.array([[6.0, np.nan]]), sampled=False)
    assert solved[0] == 2 and exact[0, 0] == pytest.approx(6.0, rel=1e-13) and np.isnan(exact[0, 1])
    assert stability._polish(a0, bc, np.array([[6.0006]]), sampled=False)[0, 0] == pytest.approx(6.0, rel=1e-12)


def test_the_crossings_polynomial_is_solved_at_half_its_degree(monkeypatch: pytest.MonkeyPatch) -> None:
    """L = (s^2 - s + 4) / (s (s + 1) (s + 2)): the characteristic polynomial
    s^3 + (3 + k) s^2 + (2 - k) s + 4 k has roots on the axis at k = 1 (s = +-j) only.
    Im(D(jw) conj(N(jw))) is odd, of degree 5: its roots come from a polynomial in w^2 of
    degree 2, not from a 5 x 5 companion matrix (the map's largest eigenvalue problem
    before; now the 3 x 3 loop's)."""
    a0 = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, -2.0, -3.0]])
    b, c = np.array([[0.0], [0.0], [1.0]]), np.array([[4.0, -1.0, 1.0]])
    sizes = []
    eigvals = np.linalg.eigvals

    def recorded(m: np.ndarray) -> np.ndarray:
        sizes.append(m.shape[-1])
        return eigvals(m)
    monkeypatch.setattr(np.linalg, "eigvals", recorded)
    g = gain_map(a0, b, c, sampled=False)
    assert max(sizes) == 3
    assert [float(k) for k in g.crossings if np.isfinite(k)] == [pytest.approx(1.0, rel=1e-13)]
    assert g.intervals() == [(0.0, pytest.approx(1.0, rel=1e-13))]


def test_conditionally_stable_design_is_reported_with_both_intervals() -> None:
    a, b, c = open_loop(CASES[3][0], False)
    g = gain_map(a, b, c, sampled=False)
    assert len(g.intervals()) == 2
    assert np.isfinite(g.max_stable_gain) and np.isinf(g.intervals()[-1][1])


def run_json(capsys: pytest.CaptureFixture[str], *argv: str) -> dict:
    assert main(list(argv)) == 0
    return json.loads(capsys.readouterr().out)


@pytest.mark.parametrize("case,bounded", [("a", False), ("b", False), ("c", True), ("d", False)])
def test_analyze_json_max_stable_gain_of_fig2(case: str, bounded: bool,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    out = run_json(capsys, "analyze", f"configs/paper/fig2{case}.yaml", "--json")
    cont = out["continuous"]
    assert (cont["max_stable_force_gain"] is not None) == bounded
    for dom in ("continuous", "discrete"):
        d = out[dom]
        assert {"open_loop", "closed_loop", "max_stable_force_gain", "stable_force_gain_intervals",
                "margins", "step"} <= set(d)
        assert {"poles", "zeros", "relative_degree", "minimum_phase"} <= set(d["open_loop"])
        assert d["closed_loop"]["position_drifts"] is False
        assert {"overshoot_pct", "rise_time", "settling_time", "steady_state_error"} <= set(d["step"])
    assert out["discrete"]["sample_time"] == 0.001 and out["discrete"]["delay_samples"] == 0
    if bounded:
        assert cont["max_stable_force_gain"] == pytest.approx(1.1187029, rel=1e-6)
        assert cont["open_loop"]["minimum_phase"] is False


def test_analyze_writes_plots(tmp_path, capsys: pytest.CaptureFixture[str]) -> None:  # type: ignore[no-untyped-def]
    assert main(["analyze", "configs/paper/fig2b.yaml", "--plot", str(tmp_path)]) == 0
    for name in ("root_locus.png", "step.png", "bode.png"):
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("overrides", [["design.identified_inertia=0.3"],    # a zero at +1171 rad/s
                                       ["design.identified_inertia=1.0", "design.force_gain=2.0"]])  # unstable
def test_root_locus_shows_the_right_half_plane_zero_and_unstable_poles(overrides: list[str]) -> None:
    """The continuous root locus' axes reach every right-half-plane zero and closed-loop
    pole: they are what bound C_f, and a plot cut short of them reads as a stable loop."""
    from dobhil.paper import continuous
    from dobhil.plotting.figures import _plt, root_locus
    d = continuous(load_config("configs/paper/fig2c.yaml", overrides))
    zeros = d.gains.zeros[~np.isnan(d.gains.zeros)]
    rightmost = float(np.concatenate([zeros, d.closed_loop_poles]).real.max())
    fig, ax = _plt().subplots()
    try:
        root_locus(ax, d)
        assert rightmost > 0 and ax.get_xlim()[1] > rightmost
    finally:
        _plt().close(fig)


def test_the_step_figure_names_the_domain_whose_loop_is_unstable(tmp_path: Path,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """The demo at C_f = 12: its continuous loop is stable, its sampled one (the runtime's)
    not. Beside the continuous step, the note of no step says it is the sampled loop's."""
    from dobhil.plotting import figures as plotting
    drawn: list[Any] = []
    monkeypatch.setattr(plotting, "save", lambda fig, path: drawn.append(fig) or path)
    from dobhil.analysis.report import analyze_domain
    params = params_from_config(load_config("demo", ["design.force_gain=12"]))
    plotting.analysis_figures(analyze_domain(params, sampled=False), analyze_domain(params, sampled=True), tmp_path)
    step = drawn[1].axes[0]
    try:
        assert [t.get_text() for t in step.texts] == ["estimated tau_int (sampled): closed loop unstable, no step"]
        assert [str(line.get_label()) for line in step.get_lines()][0] == "estimated tau_int (continuous)"
    finally:
        for fig in drawn:
            _plt().close(fig)


def test_step_metrics_of_a_closed_loop_match_python_control(capsys: pytest.CaptureFixture[str]) -> None:
    import control
    out = run_json(capsys, "analyze", "configs/paper/fig3.yaml", "--json")["continuous"]["step"]
    cfg = load_config("configs/paper/fig3.yaml")
    from dobhil.analysis.transfer import LoopSystems
    sys = LoopSystems.build(params_from_config(cfg), sampled=False).system("closed_loop")
    info = control.step_info(sys, SettlingTimeThreshold=0.02, RiseTimeLimits=(0.1, 0.9))
    assert out["overshoot_pct"] == pytest.approx(info["Overshoot"], rel=2e-2)
    assert out["rise_time"] == pytest.approx(info["RiseTime"], rel=2e-2)
    assert out["settling_time"] == pytest.approx(info["SettlingTime"], rel=5e-2)
    assert abs(out["steady_state_error"]) < 1e-9


@pytest.mark.parametrize(("horizon", "settling"), [(10.0, -math.log(0.02)), (2.0, None), (0.1, None)])
def test_a_response_outside_the_band_at_the_horizon_has_no_settling_time(horizon: float,
                                                                         settling: float | None) -> None:
    """1 - exp(-t) enters the 2 % band at ln 50 = 3.91 s; over a shorter horizon
    (analysis.step_duration) it has not settled, and the horizon's end is no settling time."""
    from dobhil.analysis.metrics import step_metrics
    t = np.linspace(0.0, horizon, 100_001)
    m = step_metrics(t, 1.0 - np.exp(-t), final=1.0)
    assert m.settling_time == (None if settling is None else pytest.approx(settling, abs=1e-3))


@pytest.mark.parametrize("sampled", [False, True])
def test_sweep_equals_pointwise_analysis(sampled: bool) -> None:
    cfg = load_config("configs/paper/fig2b.yaml")
    axes = [parse_vary("design.identified_inertia=0.1:0.6:4"),
            parse_vary("environment.stiffness=log:1e3:1e5:3")]
    res = sweep(cfg, axes, sampled=sampled, chunk=5)
    for i, ji in enumerate(axes[0].values):
        for j, k in enumerate(axes[1].values):
            a, b, c = open_loop([f"design.identified_inertia={float(ji)!r}", f"environment.stiffness={float(k)!r}"],
                                sampled, "configs/paper/fig2b.yaml")
            g = gain_map(a, b, c, sampled=sampled)
            assert res.max_stable_gain[i, j] == pytest.approx(float(g.max_stable_gain), rel=1e-9)
            assert res.minimum_phase[i, j] == bool(g.minimum_phase)


def test_sweep_cli_writes_csv_and_heatmap(tmp_path, capsys: pytest.CaptureFixture[str]) -> None:  # type: ignore[no-untyped-def]
    csv_path, png = tmp_path / "s.csv", tmp_path / "s.png"
    assert main(["sweep", "configs/paper/fig2b.yaml", "--vary", "design.identified_inertia=0.1:0.5:5",
                 "--vary", "environment.stiffness=log:1e3:1e5:4", "--sampled", "--out", str(csv_path),
                 "--plot", str(png)]) == 0
    lines = csv_path.read_text().splitlines()
    assert len(lines) == 1 + 20 and lines[0].startswith("design.identified_inertia,environment.stiffness")
    assert png.read_bytes()[:4] == b"\x89PNG"


@pytest.mark.parametrize("first, second", [("environment.damping=10:10:1", "environment.stiffness=log:1e3:1e5:3"),
                                           ("environment.damping=10:20:3", "environment.stiffness=1e4:1e4:1")])
def test_sweep_heatmap_of_two_keys_one_held_at_one_value(first: str, second: str, tmp_path) -> None:  # type: ignore[no-untyped-def]
    """Two swept keys of which one has a single value draw the line over the other (the
    heat map's contours need two values of each: matplotlib raised a TypeError)."""
    from dobhil.plotting.sweep_plot import heatmap
    result = sweep(load_config(FIG2A), [parse_vary(first), parse_vary(second)], sampled=False)
    assert heatmap(result, tmp_path / "h.svg").read_text().startswith("<?xml")


def test_a_map_with_no_finite_max_stable_gain_has_no_colour_bar(tmp_path: Path,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """Every point unbounded (the demo's continuous loop over C_f and D_env): nothing is
    coloured, and a colour bar said "max stable C_f" from -0.1 to 0.1, values no point has."""
    from dobhil.plotting import sweep_plot
    figures = []
    monkeypatch.setattr(sweep_plot, "save", lambda fig, path: figures.append(fig) or path)
    varies = ["design.force_gain=1:10:3", "environment.damping=10:50:3"]
    result = sweep(load_config("demo"), [parse_vary(v) for v in varies], sampled=False)
    assert np.isinf(result.max_stable_gain).all()
    sweep_plot.heatmap(result, tmp_path / "h.png")
    try:
        assert len(figures[0].axes) == 1   # the map alone
    finally:
        _plt().close(figures[0])

def test_a_key_held_at_one_value_given_twice_draws_the_line_not_an_empty_map(tmp_path: Path,
                                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """``design.force_gain=1:1:2`` holds C_f at 1 (two equal values): as an axis of the map its
    cells had no height, an empty picture; it is held, as NUM 1 is, and the line drawn over
    the other key."""
    from dobhil.plotting import sweep_plot
    figures = []
    monkeypatch.setattr(sweep_plot, "save", lambda fig, path: figures.append(fig) or path)
    varies = ["design.force_gain=1:1:2", "environment.damping=10:20:3"]
    result = sweep(load_config(FIG2A), [parse_vary(v) for v in varies], sampled=True)
    sweep_plot.heatmap(result, tmp_path / "h.png")
    ax = figures[0].axes[0]
    try:
        lines = [line for line in ax.get_lines() if list(line.get_xdata()) == [10.0, 15.0, 20.0]]
        assert len(lines) == 1 and np.allclose(lines[0].get_ydata(), result.max_stable_gain[0])
        assert "(design.force_gain = 1)" in ax.get_xlabel()
    finally:
        _plt().close(figures[0])

@pytest.mark.parametrize("varies", [["design.dob_bandwidth=log:10:1e4:8"],
                                    ["design.dob_bandwidth=log:10:1e4:8", "design.rtob_bandwidth=log:10:1e4:3"]])
def test_sweep_heatmap_marks_a_max_stable_gain_of_zero(varies: list[str], tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """A max stable C_f of 0 (unstable at small gains: the demo delayed 2 samples above
    g_DOb ~ 1000 rad/s) has no place on the log scale: unmarked, its gap or blank cell would
    read as the unbounded one the figure's labels name, the opposite."""
    from dobhil.plotting import sweep_plot
    figures = []
    monkeypatch.setattr(sweep_plot, "save", lambda fig, path: figures.append(fig) or path)
    result = sweep(load_config("configs/demo.yaml", ["design.delay_samples=2"]), [parse_vary(v) for v in varies],
                   sampled=True)
    zero = result.max_stable_gain == 0
    assert zero.any() and (result.max_stable_gain > 0).any()
    sweep_plot.heatmap(result, tmp_path / "h.png")
    ax = figures[0].axes[0]
    try:
        if len(varies) == 1:
            marks = [line for line in ax.get_lines() if "unstable at small C_f" in str(line.get_label())]
            assert len(marks) == 1 and list(marks[0].get_xdata()) == list(result.axes[0].values[zero])
            assert ax.get_xscale() == "log"   # a log: axis: 10..1e4 rad/s, not 5 of 8 points in the left 5 %
        else:
            assert "crossed: 0" in ax.get_title()
            assert any(list(getattr(c, "hatches", None) or []) == ["xx"] for c in ax.collections)
    finally:
        _plt().close(figures[0])


@pytest.mark.parametrize("vary", ["environment.stiffness=log:1e2:1e6:6", "design.force_gain=1:1:1"])
def test_a_swept_line_shows_its_whole_range_and_marks_unbounded_points(vary: str, tmp_path: Path,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """An unbounded max stable C_f has no place on the log axis: its gap alone left the x axis on
    the finite points (1e2..1e6 drawn as 4.6e5..1e6), or, all unbounded, on -0.05..0.05 around
    no swept value; a mark on the top edge keeps each in the picture."""
    from dobhil.plotting import sweep_plot
    figures = []
    monkeypatch.setattr(sweep_plot, "save", lambda fig, path: figures.append(fig) or path)
    result = sweep(load_config("demo"), [parse_vary(vary)], sampled=False)
    unbounded = np.isinf(result.max_stable_gain)
    assert unbounded.any()
    sweep_plot.heatmap(result, tmp_path / "h.png")
    ax = figures[0].axes[0]
    try:
        values = result.axes[0].values
        lo, hi = ax.get_xlim()
        assert lo <= values.min() and values.max() <= hi
        marks = [line for line in ax.get_lines() if "unbounded" in str(line.get_label())]
        assert len(marks) == 1 and list(marks[0].get_xdata()) == list(values[unbounded])
    finally:
        _plt().close(figures[0])
def test_paper_command_checks_every_claim(tmp_path, capsys: pytest.CaptureFixture[str]) -> None:  # type: ignore[no-untyped-def]
    assert main(["paper", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "FAILS" not in out and out.count("[ok]") >= 11
    assert (tmp_path / "fig2_root_locus.png").exists() and (tmp_path / "fig3_step.png").exists()


BAD = [
    (["--set", "plant.inertia=-1"], "plant.inertia = -1.0: must be > 0"),
    (["--set", "design.dob_bandwidth=0"], "design.dob_bandwidth = 0.0: must be > 0"),
    (["--set", "design.nonsense=1"], "unknown config key 'design.nonsense'"),
    (["--set", "design.force_gain=abc"], "design.force_gain = 'abc': wrong type str"),
    (["--set", "design.interaction_model=cubic"], "allowed: constant, ramp, sinusoid"),
    (["--set", "novalue"], "expected key=value"),
]


@pytest.mark.parametrize("extra,message", BAD)
def test_bad_input_is_one_clear_line(extra: list[str], message: str,
                                     capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["analyze", "configs/paper/fig2a.yaml", *extra]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1 and "Traceback" not in err


def test_yaml_syntax_error_names_the_line(tmp_path, capsys: pytest.CaptureFixture[str]) -> None:  # type: ignore[no-untyped-def]
    bad = tmp_path / "bad.yaml"
    bad.write_text("plant:\n  inertia: 0.25\n  damping: [1, 2\n")
    assert main(["analyze", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "YAML syntax error at line" in err and err.count("\n") == 1


@pytest.mark.parametrize("key", ["design.delay_samples", "design.input_delay", "loop.period"])
def test_sweep_rejects_structural_keys(key: str, capsys: pytest.CaptureFixture[str]) -> None:
    """Refused, and the README's command table names them: the table and the command agree."""
    assert main(["sweep", "configs/paper/fig2a.yaml", "--vary", f"{key}=0:0.0005:3"]) == 2
    assert "cannot be swept" in capsys.readouterr().err
    readme = (Path(__file__).parent.parent / "README.md").read_text()
    row = next(line for line in readme.splitlines() if line.startswith("| `dobhil sweep "))
    assert "any other config key -- `loop.period`, `design.delay_samples` and `design.input_delay` shape" in row


# --- designs that fail the analysis, and bad analysis inputs

FIG2A = "configs/paper/fig2a.yaml"
CRASHED = [
    ["environment.damping=0", "design.rtob_bandwidth=2000"],
    ["design.interaction_model=ramp"],
    ["design.disturbance_model=sinusoid", "design.disturbance_frequency=1",
     "design.dob_bandwidth=2000"],
]


@pytest.mark.parametrize("overrides", CRASHED)
def test_designs_that_crashed_are_answered(overrides: list[str],
                                           capsys: pytest.CaptureFixture[str]) -> None:
    path = "configs/paper/fig2c.yaml" if "design.disturbance_model=sinusoid" in overrides else FIG2A
    out = run_json(capsys, "analyze", path, "--json", *(f"--set={o}" for o in overrides))
    cont = out["continuous"]
    if overrides == CRASHED[0]:   # J_mi = J_m, D_env = 0: L ~ (s + g_D) K / (s^4 ...)
        assert cont["open_loop"]["relative_degree"] == 3
    a, b, c = open_loop(overrides, False, path)
    first, changes = brute_force_changes(a, b, c, False)
    edges = sorted({e for iv in cont["stable_force_gain_intervals"] for e in iv if e and e > 0})
    assert len(edges) == len(changes)


def test_sweep_points_at_zero_stiffness_are_said_apart(capsys: pytest.CaptureFixture[str]) -> None:
    """K_env = 0 has no stable C_f (the position drifts): the largest safe C_f is the other
    points', not 0."""
    assert main(["sweep", "demo", "--sampled", "--vary", "environment.stiffness=0:1e4:3"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[1].startswith("1 point at environment.stiffness = 0: the position drifts at every C_f")
    alone = sweep(load_config("demo"), [parse_vary("environment.stiffness=5e3:1e4:2")], sampled=True)
    assert out[2] == f"largest C_f safe over the points with environment.stiffness > 0: " \
                     f"{float(alone.max_stable_gain.min()):.6g}"



def test_sweep_points_too_soft_to_resolve_are_said_apart(capsys: pytest.CaptureFixture[str]) -> None:
    """K_env 1e-9 N m/rad: the position's pole is within the analysis' resolution of z = 1,
    as good as K_env = 0. The sweep said "largest C_f safe over the whole grid: 0" because of
    that one point; it is said apart as a point at 0 is."""
    assert main(["sweep", "demo", "--sampled", "--vary", "environment.stiffness=log:1e-9:1e4:3"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[1].startswith("1 point where environment.stiffness is 0 or too small to hold the position"), out
    alone = sweep(load_config("demo"), [parse_vary("environment.stiffness=log:1e-9:1e4:3")], sampled=True)
    assert out[2] == f"largest C_f safe over the other points: {float(alone.max_stable_gain[1:].min()):.6g}"
    assert not alone.drifting[1:].any() and alone.drifting[0]


def test_the_open_loop_at_c_f_0_does_not_drift() -> None:
    """At C_f = 0 the closed loop is the open loop, whose integrator sits at s = 0 / z = 1: no
    drift of the position (K_env 1e4 holds it), and the stable C_f reach from 0 is said."""
    from dobhil.analysis.report import analyze_domain
    from dobhil.synthesis.params import params_from_config
    config = load_config("demo", ["design.force_gain=0"])
    for sampled in (False, True):
        assert not analyze_domain(params_from_config(config), sampled=sampled).position_drifts
    result = sweep(load_config("demo"), [parse_vary("design.force_gain=0:10:3")], sampled=True)
    assert not result.drifting.any()

def test_the_sweep_that_crashed_answers_every_point(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["sweep", FIG2A, "--set", "design.rtob_bandwidth=2000", "--vary",
                 "environment.damping=0:100:11", "--vary", "design.dob_bandwidth=500:1000:3"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("33 points") and "could not be analysed" not in out


def test_a_one_point_sweep_says_point_not_points(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["sweep", FIG2A, "--vary", "design.force_gain=1:1:1"]) == 0
    assert capsys.readouterr().out.startswith("1 point (continuous): 1 stable at its C_f, 1 minimum phase")
    # one point left unanswered (built past --vary's floor, as no command can): said in the singular too
    from dobhil.analysis.sweep import Axis
    from dobhil.cli.sweep_cmd import _summary
    result = sweep(load_config(FIG2A), [Axis("plant.inertia", np.array([1e-300, 0.25]))], sampled=False)
    _summary(result, np.zeros(2, bool), np.zeros(2, bool))
    assert "\n1 point could not be analysed (its matrices overflow or numpy cannot decompose them); it is left " \
           "empty in --out\n" in capsys.readouterr().out
def test_the_integrator_is_no_unstable_sliver(capsys: pytest.CaptureFixture[str]) -> None:
    args = ["design.identified_inertia=1.0", "design.dob_bandwidth=70", "environment.stiffness=232",
            "loop.period=0.00018", "design.force_gain=0.1", "design.discretization=zoh"]
    d = run_json(capsys, "analyze", FIG2A, "--json", *(f"--set={o}" for o in args))["discrete"]
    assert d["stable_force_gain_intervals"][0][0] == 0.0
    assert d["stable_force_gain_intervals"][0][1] == pytest.approx(0.46523, abs=5e-6)
    assert d["max_stable_force_gain"] == d["stable_force_gain_intervals"][0][1]


def test_fast_oscillation_on_slow_settling_keeps_its_overshoot(
        capsys: pytest.CaptureFixture[str]) -> None:
    args = ["design.force_gain=40", "environment.stiffness=600", "environment.damping=200",
            "plant.inertia=0.06", "design.identified_inertia=0.06", "design.nominal_inertia=0.04"]
    step = run_json(capsys, "analyze", FIG2A, "--json",
                    *(f"--set={o}" for o in args))["continuous"]["step"]
    assert step["overshoot_pct"] == pytest.approx(48.5, abs=0.5)


def test_conditionally_stable_loop_reports_zero_max_gain(capsys: pytest.CaptureFixture[str]) -> None:
    """Unstable for small C_f (20 samples of delay), stable on a band: max 0, band listed."""
    d = run_json(capsys, "analyze", FIG2A, "--json", "--set",
                 "design.delay_samples=20")["discrete"]
    (lo, hi), = d["stable_force_gain_intervals"]
    assert lo == pytest.approx(0.3819, rel=1e-3) and hi == pytest.approx(2.963, rel=1e-3)
    assert d["max_stable_force_gain"] == 0.0


BAD_ANALYSIS = [
    (["analyze", FIG2A, "--set", "design.force_gain=1e308"], "design.force_gain"),
    (["analyze", FIG2A, "--set", "design.delay_samples=200"], "<= 20"),
    (["analyze", FIG2A, "--set", "analysis.step_duration=1e-320"], "analysis.step_duration"),
    (["analyze", FIG2A, "--set", "analysis.step_duration=1847"], "samples"),
    (["analyze", FIG2A, "--set", "design.force_gain=" + "1" + "0" * 399], "400 digits"),
    # within > 0 and still past what the matrices hold (1/J_m overflows; exp(-g T) rounds to 1):
    # the key's floor names the key, on every command that loads a config or takes its range
    (["analyze", FIG2A, "--set", "plant.inertia=1e-300"],
     "plant.inertia = 1e-300: out of range; allowed: >= 1e-12 and <= 1e+06 kg m^2"),
    (["analyze", FIG2A, "--set", "design.dob_bandwidth=1e-15"],
     "design.dob_bandwidth = 1e-15: out of range; allowed: >= 0.001 and <= 1e+07 rad/s"),
    (["run", FIG2A, "--emulate", "--lockstep", "--set", "plant.inertia=1e-300"], "plant.inertia = 1e-300: out of"),
    # a period no CAN bus carries one frame in (accepted before with a bus-budget note only)
    (["analyze", FIG2A, "--set", "loop.period=1e-12"],
     "loop.period = 1e-12: out of range; allowed: >= 3.4e-05 and <= 10 s"),
    (["sweep", FIG2A, "--vary", "plant.inertia=log:1e-300:1:3"], "--vary plant.inertia = 1e-300: out of range"),
    (["tune", FIG2A, "--range", "plant.inertia=1e-300:1"], "--range plant.inertia = 1e-300: out of range"),
    (["tune", FIG2A, "--range", "plant.inertia=0.2:0.3", "--bound", "design.rtob_bandwidth=1e-9:1"],
     "--bound design.rtob_bandwidth = 1e-09: out of range"),
    (["sweep", FIG2A, "--vary", "k=nan:2:3"], "unknown config key"),
    (["sweep", FIG2A, "--vary", "design.force_gain=nan:2:3"], "finite"),
    (["sweep", FIG2A, "--vary", "design.force_gain=0:1e9:3"], "<= 1e+06"),
    # keys the config's structure never reads: every row would be the same
    (["sweep", FIG2A, "--vary", "design.disturbance_frequency=1:10:3"], "--set design.disturbance_model=sinusoid"),
    (["sweep", FIG2A, "--set", "design.interaction_model=ramp", "--vary", "design.interaction_frequency=1:10:3"],
     "(design.interaction_model is ramp, not sinusoid)"),
    (["sweep", FIG2A, "--vary", "environment.stiffness=1:2:2", "--vary", "design.velocity_filter_bandwidth=1:9:2"],
     "--vary design.velocity_filter_bandwidth: the loop does not use it (design.velocity_source is measured"),
    (["analyze", FIG2A, "--set", "design.input_delay=0.001"], "design.input_delay"),
]


@pytest.mark.parametrize("argv,message", BAD_ANALYSIS)
def test_bad_analysis_input_is_one_line_and_exit_2(argv: list[str], message: str,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1 and "Traceback" not in err


def test_a_design_past_the_keys_ranges_is_one_line_not_a_numpy_error() -> None:
    """Built past load_config's checks (as no command can any more): the analysis still says
    it cannot answer in one line, not numpy's error."""
    import dataclasses

    from dobhil.analysis.report import analyze
    from dobhil.errors import AnalysisError
    config = load_config(FIG2A)
    with pytest.raises(AnalysisError, match="the continuous analysis cannot answer this design"):
        analyze(dataclasses.replace(config, plant=dataclasses.replace(config.plant, inertia=1e-300)))


VARY_FORMS = "allowed: KEY=START:STOP:NUM or KEY=log:START:STOP:NUM"


@pytest.mark.parametrize("vary,problem", [
    ("design.force_gain=1:10:3:4", "the range has 4 parts, not 3"),
    ("design.force_gain=log:1:10:3:4", "the range has 4 parts, not 3"),
    ("design.force_gain=1", "the range has 1 part, not 3"),
    ("design.force_gain=1:10", "the range has 2 parts, not 3"),
    ("design.force_gain=", "no range after ="),
    ("design.force_gain=log:", "no range after log:"),
    ("design.force_gain=::3", "START is empty"),
    ("design.force_gain=1::3", "STOP is empty"),
    ("design.force_gain=1:10:", "NUM is empty"),
    ("design.force_gain=a:10:3", "START 'a' is not a number"),
    ("design.force_gain=1:b:3", "STOP 'b' is not a number"),
    ("design.force_gain=1:10:2.5", "NUM '2.5' is not a whole number"),
    ("design.force_gain=1:10:0", "NUM must be at least 1 (got 0)"),
    ("design.force_gain=1:10:100001", "NUM must be at most 100000 values per axis (got 100001)"),
    ("design.force_gain", "no ="),
    ("=1:10:3", "no KEY before ="),
])
def test_sweep_vary_names_the_part_at_fault(vary: str, problem: str, capsys: pytest.CaptureFixture[str]) -> None:
    """Each malformed --vary says what is wrong with it and the forms --vary takes."""
    assert main(["sweep", FIG2A, "--vary", vary]) == 2
    err = capsys.readouterr().err
    assert f"--vary {vary!r}: {problem}; {VARY_FORMS}" in err, err
    assert err.count("\n") == 1 and "Traceback" not in err


@pytest.mark.parametrize("name, sets, sampled", [
    ("demo", [], True), ("demo", ["design.delay_samples=1"], True), ("paper/fig3", ["loop.period=0.002"], True),
    ("demo", ["environment.stiffness=124.074", "environment.damping=1.13134", "design.identified_inertia=0.098837",
              "design.rtob_bandwidth=61.4341", "design.dob_bandwidth=622.163", "design.force_gain=7.98795"], True),
    ("paper/fig2b", [], False)])
def test_gain_margin_is_the_factor_to_the_largest_stable_gain(name, sets, sampled):
    """A sampled loop whose phase reaches -180 deg only at the Nyquist frequency has a gain
    margin there (python-control's stability_margins alone reported none for the demo):
    checked against the exact stable-gain map, which finds the crossing on the eigenvalues,
    and L itself (python-control's evaluation) is -1 / (largest stable gain) at the phase
    crossover reported. The fourth design's phase comes within 0.72 deg of -180 near 15 rad/s
    without reaching it: python-control 0.10.2 took that for a crossing, 0.079 (-22 dB). Fig.
    2b's continuous loop is stable at every C_f (Section IV): no gain margin, where
    python-control found 297 dB at 1.7e10 rad/s from a round-off leading coefficient."""
    from dobhil.analysis.report import analyze_domain
    params = params_from_config(load_config(name, sets))
    domain = analyze_domain(params, sampled=sampled)
    c_f = float(params.value("force_gain"))
    top = float(domain.gains.max_stable_gain)
    if not sampled:
        assert top == np.inf and domain.margins["gain_margin"] is None
        assert domain.margins["gain_margin_db"] is None and domain.margins["phase_crossover_freq"] is None
        return
    assert c_f < top < np.inf
    assert domain.margins["gain_margin"] == pytest.approx(top / c_f, rel=1e-6)
    open_loop = domain.systems.system("open_loop")
    at = np.exp(1j * domain.margins["phase_crossover_freq"] * open_loop.dt)
    assert complex(np.asarray(open_loop(at)).ravel()[0]) == pytest.approx(-1.0 / top, rel=1e-6)


@pytest.mark.parametrize("sets", [[], ["environment.stiffness=3044.34", "environment.damping=4.66794",
                                       "design.identified_inertia=0.41141", "design.dob_bandwidth=1874.42",
                                       "design.rtob_bandwidth=1083.26", "design.force_gain=15.0111"]])
def test_continuous_stability_margin_is_the_smallest_distance_to_minus_one(sets):
    """The stability margin is the smallest |1 + C_f L(jw)| over all w, which tends to 1 as
    w grows (L strictly proper): checked on a dense grid up to 1e8 rad/s. python-control's
    stationary points alone gave 1.26 for the demo and none for the second design."""
    from dobhil.analysis.report import analyze_domain
    params = params_from_config(load_config("demo", sets))
    domain = analyze_domain(params, sampled=False)
    open_loop = domain.systems.system("open_loop")
    w = np.geomspace(1e-2, 1e8, 4001)
    solved = np.linalg.solve(1j * w[:, None, None] * np.eye(open_loop.nstates) - open_loop.A,
                             np.broadcast_to(open_loop.B, (w.size, *open_loop.B.shape)))
    dense = np.abs(1.0 + float(params.value("force_gain")) * (open_loop.C @ solved)[:, 0, 0])
    assert domain.margins["stability_margin"] == pytest.approx(dense.min(), rel=1e-3)


def test_the_step_figure_of_a_loop_unstable_in_both_domains_says_so_without_warnings(tmp_path: Path) -> None:
    """At K_env = 0 both domains are unstable (the position drifts): the step figure of
    ``analyze --plot`` has no curve to put in a legend, which matplotlib warned about on the
    user's terminal; each domain is said in words instead, one line apart, and no legend."""
    import warnings

    from dobhil.analysis.report import analyze
    from dobhil.config import load_config
    from dobhil.plotting.figures import step_figure
    result = analyze(load_config("demo", ["environment.stiffness=0"]))
    assert not result.continuous.stable and not result.discrete.stable
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        path = step_figure(result.continuous, result.discrete, tmp_path)
    assert path == tmp_path / "step.png" and path.stat().st_size > 0


def test_the_bode_of_a_loop_slower_than_pi_seconds_stays_below_nyquist() -> None:
    """loop.period = 10 s (allowed, at most 10): the Nyquist frequency is 0.314 rad/s, and a
    grid from 1 rad/s down to it drew an aliased curve above Nyquist (python-control warned
    on the user's terminal: "evaluation above Nyquist frequency")."""
    import warnings

    import control

    from dobhil.plotting.figures import bode
    fig, axes = _plt().subplots(2, 1)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            bode((axes[0], axes[1]), control.tf([1.0], [1.0, -0.5], dt=10.0), "C_f L(z)")
        w = axes[0].get_lines()[0].get_xdata()
        assert w.max() < np.pi / 10.0 and w.min() < w.max()
    finally:
        _plt().close(fig)

@pytest.mark.parametrize("stiffness", ["0", "1e-9"])
def test_analyze_at_zero_stiffness_says_the_position_drifts_not_a_gain_margin(stiffness: str) -> None:
    """K_env = 0: a closed-loop pole at s = 0 / z = 1 that no C_f moves (at 1e-9 N m/rad
    within the analysis' resolution of it). The sampled loop printed "max stable C_f: 0" and,
    beside it, a gain margin of 15.08 dB: neither says what is true, that the position drifts
    at every C_f (as the sweep and the gate say)."""
    from dobhil.analysis.report import analyze, as_json, as_text
    result = analyze(load_config("paper/fig3", [f"environment.stiffness={stiffness}"]))
    report = as_json(result)
    for domain in ("continuous", "discrete"):
        d = report[domain]
        assert d["closed_loop"]["position_drifts"] and not d["closed_loop"]["stable"]
        assert d["margins"]["gain_margin_db"] is None and d["margins"]["gain_margin"] is None
    text = as_text(result)
    assert "max stable C_f: 0" not in text and "gain 15.08 dB" not in text
    assert text.count("the position drifts at every C_f") == 2
    from dobhil.plotting.figures import root_locus
    fig, ax = _plt().subplots()
    root_locus(ax, result.discrete)   # the root locus' title said "max stable C_f = 0"
    assert ax.get_title() == "the position drifts at every C_f (K_env 0 or too small to hold it)"
    _plt().close(fig)


def test_points_where_the_position_drifts_have_no_stable_c_f(tmp_path: Path) -> None:
    """At K_env = 0 no C_f is stable (the summary and analyze's text say so); the gain map
    alone, at a pole that stays at z = 1 within rounding, read 5.09 or 0 by the damping (the
    estimated velocity's demo: 5.09 at D_env 100/11, 0 at 0 and 200/11). The CSV, the result
    and analyze --json say none: 0, no interval, and that the position drifts."""
    sets = ["--set", "design.velocity_source=estimated"]
    csv_path = tmp_path / "s.csv"
    assert main(["sweep", "demo", *sets, "--sampled", "--vary", "environment.stiffness=0:0:1",
                 "--vary", f"environment.damping=0:{200 / 11!r}:3",
                 "--out", str(csv_path)]) == 0
    rows = csv_path.read_text().splitlines()
    assert rows[0].split(",")[-1] == "position_drifts"
    assert all(r.split(",")[-3:] == ["0.0", "0", "True"] for r in rows[1:]), rows
    config = load_config("demo", ["design.velocity_source=estimated", "design.force_gain=0"])
    result = sweep(config, [parse_vary("environment.stiffness=0:0:1"), parse_vary("environment.damping=0:10:3")],
                   sampled=True)
    assert result.drifting.all() and not result.max_stable_gain.any() and not result.interval_count.any()
    from dobhil.analysis.report import analyze_domain, domain_json
    config = load_config("demo", ["design.velocity_source=estimated", "environment.stiffness=0",
                                  f"environment.damping={100 / 11!r}"])
    domain = domain_json(analyze_domain(params_from_config(config), sampled=True), with_sensitivities=False)
    assert domain["closed_loop"]["position_drifts"]   # what analyze --json prints for the sampled loop
    assert domain["max_stable_force_gain"] == 0.0 and domain["stable_force_gain_intervals"] == []
