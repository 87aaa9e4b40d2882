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
