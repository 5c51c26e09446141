"""PNG figures of the things people look at (matplotlib, non-interactive backend)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from fgat.io.files import atomic_path

LATTICE_CELL_IN = (0.85, 1.8)
"""Smallest and largest side (inches) of one view's panel in the lattice layouts."""


def _lattice_cells(n_views: int) -> tuple[np.ndarray, float, float]:
    """Where each of ``n_views`` views sits in a lattice layout: ``(V, 2)`` (left, bottom) of
    its unit cell in cells from the layout's lower-left corner, and the layout's width and
    height in cells (fgat's view order on the unrotated hexagonal lattice,
    :func:`~fgat.optics.lenslets.hexagonal_offsets`, one pitch per cell)."""
    from fgat.optics.lenslets import hexagonal_offsets

    offsets = hexagonal_offsets(n_views, 1.0)
    left = offsets[:, 1] - offsets[:, 1].min()
    bottom = offsets[:, 0].max() - offsets[:, 0]  # rows point down, the figure's y up
    return np.stack([left, bottom], axis=1), float(left.max() + 1), float(bottom.max() + 1)


def plot_psf_stack(
    stack: np.ndarray,
    path: str | Path,
    *,
    title: str = "PSF stack",
    depths_um: Sequence[float] | None = None,
    pixel_um: float | None = None,
) -> Path:
    """Save x-y (left) and x-z (right) maximum projections of every view of a PSF stack, each
    view at its place in the hexagonal lenslet array, numbered, on one colour scale.

    The views sit on the unrotated lattice in fgat's view order (view 0 in the middle, see
    :mod:`fgat.optics.lenslets`), one cell per lenslet, so that 7 or 37 views make a compact
    figure; the lower-left view carries the axes (``um``, or pixels and depth indices without
    ``pixel_um`` and ``depths_um``), the colour bar the PSF's value (the fraction of a point's
    light per pixel).

    Parameters
    ----------
    stack : numpy.ndarray
        ``(V, Z, h, w)`` PSF stack.
    path : str or Path
        PNG file to write (atomically).
    depths_um : sequence of float, optional
        ``(Z,)`` depths, used for the x-z axis extent.
    pixel_um : float, optional
        Lateral sample-space pixel size, used for the axis extents.
    """
    plt = pyplot()
    stack = np.asarray(stack, dtype=np.float64)
    n_views, n_depths, h, w = stack.shape
    pixel = pixel_um or 1.0
    unit = "um" if pixel_um else "px"
    z = np.asarray(depths_um if depths_um is not None else np.arange(n_depths), dtype=float)
    cells, width, height = _lattice_cells(n_views)
    cell = float(np.clip(6.0 / max(width, height), *LATTICE_CELL_IN))
    margin = {"left": 0.9, "gap": 1.0, "right": 1.3, "bottom": 0.7, "top": 0.75}
    size = (
        margin["left"] + 2 * width * cell + margin["gap"] + margin["right"],
        margin["bottom"] + height * cell + margin["top"],
    )
    figure = plt.figure(figsize=size)
    top = max(float(stack.max()), 1e-30)
    corner = int(np.lexsort((cells[:, 0], cells[:, 1]))[0])  # lowest row, leftmost
    lateral = (-w / 2 * pixel, w / 2 * pixel)
    panels = (
        ("x-y", lambda v: stack[v].max(axis=0), (*lateral, h / 2 * pixel, -h / 2 * pixel)),
        ("x-z", lambda v: stack[v].max(axis=1), (*lateral, z[-1], z[0])),
    )
    for p, (name, projection, extent) in enumerate(panels):
        origin = margin["left"] + p * (width * cell + margin["gap"])
        for v in range(n_views):
            box = (
                (origin + (cells[v, 0] + 0.09) * cell) / size[0],
                (margin["bottom"] + (cells[v, 1] + 0.09) * cell) / size[1],
                0.82 * cell / size[0],  # below the sqrt(3) / 2 spacing of the lattice's rows
                0.82 * cell / size[1],
            )
            axis = figure.add_axes(box)
            image = axis.imshow(
                projection(v), cmap="magma", vmin=0, vmax=top, aspect="auto", extent=extent
            )
            axis.text(
                0.04,
                0.96,
                str(v),
                transform=axis.transAxes,
                color="white",
                fontsize=7,
                ha="left",
                va="top",
            )
            if v != corner:
                axis.set_xticks([])
                axis.set_yticks([])
                continue
            axis.tick_params(labelsize=6)
            axis.set_xlabel(f"x ({unit})", fontsize=7)
            depth = "z (um)" if depths_um is not None else "depth index"
            axis.set_ylabel(f"y ({unit})" if name == "x-y" else depth, fontsize=7)
        figure.text(
            (origin + width * cell / 2) / size[0],
            1 - 0.45 / size[1],
            f"{name} maximum projections",
            ha="center",
            va="top",
            fontsize=9,
        )
    bar_axis = figure.add_axes(
        (1 - 0.95 / size[0], margin["bottom"] / size[1], 0.15 / size[0], height * cell / size[1])
    )
    bar = figure.colorbar(image, cax=bar_axis)
    bar.set_label("PSF (fraction of a point's light per pixel)", fontsize=7)
    bar.ax.tick_params(labelsize=6)
    figure.suptitle(f"{title}: {n_views} views at their lenslets (fgat view order)", fontsize=10)
    return save_figure(figure, path)


