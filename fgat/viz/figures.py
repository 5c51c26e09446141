"""Figure plumbing every plot shares: matplotlib without a display, titled figures saved
atomically as PNG, and line plots of curves.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from fgat.io.files import atomic_path


def finish_figure(figure, path: str | Path, title: str = "", fontsize: float = 10) -> Path:
    """Give ``figure`` its ``title`` (when there is one), lay it out and save it
    (:func:`save_figure`)."""
    if title:
        figure.suptitle(title, fontsize=fontsize)
    figure.tight_layout()
    return save_figure(figure, path)


def save_figure(figure, path: str | Path) -> Path:
    """Write a matplotlib figure as PNG (atomically) and close it."""
    import matplotlib.pyplot as plt  # matplotlib loaded when a figure is drawn: keeps start-up fast

    path = Path(path)
    with atomic_path(path) as temporary:
        figure.savefig(temporary, dpi=110, format="png")
    plt.close(figure)
    return path


def pyplot():
    """matplotlib.pyplot on the non-interactive Agg backend (no display needed)."""
    import matplotlib  # matplotlib loaded when a figure is drawn: keeps start-up fast

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # matplotlib loaded when a figure is drawn: keeps start-up fast

    return plt


def plot_curves(
    curves: dict[str, dict[str, Sequence[float]]],
    path: str | Path,
    *,
    xlabel: str,
    ylabels: dict[str, str],
    title: str = "",
) -> Path:
    """One panel per metric and group: ``curves[group][series] -> values`` per metric key.

    Parameters
    ----------
    curves : dict
        ``{group: {series: {metric: values}}}``, e.g. ``{"beads": {"RL": {"psnr": [...]}}}``.
    path : str or Path
        PNG file.
    ylabels : dict
        ``{metric: axis label}``; one row of panels per metric.
    """
    plt = pyplot()
    groups = list(curves)
    figure, axes = plt.subplots(
        len(ylabels), len(groups), figsize=(4.2 * len(groups), 3.0 * len(ylabels)), squeeze=False
    )
    for column, group in enumerate(groups):
        for row, (metric, label) in enumerate(ylabels.items()):
            axis = axes[row, column]
            for series, values in curves[group].items():
                y = np.asarray(values[metric], dtype=float)
                x = np.arange(1, len(y) + 1)
                finite = np.isfinite(y)  # a metric sampled every few steps is NaN in between
                axis.plot(x[finite], y[finite], label=series)
            axis.set_xlabel(xlabel)
            axis.set_ylabel(label)
            axis.set_title(group, fontsize=10)
            axis.grid(alpha=0.3)
            axis.legend(fontsize=8)
    return finish_figure(figure, path, title, fontsize=11)


def grouped_lines(axis, groups: dict[str, Sequence[tuple]], **style) -> list[str]:
    """Draw ``{label: [(x, y), ...]}`` on ``axis``, one colour of the property cycle per label
    (the label on its first line only, for the legend); returns the colours in label order."""
    cycle = pyplot().rcParams["axes.prop_cycle"].by_key()["color"]
    colours = [cycle[k % len(cycle)] for k in range(len(groups))]
    for colour, (label, lines) in zip(colours, groups.items()):
        for n, (x, y) in enumerate(lines):
            axis.plot(x, y, color=colour, label=label if n == 0 else None, **style)
    return colours
