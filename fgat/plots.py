"""PNG figures of the things people look at (matplotlib, non-interactive backend)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from fgat.io import atomic_path


def plot_psf_stack(
    stack: np.ndarray,
    path: str | Path,
    *,
    title: str = "PSF stack",
    depths_um: Sequence[float] | None = None,
    pixel_um: float | None = None,
) -> Path:
    """Save x-y (top row) and x-z (bottom row) maximum projections of every view of a PSF stack.

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
    stack = np.asarray(stack)
    n_views, n_depths, h, w = stack.shape
    pixel = pixel_um or 1.0
    unit = "um" if pixel_um else "px"
    z = np.asarray(depths_um if depths_um is not None else np.arange(n_depths), dtype=float)
    figure, axes = plt.subplots(2, n_views, figsize=(2.2 * n_views, 4.6), squeeze=False)
    for v in range(n_views):
        xy = stack[v].max(axis=0)
        xz = stack[v].max(axis=1)
        axes[0, v].imshow(
            xy, cmap="magma", extent=(-w / 2 * pixel, w / 2 * pixel, h / 2 * pixel, -h / 2 * pixel)
        )
        axes[0, v].set_title(f"view {v}", fontsize=9)
        axes[1, v].imshow(
            xz, cmap="magma", aspect="auto", extent=(-w / 2 * pixel, w / 2 * pixel, z[-1], z[0])
        )
        for axis in axes[:, v]:
            axis.tick_params(labelsize=7)
    axes[0, 0].set_ylabel(f"y ({unit})", fontsize=8)
    axes[1, 0].set_ylabel("z (um)" if depths_um is not None else "depth index", fontsize=8)
    for v in range(n_views):
        axes[1, v].set_xlabel(f"x ({unit})", fontsize=8)
    figure.suptitle(f"{title}: x-y (top) and x-z (bottom) maximum projections", fontsize=10)
    figure.tight_layout()
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
):
    """The figure of :func:`plot_mip_series` (a matplotlib ``Figure``, not yet saved)."""
    plt = pyplot()
    names = list(series)
    count = len(times)
    columns = np.unique(np.linspace(0, count - 1, min(count, max_columns)).round().astype(int))
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
        top = max(float(mips.max()), 1e-30)
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


def plot_mip_series(
    series: dict[str, np.ndarray],
    times: Sequence[float],
    path: str | Path,
    *,
    title: str = "",
    voxel_size_um: Sequence[float] | None = None,
    units: dict[str, str] | None = None,
    max_columns: int = 8,
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
    """
    return save_figure(
        mip_series_figure(
            series,
            times,
            title=title,
            voxel_size_um=voxel_size_um,
            units=units,
            max_columns=max_columns,
        ),
        path,
    )


def plot_lenslet_overlay(
    image: np.ndarray, centers: np.ndarray, radius_px: float, path: str | Path
) -> Path:
    """The image ``(H, W)`` with a circle of ``radius_px`` and the view number at each lenslet
    centre ``(V, 2)`` (row, col) pixels."""
    plt = pyplot()
    figure, axis = plt.subplots(figsize=(6.0, 6.0 * image.shape[0] / image.shape[1]))
    axis.imshow(image, cmap="gray")
    for view, (row, col) in enumerate(np.asarray(centers)):
        axis.add_patch(plt.Circle((col, row), radius_px, fill=False, color="tab:orange", lw=0.8))
        axis.text(col, row, str(view), color="tab:orange", ha="center", va="center", fontsize=8)
    axis.set_title(f"{len(centers)} lenslets, fgat view order", fontsize=10)
    axis.set_xlabel("column (px)")
    axis.set_ylabel("row (px)")
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
    """The image ``(H, W)`` with a circle of ``radius_px`` and the view number at each lenslet
    centre ``(V, 2)`` (row, col) pixels, each view's gain under its number when ``gains``
    ``(V,)`` are given, and the hot pixels ``(H, W)`` (bool) marked with red crosses."""
    plt = pyplot()
    figure, axis = plt.subplots(figsize=(6.0, 6.0 * image.shape[0] / image.shape[1]))
    axis.imshow(image, cmap="gray")
    title = f"{len(centers)} lenslets, fgat view order"
    for view, (row, col) in enumerate(np.asarray(centers)):
        axis.add_patch(plt.Circle((col, row), radius_px, fill=False, color="tab:orange", lw=0.8))
        label = str(view) if gains is None else f"{view}\n{gains[view]:.3f}"
        axis.text(col, row, label, color="tab:orange", ha="center", va="center", fontsize=8)
    if gains is not None:
        title += f", gains {np.min(gains):.3f}-{np.max(gains):.3f}"
    if hot_pixels is not None and hot_pixels.any():
        rows, cols = np.nonzero(hot_pixels)
        axis.plot(cols, rows, "x", color="red", markersize=4, markeredgewidth=0.8)
        title += f", {len(rows)} hot pixel(s) (x)"
    axis.set_title(title, fontsize=10)
    axis.set_xlabel("column (px)")
    axis.set_ylabel("row (px)")
    figure.tight_layout()
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