def _finish_figure(figure, path: str | Path, title: str = "", fontsize: float = 10) -> Path:
    """Give ``figure`` its ``title`` (when there is one), lay it out and save it
    (:func:`save_figure`)."""
    if title:
        figure.suptitle(title, fontsize=fontsize)
    figure.tight_layout()
    return save_figure(figure, path)


def save_figure(figure, path: str | Path) -> Path:
    """Write a matplotlib figure as PNG (atomically) and close it."""
    import matplotlib.pyplot as plt

    path = Path(path)
    with atomic_path(path) as temporary:
        figure.savefig(temporary, dpi=110, format="png")
    plt.close(figure)
    return path


def pyplot():
    """matplotlib.pyplot on the non-interactive Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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
    return _finish_figure(figure, path, title, fontsize=11)


def mips_figure(
    volumes: dict[str, np.ndarray],
    *,
    title: str = "",
    voxel_size_um: Sequence[float] | None = None,
    units: dict[str, str] | None = None,
):
    """The figure of :func:`plot_mips` (a matplotlib ``Figure``, not yet saved)."""
    plt = pyplot()
    names = list(volumes)
    dz, dy, dx = voxel_size_um or (1.0, 1.0, 1.0)
    length = "um" if voxel_size_um else "voxels"
    figure, axes = plt.subplots(
        2,
        len(names),
        figsize=(2.9 * len(names) + 0.6, 5.0),
        squeeze=False,
        gridspec_kw={"height_ratios": [1, 0.6]},
        layout="constrained",
    )
    for column, name in enumerate(names):
        volume = np.asarray(volumes[name], dtype=np.float64)
        z, y, x = volume.shape
        top = max(float(volume.max()), 1e-30)
        lateral = (-x * dx / 2, x * dx / 2)  # grid centred on 0, as the reconstruction's
        image = axes[0, column].imshow(
            volume.max(axis=0),
            cmap="gray",
            vmin=0,
            vmax=top,
            extent=(*lateral, y * dy / 2, -y * dy / 2),
        )
        axes[1, column].imshow(
            volume.max(axis=1),
            cmap="gray",
            vmin=0,
            vmax=top,
            aspect="auto",
            extent=(*lateral, z * dz / 2, -z * dz / 2),
        )
        axes[0, column].set_title(name, fontsize=9)
        axes[1, column].set_xlabel(f"x ({length})", fontsize=8)
        for axis in axes[:, column]:
            axis.tick_params(labelsize=6)
        bar = figure.colorbar(image, ax=axes[:, column].tolist(), shrink=0.9)
        bar.set_label((units or {}).get(name, "a.u."), fontsize=8)
        bar.ax.tick_params(labelsize=6)
    axes[0, 0].set_ylabel(f"x-y MIP\ny ({length})", fontsize=8)
    axes[1, 0].set_ylabel(f"x-z MIP\nz ({length})", fontsize=8)
    if title:
        figure.suptitle(title, fontsize=10)
    return figure


def plot_mips(
    volumes: dict[str, np.ndarray],
    path: str | Path,
    *,
    title: str = "",
    voxel_size_um: Sequence[float] | None = None,
    units: dict[str, str] | None = None,
) -> Path:
    """x-y (top) and x-z (bottom) maximum projections of labelled ``(Z, Y, X)`` volumes, side
    by side.

    Parameters
    ----------
    volumes : dict
        ``{label: (Z, Y, X) volume}``; one column each, titled with its label, both projections
        on one grey scale from 0 to the volume's maximum.
    path : str or Path
        PNG file to write (atomically).
    voxel_size_um : (dz, dy, dx), optional
        Axes in um on a grid centred on 0 (voxel indices without).
    units : dict, optional
        ``{label: unit}`` of each column's colour bar (``"counts"``; default ``"a.u."``).
    """
    return save_figure(
        mips_figure(volumes, title=title, voxel_size_um=voxel_size_um, units=units), path
    )


def plot_pupil_phases(phases: dict[str, np.ndarray], path: str | Path, *, title: str = "") -> Path:
    """Pupil phase maps in waves (``{label: (H, W)}``, NaN outside the pupil) on one colour
    scale."""
    plt = pyplot()
    values = np.concatenate([np.asarray(p)[np.isfinite(p)] for p in phases.values()])
    limit = float(np.abs(values).max()) if values.size else 1.0
    figure, axes = plt.subplots(
        1, len(phases), figsize=(3.2 * len(phases) + 0.8, 3.2), squeeze=False
    )
    for axis, (label, phase) in zip(axes[0], phases.items()):
        image = axis.imshow(phase, cmap="twilight_shifted", vmin=-limit, vmax=limit)
        axis.set_title(label, fontsize=9)
        axis.axis("off")
    figure.colorbar(image, ax=axes[0].tolist(), shrink=0.8, label="waves")
    if title:
        figure.suptitle(title, fontsize=10)
    return save_figure(figure, path)


def plot_coefficients(
    indices, series: dict[str, Sequence[float]], path: str | Path, *, title: str = ""
) -> Path:
    """Grouped bars of Zernike coefficients (waves) per Noll index, one colour per series."""
    plt = pyplot()
    indices = list(indices)
    width = 0.8 / max(len(series), 1)
    figure, axis = plt.subplots(figsize=(0.45 * len(indices) + 2.5, 3.2))
    positions = np.arange(len(indices))
    for k, (label, values) in enumerate(series.items()):
        axis.bar(positions + (k - (len(series) - 1) / 2) * width, values, width, label=label)
    axis.set_xticks(positions, [str(j) for j in indices], fontsize=8)
    axis.set_xlabel("Noll index j")
    axis.set_ylabel("coefficient (waves)")
    axis.axhline(0, color="black", linewidth=0.6)
    axis.legend(fontsize=8)
    if title:
        axis.set_title(title, fontsize=10)
    figure.tight_layout()
    return save_figure(figure, path)


def mip_series_figure(
    series: dict[str, np.ndarray],
    times: Sequence[float],
    *,
    title: str = "",
    voxel_size_um: Sequence[float] | None = None,
    units: dict[str, str] | None = None,
    max_columns: int = 8,
    maxima: dict[str, float] | None = None,
):
    """The figure of :func:`plot_mip_series` (a matplotlib ``Figure``, not yet saved)."""
    plt = pyplot()
    names = list(series)
    columns = mip_series_columns(len(times), max_columns)
    _, dy, dx = voxel_size_um or (1.0, 1.0, 1.0)
    length = "um" if voxel_size_um else "voxels"
    figure, axes = plt.subplots(
        len(names),
        len(columns),
        figsize=(1.7 * len(columns) + 1.6, 1.9 * len(names) + 0.5),
        squeeze=False,
        sharex=True,
        sharey=True,
        layout="constrained",
    )
    for row, name in enumerate(names):
        mips = np.asarray(series[name], dtype=np.float64).max(axis=1)  # (T, Y, X)
        _, y, x = mips.shape
        top = max(float((maxima or {}).get(name, mips.max())), 1e-30)
        for column, k in enumerate(columns):
            axis = axes[row, column]
            image = axis.imshow(
                mips[k],
                cmap="gray",
                vmin=0,
                vmax=top,
                extent=(-x * dx / 2, x * dx / 2, y * dy / 2, -y * dy / 2),
            )
            axis.tick_params(labelsize=6)
            if row == 0:
                axis.set_title(f"t = {float(times[k]):.2f}", fontsize=8)
            if row == len(names) - 1:
                axis.set_xlabel(f"x ({length})", fontsize=7)
        axes[row, 0].set_ylabel(f"{name}\ny ({length})", fontsize=8)
        bar = figure.colorbar(image, ax=axes[row].tolist(), shrink=0.9)
        bar.set_label((units or {}).get(name, "a.u."), fontsize=7)
        bar.ax.tick_params(labelsize=6)
    if title:
        figure.suptitle(title, fontsize=10)
    return figure


def mip_series_columns(count: int, max_columns: int = 8) -> np.ndarray:
    """The time indices :func:`plot_mip_series` shows of ``count``: at most ``max_columns``,
    evenly spread, first and last included."""
    return np.unique(np.linspace(0, count - 1, min(count, max_columns)).round().astype(int))


def plot_mip_series(
    series: dict[str, np.ndarray],
    times: Sequence[float],
    path: str | Path,
    *,
    title: str = "",
    voxel_size_um: Sequence[float] | None = None,
    units: dict[str, str] | None = None,
    max_columns: int = 8,
    maxima: dict[str, float] | None = None,
) -> Path:
    """x-y maximum projections over time: one row per labelled ``(T, Z, Y, X)`` series, one column
    per time point (at most ``max_columns``, evenly chosen), each row on one grey scale from 0 to
    its maximum (one colour bar per row), so that changes over time stay visible.

    Parameters
    ----------
    series : dict
        ``{label: (T, Z, Y, X) volumes}``.
    times : sequence of float
        ``(T,)`` normalised times, in the column titles.
    path : str or Path
        PNG file to write (atomically).
    voxel_size_um : (dz, dy, dx), optional
        Axes in um on a grid centred on 0 (voxel indices without).
    units : dict, optional
        ``{label: unit}`` of each row's colour bar (``"counts"``; default ``"a.u."``).
    maxima : dict, optional
        ``{label: top}`` of a row's grey scale, for series given only at the shown time points
        (:func:`mip_series_columns`) whose maximum over all time points is known; default the
        series' maximum.
    """
    return save_figure(
        mip_series_figure(
            series,
            times,
            title=title,
            voxel_size_um=voxel_size_um,
            units=units,
            max_columns=max_columns,
            maxima=maxima,
        ),
        path,
    )


def plot_calibration_overlay(
    image: np.ndarray,
    centers: np.ndarray,
    radius_px: float,
    path: str | Path,
    *,
    gains: np.ndarray | None = None,
    hot_pixels: np.ndarray | None = None,
) -> Path:
    """The image ``(H, W)`` with a circle of ``radius_px`` at each lenslet centre ``(V, 2)``
    (row, col) pixels, its view number on the circle's upper-left rim (small, clear of the
    disc's contents), and the hot pixels ``(H, W)`` (bool) marked with red crosses. With
    ``gains`` ``(V,)`` each circle takes its gain's colour (colour bar) and a table beside the
    image lists every view's gain."""
    plt = pyplot()
    centers = np.asarray(centers, dtype=np.float64)
    height, width = image.shape
    table_columns = 0 if gains is None else 1 + int(len(centers) > 19)
    table_rows = -(-len(centers) // max(table_columns, 1))
    side = 0.0 if gains is None else 0.4 + 1.0 * table_columns
    image_in = 6.0
    size = (image_in + 1.0 + side, max(image_in * height / width + 1.0, 0.16 * table_rows + 1.2))
    figure = plt.figure(figsize=size)
    axis = figure.add_axes(
        (0.75 / size[0], 0.6 / size[1], image_in / size[0], (size[1] - 1.0) / size[1])
    )
    axis.imshow(image, cmap="gray")
    title = f"{len(centers)} lenslets, fgat view order"
    colours = plt.get_cmap("viridis")
    rim = radius_px / np.sqrt(2.0)
    points_per_px = 72.0 * min(image_in / width, (size[1] - 1.0) / height)
    fontsize = float(np.clip(0.45 * radius_px * points_per_px, 4.5, 8.0))
    for view, (row, col) in enumerate(centers):
        colour = "tab:orange" if gains is None else colours(float(gains[view]))
        axis.add_patch(plt.Circle((col, row), radius_px, fill=False, color=colour, lw=0.8))
        axis.text(
            col - rim,
            row - rim,
            str(view),
            color="black",
            ha="center",
            va="center",
            fontsize=fontsize,
            bbox={"boxstyle": "round,pad=0.15", "facecolor": colour, "edgecolor": "none"},
        )
    if gains is not None:
        title += f", gains {np.min(gains):.3f}-{np.max(gains):.3f}"
        mappable = plt.cm.ScalarMappable(cmap=colours, norm=plt.Normalize(0.0, 1.0))
        bar = figure.colorbar(mappable, ax=axis, fraction=0.04, pad=0.02)
        bar.set_label("relative gain (circle colour)", fontsize=8)
        bar.ax.tick_params(labelsize=7)
        lines = [f"{v:>3} {g:.3f}" for v, g in enumerate(gains)]
        columns = [lines[k * table_rows : (k + 1) * table_rows] for k in range(table_columns)]
        for k, column in enumerate(columns):
            figure.text(
                (image_in + 1.35 + 1.0 * k) / size[0],
                1 - 0.55 / size[1],
                "view gain\n" + "\n".join(column),
                family="monospace",
                fontsize=7,
                va="top",
            )
    if hot_pixels is not None and hot_pixels.any():
        rows, cols = np.nonzero(hot_pixels)
        axis.plot(cols, rows, "x", color="red", markersize=4, markeredgewidth=0.8)
        title += f", {len(rows)} hot pixel(s) (x)"
    axis.set_title(title, fontsize=10)
    axis.set_xlabel("column (px)")
    axis.set_ylabel("row (px)")
    return save_figure(figure, path)


def plot_standard_errors(
    labels: Sequence[str],
    estimates: Sequence[float],
    stderrs: Sequence[float],
    flagged: Sequence[bool],
    path: str | Path,
    *,
    groups: Sequence[str],
    truth: Sequence[float] | None = None,
    title: str = "",
) -> Path:
    """Estimated parameters with +/- 2 standard-error bars, one panel per group.

    Parameters
    ----------
    labels, estimates, stderrs, flagged : sequence
        Per parameter: its tick label (``"c5"``, ``"b0_y"``), value, standard error, and whether
        it is flagged as poorly determined (drawn in red, the others in blue).
    path : str or Path
        PNG file to write (atomically).
    groups : sequence of str
        Per parameter, its panel's y-axis label with the unit (``"Zernike (waves)"``); panels in
        order of first appearance.
    truth : sequence of float, optional
        True values, drawn as black crosses.
    """
    plt = pyplot()
    estimates, stderrs = np.asarray(estimates, float), np.asarray(stderrs, float)
    flagged = np.asarray(flagged, bool)
    panels = list(dict.fromkeys(groups))
    members = {panel: [k for k, g in enumerate(groups) if g == panel] for panel in panels}
    widest = max(len(k) for k in members.values())
    figure, axes = plt.subplots(
        len(panels), 1, figsize=(0.32 * widest + 2.8, 2.6 * len(panels) + 0.4), squeeze=False
    )
    for axis, panel in zip(axes[:, 0], panels):
        indices = np.asarray(members[panel])
        positions = np.arange(len(indices))
        for chosen, color, label in (
            (~flagged[indices], "tab:blue", "estimate +/- 2 s.e."),
            (flagged[indices], "tab:red", "flagged (s.e. above tolerance)"),
        ):
            if chosen.any():
                axis.errorbar(
                    positions[chosen],
                    estimates[indices][chosen],
                    yerr=2 * stderrs[indices][chosen],
                    fmt="o",
                    markersize=3.5,
                    capsize=2.5,
                    color=color,
                    label=label,
                )
        if truth is not None:
            axis.plot(
                positions, np.asarray(truth, float)[indices], "x", color="black", label="truth"
            )
        axis.axhline(0, color="black", linewidth=0.6)
        axis.set_xticks(positions, [labels[k] for k in indices], fontsize=7, rotation=90)
        axis.set_ylabel(panel, fontsize=8)
        axis.tick_params(axis="y", labelsize=7)
        axis.grid(alpha=0.3)
        axis.legend(fontsize=7)
    if title:
        figure.suptitle(title, fontsize=10)
    figure.tight_layout()
    return save_figure(figure, path)


def _zernike_labels(indices) -> list[str]:
    """``"j (Family)"`` tick labels of Noll indices."""
    from fgat.optics.zernike import zernike_family

    return [f"{j} ({zernike_family(j)})" for j in indices]


def plot_eta_profiles(
    indices, profiles: dict[str, Sequence[float]], path: str | Path, *, title: str = ""
) -> Path:
    """Bars of modal profiles (Eq. S48, dimensionless) per Noll index, one panel per profile
    (``{label: (K,)}``, e.g. ``eta^b`` and ``eta^s``), with each profile's median dashed."""
    plt = pyplot()
    indices = list(indices)
    figure, axes = plt.subplots(
        1, len(profiles), figsize=(0.42 * len(indices) * len(profiles) + 1.5, 3.8), squeeze=False
    )
    positions = np.arange(len(indices))
    for axis, (label, values) in zip(axes[0], profiles.items()):
        values = np.asarray(values, dtype=float)
        axis.bar(positions, values, 0.7)
        axis.axhline(
            np.median(values), color="black", linestyle="--", linewidth=0.8, label="median"
        )
        axis.set_xticks(positions, _zernike_labels(indices), rotation=70, ha="right", fontsize=7)
        axis.set_ylabel("eta_j")
        axis.set_title(label, fontsize=9)
        axis.legend(fontsize=7)
    return _finish_figure(figure, path, title)


def plot_cross_information(
    block: np.ndarray, indices, n_views: int, path: str | Path, *, title: str = ""
) -> Path:
    """Heat map of the cross-information ``C`` ``(K, 4V)`` (Eq. S43): Zernike terms (rows) against
    the intercepts then slopes of every view (columns ``b<v>_y, b<v>_x, ..., s<v>_y, s<v>_x``,
    pixels), on a symmetric colour scale."""
    plt = pyplot()
    block = np.asarray(block, dtype=float)
    indices = list(indices)
    limit = float(np.abs(block).max()) or 1.0
    columns = [f"{kind}{v}_{axis}" for kind in "bs" for v in range(n_views) for axis in "yx"]
    figure, axis = plt.subplots(figsize=(0.28 * len(columns) + 3.5, 0.28 * len(indices) + 1.8))
    image = axis.imshow(block, cmap="RdBu_r", vmin=-limit, vmax=limit, aspect="auto")
    axis.set_yticks(np.arange(len(indices)), _zernike_labels(indices), fontsize=7)
    axis.set_xticks(np.arange(len(columns)), columns, rotation=90, fontsize=7)
    axis.axvline(2 * n_views - 0.5, color="black", linewidth=1.0)
    figure.colorbar(image, ax=axis, label="C (image units^2 per wave per pixel)")
    if title:
        axis.set_title(title, fontsize=10)
    figure.tight_layout()
    return save_figure(figure, path)


def plot_leakage(
    indices,
    cases: dict[str, tuple[Sequence[float], Sequence[float]]],
    path: str | Path,
    *,
    title: str = "",
) -> Path:
    """Measured against predicted Zernike leakage (waves) per Noll index, one panel per case
    (``{label: (measured (K,), predicted (K,))}``, Eq. S51)."""
    plt = pyplot()
    indices = list(indices)
    figure, axes = plt.subplots(
        len(cases), 1, figsize=(0.42 * len(indices) + 2.5, 2.6 * len(cases)), squeeze=False
    )
    positions = np.arange(len(indices))
    for axis, (label, (measured, predicted)) in zip(axes[:, 0], cases.items()):
        axis.bar(positions - 0.2, measured, 0.4, label="measured (refit)")
        axis.bar(positions + 0.2, predicted, 0.4, label="predicted -A^-1 C dTheta_G")
        axis.axhline(0, color="black", linewidth=0.6)
        axis.set_xticks(positions, [str(j) for j in indices], fontsize=8)
        axis.set_ylabel("dc_j (waves)")
        axis.set_title(label, fontsize=9)
        axis.legend(fontsize=7)
    axes[-1, 0].set_xlabel("Noll index j")
    return _finish_figure(figure, path, title)


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
    return _finish_figure(figure, path, title)


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
    return _finish_figure(figure, path, title)


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
    return _finish_figure(figure, path, title)


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
    return _finish_figure(figure, path, title)


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
    _grouped_lines(axis, kept, linewidth=0.8, alpha=0.7)
    axis.set_xscale("log")
    axis.set_yscale("log")
    axis.set_xlabel("lag (s)")
    axis.set_ylabel("MSD (um^2)")
    axis.grid(alpha=0.3, which="both")
    axis.legend(fontsize=8)
    return _finish_figure(figure, path, title)


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
    colours = _grouped_lines(axis, {k: [(p[:, 0], p[:, 1]) for p in v] for k, v in xy.items()})
    for colour, group in zip(colours, xy.values()):
        for positions in group:
            axis.plot(positions[0, 0], positions[0, 1], "o", color=colour, markersize=2.5)
    axis.set_aspect("equal", adjustable="datalim")
    axis.invert_yaxis()
    axis.set_xlabel("x (um)")
    axis.set_ylabel("y (um)")
    axis.legend(fontsize=8)
    return _finish_figure(figure, path, title)


def _grouped_lines(axis, groups: dict[str, Sequence[tuple]], **style) -> list[str]:
    """Draw ``{label: [(x, y), ...]}`` on ``axis``, one colour of the property cycle per label
    (the label on its first line only, for the legend); returns the colours in label order."""
    cycle = pyplot().rcParams["axes.prop_cycle"].by_key()["color"]
    colours = [cycle[k % len(cycle)] for k in range(len(groups))]
    for colour, (label, lines) in zip(colours, groups.items()):
        for n, (x, y) in enumerate(lines):
            axis.plot(x, y, color=colour, label=label if n == 0 else None, **style)
    return colours
