"""Figures of the analyses: tubule widths, cell montages and class fractions, speed
histograms, MSD curves and trajectories.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from fgat.viz.figures import finish_figure, grouped_lines, pyplot


def plot_tubule_widths(
    image: np.ndarray,
    profiles_px: Sequence[tuple[Sequence[float], Sequence[float]]],
    widths_um: dict[str, Sequence[float]],
    path: str | Path,
    *,
    title: str = "",
) -> Path:
    """The measured image with its line profiles (left) and box plots of tubule widths (right,
    Fig. 3j).

    Parameters
    ----------
    image : numpy.ndarray
        ``(Y, X)`` image the profiles were taken on (e.g. a volume's x-y MIP).
    profiles_px : sequence
        Per segment, the profile's ``(src, dst)`` end points ``(y, x)`` in pixels (pixel centres
        at integer coordinates), drawn and numbered in order.
    widths_um : dict
        ``{label: widths (um)}``; one box each, NaN widths left out, every width drawn as a dot.
    path : str or Path
        PNG file to write (atomically).
    """
    plt = pyplot()
    figure, (left, right) = plt.subplots(
        1, 2, figsize=(9.0, 4.2), gridspec_kw={"width_ratios": [1.4, 1]}
    )
    left.imshow(np.asarray(image, dtype=float), cmap="gray")
    for index, (src, dst) in enumerate(profiles_px):
        (y0, x0), (y1, x1) = src, dst
        left.plot([x0, x1], [y0, y1], color="tab:orange", linewidth=1.0)
        left.text(x1, y1, str(index), color="tab:orange", fontsize=7)
    left.set_xlabel("x (px)")
    left.set_ylabel("y (px)")
    left.set_title("profiles", fontsize=9)
    values = [np.asarray(w, dtype=float) for w in widths_um.values()]
    values = [v[np.isfinite(v)] for v in values]
    right.boxplot(values, showfliers=False)
    jitter = np.random.default_rng(0)
    for position, v in enumerate(values, start=1):
        spread = jitter.uniform(-0.12, 0.12, v.size)
        right.plot(position + spread, v, "o", color="tab:blue", markersize=3, alpha=0.7)
    right.set_xticks(np.arange(1, len(values) + 1), list(widths_um), fontsize=8)
    right.set_ylabel("apparent width, FWHM (um)")
    right.grid(alpha=0.3)
    return finish_figure(figure, path, title)


def plot_cell_montage(
    mips: dict[str, np.ndarray],
    cells_yx_um: np.ndarray,
    classes: Sequence[str],
    path: str | Path,
    *,
    pixel_um: tuple[float, float],
    radius_um: float,
    title: str = "",
    axes_names: tuple[str, str] = ("y", "x"),
) -> Path:
    """Maximum-projection montage of a cytometry volume (Fig. S14): each channel in grey, their
    merge in colour (the first channel blue, the others green, red, magenta, cyan, yellow), and a
    circle on every detected cell in the merge, coloured by its class (colours in the sorted
    order of the class labels, so every montage of a set of classes agrees).

    Parameters
    ----------
    mips : dict
        ``{channel name: (rows, columns) maximum projection}``, nuclei first (x-y by default).
    cells_yx_um : numpy.ndarray
        ``(N, 2)`` cell centres (row, column) in um, e.g. ``(y, x)`` (voxel ``i``'s centre at
        ``(i + 0.5) * size``).
    classes : sequence of str
        ``(N,)`` class label of every cell.
    path : str or Path
        PNG file to write (atomically).
    pixel_um : tuple of float
        Pixel size (rows, columns) in um, e.g. ``(dy, dx)``.
    radius_um : float
        Radius of the circles in um.
    axes_names : (str, str)
        Names of the projection's (rows, columns) axes for the labels, e.g. ``("z", "x")``.
    """
    plt = pyplot()
    names = list(mips)
    colours = np.array([[0, 0.4, 1], [0, 1, 0], [1, 0, 0], [1, 0, 1], [0, 1, 1], [1, 1, 0]])
    scaled = []
    for name in names:
        low, high = np.percentile(np.asarray(mips[name], dtype=float), (1.0, 99.9))
        scaled.append(np.clip((mips[name] - low) / max(high - low, 1e-30), 0, 1))
    merge = np.clip(
        sum(s[..., None] * colours[k % len(colours)] for k, s in enumerate(scaled)), 0, 1
    )
    height, width = scaled[0].shape
    extent = (0, width * pixel_um[1], height * pixel_um[0], 0)
    figure, axes = plt.subplots(
        1, len(names) + 1, figsize=(3.0 * (len(names) + 1), 3.4), squeeze=False
    )
    for axis, name, image in zip(axes[0], names, scaled):
        axis.imshow(image, cmap="gray", extent=extent)
        axis.set_title(name, fontsize=9)
    axes[0, -1].imshow(merge, extent=extent)
    axes[0, -1].set_title(f"merge, {len(classes)} cells", fontsize=9)
    cycle = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    colour = {c: cycle[k % len(cycle)] for k, c in enumerate(sorted(set(classes)))}
    for (y, x), label in zip(np.asarray(cells_yx_um).reshape(-1, 2), classes):
        axes[0, -1].add_patch(
            plt.Circle((x, y), radius_um, fill=False, color=colour[label], lw=0.8)
        )
    handles = [plt.Line2D([], [], marker="o", mfc="none", ls="", color=c) for c in colour.values()]
    if colour:
        axes[0, -1].legend(handles, list(colour), fontsize=6, loc="lower right")
    for axis in axes[0]:
        axis.set_xlabel(f"{axes_names[1]} (um)", fontsize=8)
        axis.tick_params(labelsize=7)
    axes[0, 0].set_ylabel(f"{axes_names[0]} (um)", fontsize=8)
    return finish_figure(figure, path, title)


def plot_class_fractions(
    classes: Sequence[str],
    fractions: Sequence[float],
    path: str | Path,
    *,
    reference_fractions: Sequence[float] | None = None,
    pvalues: Sequence[float] | None = None,
    title: str = "",
) -> Path:
    """Bars of the class fractions, beside a reference's (e.g. flow cytometry, Fig. 5g) when
    given, with each class's p-value (e.g. Fisher's exact test) above its bars."""
    plt = pyplot()
    positions = np.arange(len(classes))
    figure, axis = plt.subplots(figsize=(1.3 * len(classes) + 2.0, 3.8))
    offset = 0.0 if reference_fractions is None else 0.2
    axis.bar(positions - offset, fractions, 0.4 if offset else 0.6, label="measured")
    if reference_fractions is not None:
        axis.bar(positions + offset, reference_fractions, 0.4, label="reference")
        axis.legend(fontsize=8)
    if pvalues is not None:
        tops = np.fmax(fractions, reference_fractions if offset else fractions)
        for x, top, p in zip(positions, tops, pvalues):
            axis.text(x, top, f"p={p:.2g}", ha="center", va="bottom", fontsize=7)
    axis.set_xticks(positions, list(classes), rotation=20, ha="right", fontsize=8)
    axis.set_ylabel("fraction of cells")
    axis.grid(axis="y", alpha=0.3)
    return finish_figure(figure, path, title)


def plot_speed_histogram(
    mean_speeds: Sequence[float],
    path: str | Path,
    *,
    threshold: float | None = None,
    title: str = "",
) -> Path:
    """Histogram of per-cell mean speeds (um/s) on log-spaced bins, with the slow/fast threshold
    as a dashed line when there is one (Fig. 5h)."""
    plt = pyplot()
    speeds = np.asarray(mean_speeds, dtype=float)
    speeds = speeds[np.isfinite(speeds) & (speeds > 0)]
    figure, axis = plt.subplots(figsize=(5.0, 3.6))
    low, high = np.log10(speeds.min()), np.log10(speeds.max())
    bins = np.logspace(low - 0.05, high + 0.05, max(5, min(30, speeds.size)) + 1)
    axis.hist(speeds, bins=bins, color="tab:blue", alpha=0.8)
    if threshold is not None:
        axis.axvline(
            threshold, color="black", linestyle="--", label=f"threshold {threshold:.3g} um/s"
        )
        axis.legend(fontsize=8)
    axis.set_xscale("log")
    axis.set_xlabel("mean speed (um/s)")
    axis.set_ylabel("cells")
    return finish_figure(figure, path, title)


def plot_msd_curves(
    curves: dict[str, Sequence[tuple[Sequence[float], Sequence[float]]]],
    path: str | Path,
    *,
    title: str = "",
) -> Path:
    """Mean squared displacement against lag on log-log axes, one colour per group (Fig. 5j).

    Parameters
    ----------
    curves : dict
        ``{label: [(lags_s, msd_um2), ...]}``: per group (e.g. slow and fast cells), one curve
        per trajectory; NaN and non-positive values are left out.
    path : str or Path
        PNG file to write (atomically).
    """
    plt = pyplot()
    figure, axis = plt.subplots(figsize=(5.0, 3.8))
    kept = {}
    for label, group in curves.items():
        kept[label] = []
        for lags, values in group:
            lags, values = np.asarray(lags, dtype=float), np.asarray(values, dtype=float)
            keep = np.isfinite(values) & (values > 0) & (lags > 0)
            kept[label].append((lags[keep], values[keep]))
    grouped_lines(axis, kept, linewidth=0.8, alpha=0.7)
    axis.set_xscale("log")
    axis.set_yscale("log")
    axis.set_xlabel("lag (s)")
    axis.set_ylabel("MSD (um^2)")
    axis.grid(alpha=0.3, which="both")
    axis.legend(fontsize=8)
    return finish_figure(figure, path, title)


def plot_trajectories(
    tracks: dict[str, Sequence[np.ndarray]],
    path: str | Path,
    *,
    title: str = "",
) -> Path:
    """Trajectories projected on x-y, one colour per group, each start marked with a dot
    (Fig. 5i); y grows downwards as in the images.

    Parameters
    ----------
    tracks : dict
        ``{label: [(T, 2) positions (x, y) in um, ...]}``.
    path : str or Path
        PNG file to write (atomically).
    """
    plt = pyplot()
    figure, axis = plt.subplots(figsize=(5.0, 4.6))
    xy = {label: [np.asarray(p, dtype=float) for p in group] for label, group in tracks.items()}
    colours = grouped_lines(axis, {k: [(p[:, 0], p[:, 1]) for p in v] for k, v in xy.items()})
    for colour, group in zip(colours, xy.values()):
        for positions in group:
            axis.plot(positions[0, 0], positions[0, 1], "o", color=colour, markersize=2.5)
    axis.set_aspect("equal", adjustable="datalim")
    axis.invert_yaxis()
    axis.set_xlabel("x (um)")
    axis.set_ylabel("y (um)")
    axis.legend(fontsize=8)
    return finish_figure(figure, path, title)
