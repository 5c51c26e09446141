"""Volumes as pictures: x-y and x-z maximum-intensity projections (MIPs) with their scale
in micrometres and colour bars, for one volume or a series.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from fgat.viz.figures import pyplot, save_figure


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
