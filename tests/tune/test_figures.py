"""``dobhil tune --plot``'s figures, drawn with Agg from the arrays the command hands in."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")

import numpy as np
import pytest
from matplotlib.colors import to_rgba

from dobhil.plotting import tune_figures


def test_a_margin_with_no_value_is_drawn_not_met(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A design unstable at a margin's worst point has no margin there (NaN, the text's
    "none (unstable there): NOT MET"): its bar is red and short of 1, not a green full bar."""
    figures: list[Any] = []
    monkeypatch.setattr(tune_figures, "save", lambda fig, path: figures.append(fig) or path)
    data = tune_figures.TunePlotData(
        keys=("environment.stiffness",), points={"environment.stiffness": np.array([1e4])}, gm_db=np.array([6.0]),
        baseline_stable=np.array([True]), worst_at={"environment.stiffness": 1e4}, tuned_step=None, config_step=None,
        constraints=[("stability", 14.1, 1.0), ("gain_margin", math.nan, 6.0), ("phase_margin", 45.0, 30.0)])
    tune_figures.margins_figure(data, tmp_path / "margins.png")
    ax = figures[0].axes[0]
    try:
        bars = dict(zip([t.get_text().split("\n")[0] for t in ax.get_yticklabels()], ax.patches))
        assert bars["gain_margin"].get_width() < 1 and bars["gain_margin"].get_facecolor() == to_rgba("tab:red")
        assert bars["phase_margin"].get_width() == pytest.approx(1.5)
        assert "none (unstable)" in [t.get_text() for t in ax.get_yticklabels()][1]
    finally:
        import matplotlib.pyplot as plt
        plt.close(figures[0])


@pytest.mark.parametrize("keys", [("environment.stiffness",), ("environment.stiffness", "environment.damping")])
def test_the_stability_map_marks_the_tuned_designs_unstable_points(keys: tuple[str, ...], tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """Where the tuned design is unstable its gain margin is the search's stand-in (-100 dB,
    no measurement): not drawn as a margin (nor stretching the colour scale), but crossed."""
    figures: list[Any] = []
    monkeypatch.setattr(tune_figures, "save", lambda fig, path: figures.append(fig) or path)
    stiffness = np.repeat([1e3, 1e4, 1e5], 2)
    points = {"environment.stiffness": stiffness, "environment.damping": np.tile([10.0, 100.0], 3)}
    stable = np.array([False, True, True, True, True, True])
    data = tune_figures.TunePlotData(
        keys=keys, points={k: points[k] for k in keys}, gm_db=np.where(stable, [0, 9.0, 12.0, 8.0, 10.0, 11.0], -100.0),
        baseline_stable=np.ones(6, bool), worst_at={k: 1e4 for k in keys}, tuned_step=None, config_step=None,
        constraints=[], tuned_stable=stable)
    tune_figures.stability_map(data, tmp_path / "map.png")
    ax = figures[0].axes[0]
    try:
        if len(keys) == 1:
            lines = {str(line.get_label()): line for line in ax.get_lines()}
            margin = np.asarray(lines["tuned: worst gain margin"].get_ydata(), float)
            assert np.isnan(margin[0]) and list(margin[1:]) == [8.0, 10.0]
            assert list(lines["tuned design unstable (no margin)"].get_xdata()) == [1e3]
        else:
            assert ax.collections[0].get_clim()[0] == pytest.approx(8.0)   # the mesh: no -100 dB
            assert any(list(getattr(c, "hatches", None) or []) == ["xx"] for c in ax.collections)
    finally:
        import matplotlib.pyplot as plt
        plt.close(figures[0])


def test_a_pole_a_hair_below_1_is_drawn_unstable(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Largest |pole| 1 - 2e-14 (K_env 1e-9 N m/rad): unstable by the analysis' tolerance, as
    the text's "stability: ... NOT MET" says; its bar was green, right of 1."""
    figures: list[Any] = []
    monkeypatch.setattr(tune_figures, "save", lambda fig, path: figures.append(fig) or path)
    data = tune_figures.TunePlotData(
        keys=("environment.stiffness",), points={"environment.stiffness": np.array([1e-9])}, gm_db=np.array([6.0]),
        baseline_stable=np.array([False]), worst_at={"environment.stiffness": 1e-9}, tuned_step=None,
        config_step=None, constraints=[("stability", 1.0 - 2e-14, 1.0)])
    tune_figures.margins_figure(data, tmp_path / "margins.png")
    try:
        (bar,) = figures[0].axes[0].patches
        assert bar.get_facecolor() == to_rgba("tab:red")
    finally:
        import matplotlib.pyplot as plt
        plt.close(figures[0])
