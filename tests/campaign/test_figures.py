"""The campaign's figures, drawn with Agg: no two tick labels of an axis touch (each label's
drawn extent measured with the canvas' renderer), on the values that made them touch."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dobhil.campaign.runner import METRICS
from dobhil.plotting.campaign_figures import metric_figure, vary_figure
from dobhil.plotting.ticks import overlapping_tick_labels


def campaign_like(rng: np.random.Generator, n: int, settle_lo: float) -> dict[str, np.ndarray]:
    """Metrics as a tuned design's 1 s campaign gave them: settling times crowded against the
    run's end (long labels 0.9825, 0.9850, ...), the rest spread."""
    return {"force_rms_error": rng.uniform(0.062, 0.097, n), "final_error": rng.normal(0.0, 0.008, n),
            "overshoot_pct": rng.uniform(8, 26, n), "rise_time": rng.uniform(0.003, 0.045, n),
            "settling_time": rng.uniform(settle_lo, 0.9995, n), "final_tau_int_true": rng.normal(1.0, 0.04, n)}


def close(fig: object) -> None:
    import matplotlib.pyplot as plt
    plt.close(fig)  # type: ignore[arg-type]


def test_the_labels_that_touched_do_not_any_more() -> None:
    fig = metric_figure(campaign_like(np.random.default_rng(0), 100, 0.9825), 100)
    try:
        assert sum(ax.get_visible() for ax in fig.axes) == len(METRICS)
        assert overlapping_tick_labels(fig) == []
        # every histogram keeps a scale: at least two labels on each axis
        for ax in fig.axes:
            if ax.get_visible():
                assert sum(bool(t.get_text()) for t in ax.get_xticklabels()) >= 2
    finally:
        close(fig)


@settings(max_examples=8, deadline=None)
@given(lo=st.floats(0.5, 0.999), n=st.integers(3, 400), seed=st.integers(0, 2**16))
def test_no_tick_labels_overlap_whatever_the_spread(lo: float, n: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    metrics = campaign_like(rng, n, lo)
    fig = metric_figure(metrics, n)
    try:
        assert overlapping_tick_labels(fig) == []
    finally:
        close(fig)
    draws = {"plant.inertia": rng.normal(0.25, 0.02, n), "environment.stiffness": np.exp(rng.uniform(7, 11.5, n)),
             "environment.damping": rng.uniform(lo, lo + 1e-3, n)}
    ok = rng.uniform(size=n) > 0.1
    fig = vary_figure(draws, metrics["force_rms_error"], ok)
    try:
        assert overlapping_tick_labels(fig) == []
    finally:
        close(fig)


def test_the_measurement_sees_touching_labels() -> None:
    """The check itself: labels forced onto one another are found."""
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(2, 2))
    ax.set_xlim(0.98250, 0.99950)
    ax.set_xticks(np.linspace(0.98250, 0.99950, 12))
    ax.ticklabel_format(axis="x", useOffset=False)
    try:
        assert overlapping_tick_labels(fig)
    finally:
        close(fig)


def test_the_fit_lays_the_figure_out_without_drawing_it(monkeypatch: pytest.MonkeyPatch) -> None:
    """fit_ticks measures on the layout a draw makes (the labels' overlap is checked on a real
    draw afterwards) but draws no artist itself: each re-layout is the layout engine's and the
    axes' tick placement, not a whole draw of every bar and line."""
    import matplotlib.pyplot as plt
    from matplotlib.figure import Figure

    from dobhil.plotting.ticks import fit_ticks
    fig, ax = plt.subplots(figsize=(2.4, 2), layout="constrained")
    ax.hist(np.linspace(0.98250, 0.99950, 50), bins=20)
    ax.set_xticks(np.linspace(0.98250, 0.99950, 12))   # labels forced onto one another
    ax.ticklabel_format(axis="x", useOffset=False)
    try:
        before = overlapping_tick_labels(fig)
        draws: list[object] = []
        drawn = Figure.draw
        monkeypatch.setattr(Figure, "draw", lambda f, renderer: draws.append(f) or drawn(f, renderer))
        fit_ticks(fig)
        assert draws == []
        monkeypatch.undo()
        assert before and overlapping_tick_labels(fig) == []   # it had labels to thin, and thinned them
    finally:
        close(fig)


if __name__ == "__main__":   # pragma: no cover
    pytest.main([__file__])
