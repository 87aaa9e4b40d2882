"""Tick labels that do not run into each other.

matplotlib's locators choose ticks from the axis length and a font-size guess, not from the
labels' drawn widths: long labels (``0.9825``, ``0.9850``, ... on a narrow histogram) touch
or overlap. :func:`fit_ticks` lays the figure out, measures every tick label
(``Text.get_window_extent`` with the canvas' renderer) and asks an axis with touching labels
for fewer ticks until none touch; :func:`overlapping_tick_labels` is the measurement alone,
on a real draw. The layout of :func:`fit_ticks` runs what a draw runs before it draws:
the figure's layout engine (constrained layout: the axes' positions from their labels'
sizes), each axes' aspect, and each axis' ticks and labels placed (``Axis.get_tightbbox``
places them as ``Axis.draw`` does) -- the labels measured where a draw puts them, no artist
drawn (``Figure.draw_without_rendering`` also walks every bar and line: the fit of 12
campaign pages took 2.90-3.20 s of CPU against 3.52-3.63 s with it, the same ticks on 60
pages, measured here).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from matplotlib.axis import Axis
    from matplotlib.figure import Figure

#: fewest ticks an axis is thinned to (two values still give a scale)
MIN_TICKS = 2

#: blank space required between two labels [pixels at the figure's dpi]
GAP_PX = 2.0


def _shown_labels(axis: Axis) -> list[Any]:
    """The axis' major tick labels that are drawn: visible, non-empty, inside the view."""
    lo, hi = sorted(axis.get_view_interval())
    out = []
    for tick in axis.get_major_ticks():
        label = tick.label1
        if label.get_visible() and label.get_text() and lo <= tick.get_loc() <= hi:
            out.append(label)
    return out


def _laid_out(fig: Figure) -> Any:
    """``fig`` laid out as a draw would, without drawing it (see the module docstring); the
    canvas' renderer."""
    renderer = fig.canvas.get_renderer()  # type: ignore[attr-defined]
    engine = fig.get_layout_engine()
    if engine is not None:
        engine.execute(fig)
    for ax in fig.axes:
        ax.apply_aspect()
        for axis in (ax.xaxis, ax.yaxis):
            axis.get_tightbbox(renderer)
    return renderer


def _axis_overlaps(axis: Axis, renderer: Any) -> list[tuple[str, str]]:
    boxes = [(label.get_text(), label.get_window_extent(renderer).padded(GAP_PX / 2))
             for label in _shown_labels(axis)]
    return [(a, b) for i, (a, box_a) in enumerate(boxes) for b, box_b in boxes[i + 1:] if box_a.overlaps(box_b)]


def overlapping_tick_labels(fig: Figure) -> list[tuple[str, str]]:
    """Every pair of tick labels of one axis of ``fig`` that touch (closer than
    :data:`GAP_PX`) once drawn: a real draw, as the saved figure is rendered (the check of
    :func:`fit_ticks`' layout-only measure)."""
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()  # type: ignore[attr-defined]
    return [pair for ax in fig.axes if ax.get_visible()
            for axis in (ax.xaxis, ax.yaxis) for pair in _axis_overlaps(axis, renderer)]


def fit_ticks(fig: Figure) -> None:
    """Fewer ticks on each axis whose labels touch, until none do (or :data:`MIN_TICKS`)."""
    from matplotlib.ticker import MaxNLocator
    renderer = _laid_out(fig)
    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            if axis.get_scale() != "linear":
                continue   # a log axis' locator places decades; its labels are short
            count = len(_shown_labels(axis))
            while _axis_overlaps(axis, renderer) and count > MIN_TICKS:
                count -= 1
                axis.set_major_locator(MaxNLocator(nbins=max(1, count - 1), steps=[1, 2, 2.5, 5, 10]))
                renderer = _laid_out(fig)


__all__ = ["fit_ticks", "overlapping_tick_labels"]
