"""Learning-curve pictures with matplotlib (Agg canvas, no display needed): one panel per metric,
the seed mean as a line, the seeds' min–max as a band, the random agent as a dashed reference line,
the x axis in env steps per seed."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter, MaxNLocator

from baselines import outputs

MEAN_COLOUR, BAND_COLOUR, REFERENCE_COLOUR = "#1f4e9c", "#9bb7e0", "#c0392b"


def steps_label(value: float, _pos=None) -> str:
    """Axis tick text for a step count: ``0``, ``500``, ``20k``, ``1.5M``."""
    for size, unit in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if abs(value) >= size:
            return f"{value / size:.3g}{unit}"
    return f"{value:.0f}"


def curves_figure(steps, panels: dict, title: str = "", reference: dict | None = None) -> Figure:
    """A matplotlib Figure (Agg canvas attached): one panel per ``panels[name] = array`` of shape
    ``(seeds, points)`` (or ``(points,)``) against ``steps`` (env steps per seed, ``(points,)``).
    NaN points are gaps. ``reference[name] = value`` draws a dashed line labelled "random agent"."""
    steps = np.asarray(steps, np.float64)
    fig = Figure(figsize=(8.0, 1.0 + 2.3 * max(len(panels), 1)), dpi=110, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(max(len(panels), 1), 1, sharex=True, squeeze=False)[:, 0]
    for ax, (name, arr) in zip(axes, panels.items()):
        arr = np.asarray(arr, np.float64)
        arr = arr[None] if arr.ndim == 1 else arr
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns stay NaN: gaps in the line
            mean = np.nanmean(arr, axis=0)
            lo, hi = np.nanmin(arr, axis=0), np.nanmax(arr, axis=0)
        seeds = arr.shape[0]
        if seeds > 1:
            ax.fill_between(steps, lo, hi, color=BAND_COLOUR, alpha=0.6, linewidth=0, label=f"{seeds} seeds (min–max)")
        ax.plot(steps, mean, color=MEAN_COLOUR, linewidth=1.8, label="mean over seeds" if seeds > 1 else "1 seed")
        ok = np.isfinite(mean)
        alone = ok & ~np.concatenate([[False], ok[:-1]]) & ~np.concatenate([ok[1:], [False]])
        ax.plot(steps[alone], mean[alone], "o", color=MEAN_COLOUR, markersize=4)  # points no line reaches
        ref = (reference or {}).get(name)
        if ref is not None and np.isfinite(ref):
            ax.axhline(ref, color=REFERENCE_COLOUR, linestyle="--", linewidth=1.4, label=f"random agent ({ref:.3g})")
        ax.set_ylabel(name)
        ax.grid(True, color="#dddddd", linewidth=0.6)
        ax.yaxis.set_major_locator(MaxNLocator(5))
        ax.legend(loc="best", fontsize="small", framealpha=0.85)
    axes[-1].set_xlabel("env steps per seed")
    axes[-1].xaxis.set_major_formatter(FuncFormatter(steps_label))
    if len(steps):
        axes[-1].set_xlim(0, max(float(steps.max()), 1.0))
    if title:
        fig.suptitle(title, fontsize="medium")
    return fig


def plot_curves(path, steps, panels: dict, title: str = "", reference: dict | None = None) -> Path:
    """Write the learning-curve PNG of :func:`curves_figure` to ``path``; returns the path."""
    return outputs.save_figure(curves_figure(steps, panels, title=title, reference=reference), path)
