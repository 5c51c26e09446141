"""Figures of the optics: PSF stacks per view, pupil phases and Zernike coefficients, the
calibration overlay, standard errors, and the cross-information diagnostics (Notes S4-S5).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from fgat.viz.figures import finish_figure, pyplot, save_figure

LATTICE_CELL_IN = (0.85, 1.8)
"""Smallest and largest side (inches) of one view's panel in the lattice layouts."""


def _lattice_cells(n_views: int) -> tuple[np.ndarray, float, float]:
    """Where each of ``n_views`` views sits in a lattice layout: ``(V, 2)`` (left, bottom) of
    its unit cell in cells from the layout's lower-left corner, and the layout's width and
    height in cells (fgat's view order on the unrotated hexagonal lattice,
    :func:`~fgat.optics.lenslets.hexagonal_offsets`, one pitch per cell)."""
    from fgat.optics.lenslets import hexagonal_offsets  # imported when used: keeps start-up fast

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
    from fgat.optics.zernike import zernike_family  # imported when used: keeps start-up fast

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
    return finish_figure(figure, path, title)


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
    return finish_figure(figure, path, title)
