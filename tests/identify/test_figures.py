"""The identify figure (``dobhil identify --plot``): a fast excitation stays readable -- the
whole record's torque as its min-max band and mean per bin (never one line segment per
level), a zoomed window sample by sample -- checked on the drawn artists, and the band
against the samples it stands for (hypothesis)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from dobhil.plotting import identify_figures
from dobhil.plotting.identify_figures import ENVELOPE_BINS, ZOOM_SAMPLES, envelope, measured_vs_model, zoom_window

finite = st.floats(-1e6, 1e6, allow_nan=False)


@settings(max_examples=200, deadline=None)
@given(y=arrays(float, st.integers(2, 3000), elements=finite), bins=st.integers(1, 700))
def test_every_sample_lies_in_its_bins_band_and_each_band_is_spanned_by_samples(y: np.ndarray, bins: int) -> None:
    t = np.arange(y.size) * 1e-3
    edges, lo, hi, mean = envelope(t, y, bins)
    assert len(lo) == len(hi) == len(mean) == len(edges) - 1 <= min(bins, y.size)
    assert edges[0] == t[0] and np.all(np.diff(edges) > 0)
    which = np.searchsorted(edges, t, side="right") - 1   # the bin of each sample
    assert np.all(lo[which] <= y) and np.all(y <= hi[which])
    for i in range(len(lo)):   # each band's ends are samples of its bin; the mean is its samples'
        inside = y[which == i]
        assert lo[i] == inside.min() and hi[i] == inside.max()
        assert mean[i] == pytest.approx(inside.mean(), rel=1e-9, abs=1e-9)


def test_envelope_refuses_mismatched_inputs() -> None:
    with pytest.raises(ValueError, match="equal length"):
        envelope(np.arange(3.0), np.arange(4.0))
    with pytest.raises(ValueError, match=">= 2"):
        envelope(np.arange(1.0), np.arange(1.0))


def test_zoom_window_only_for_records_too_long_to_read() -> None:
    assert zoom_window(2 * ZOOM_SAMPLES) is None
    window = zoom_window(5000)
    assert window is not None and window.stop - window.start == ZOOM_SAMPLES
    assert window.start == (5000 - ZOOM_SAMPLES) // 2


def _prbs(n: int, clock: int, seed: int = 1) -> np.ndarray:
    levels = np.random.default_rng(seed).integers(0, 2, n // clock + 1)
    return 1.0 + 0.5 * (2 * np.repeat(levels, clock)[:n] - 1)


def _drawn(monkeypatch: pytest.MonkeyPatch, tmp_path: Path, n: int) -> tuple[Path, Any]:
    """The figure of a 2 ms PRBS of ``n`` samples at 1 kHz, and the figure object as saved."""
    t = np.arange(n) * 1e-3
    torque = _prbs(n, 2)
    velocity = np.cumsum(torque - torque.mean()) * 1e-3
    seen: dict[str, Any] = {}
    real_save = identify_figures.save

    def keep(fig: Any, path: Path) -> Path:
        seen["fig"] = fig
        return real_save(fig, path)

    monkeypatch.setattr(identify_figures, "save", keep)
    path = measured_vs_model(t, (velocity * 1e-3, velocity), (velocity * 1e-3, velocity), "prbs", tmp_path / "f.png",
                             torque=torque)
    return path, seen["fig"]


def _shapes(ax: Any) -> list[np.ndarray]:
    """The vertices of every filled area and patch the axes draws (x in data units)."""
    return ([p.vertices for c in ax.collections for p in c.get_paths()]
            + [p.get_patch_transform().transform(p.get_path().vertices) for p in ax.patches])


def _vertices(ax: Any) -> int:
    """Points the axes draws in lines, filled areas and patches."""
    return sum(len(line.get_xdata()) for line in ax.get_lines()) + sum(len(v) for v in _shapes(ax))


def test_a_long_prbs_is_a_band_with_a_zoomed_window(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """5 s of a 2 ms PRBS (2,500 levels): the torque panel draws a bounded number of points
    whatever the record's length (the band, the mean, the window), the last panel the window's
    samples, sample by sample, with the velocity on its second axis."""
    path, fig = _drawn(monkeypatch, tmp_path, 5000)
    assert path.stat().st_size > 10_000 and path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    torque_ax, zoom_ax = fig.axes[0], fig.axes[4]
    assert torque_ax.get_ylabel() == "torque sent [N m]" and "(zoom)" in zoom_ax.get_ylabel()
    assert _vertices(torque_ax) <= 8 * ENVELOPE_BINS + 20   # not the 5,000 samples' steps
    zoom_x = zoom_ax.get_lines()[0].get_xdata()
    assert len(zoom_x) == ZOOM_SAMPLES and np.all(np.diff(zoom_x) == pytest.approx(1e-3))
    twin = [ax for ax in fig.axes if ax is not zoom_ax and ax.bbox.bounds == zoom_ax.bbox.bounds]
    assert twin and len(twin[0].get_lines()) == 2   # velocity measured and model in the window
    # the shaded span on the whole record is the zoomed window
    window = zoom_window(5000)
    assert window is not None
    assert any(np.isclose(v[:, 0].min(), window.start * 1e-3) and np.isclose(v[:, 0].max(), (window.stop - 1) * 1e-3)
               for v in _shapes(torque_ax)), "no shaded zoom window"
    # the band doubles with the record's length no more than the bins allow
    _, longer = _drawn(monkeypatch, tmp_path, 20000)
    assert _vertices(longer.axes[0]) <= 8 * ENVELOPE_BINS + 20


def test_a_short_record_is_drawn_sample_by_sample(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    _, fig = _drawn(monkeypatch, tmp_path, 2 * ZOOM_SAMPLES)
    assert len(fig.axes) == 4   # torque, position, velocity, residual: no zoom
    assert len(fig.axes[0].get_lines()[0].get_xdata()) == 2 * ZOOM_SAMPLES
