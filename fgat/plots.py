"""PNG figures of the things people look at (matplotlib, non-interactive backend)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from fgat.io import atomic_path


def plot_psf_stack(stack: np.ndarray, path: str | Path, *, title: str = "PSF stack",
                   depths_um: Sequence[float] | None = None, pixel_um: float | None = None) -> Path:
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
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    stack = np.asarray(stack)
    n_views, n_depths, h, w = stack.shape
    pixel = pixel_um or 1.0
    unit = "um" if pixel_um else "px"
    z = np.asarray(depths_um if depths_um is not None else np.arange(n_depths), dtype=float)
    figure, axes = plt.subplots(2, n_views, figsize=(2.2 * n_views, 4.6), squeeze=False)
    for v in range(n_views):
        xy = stack[v].max(axis=0)
        xz = stack[v].max(axis=1)
        axes[0, v].imshow(xy, cmap="magma", extent=(-w / 2 * pixel, w / 2 * pixel, h / 2 * pixel, -h / 2 * pixel))
        axes[0, v].set_title(f"view {v}", fontsize=9)
        axes[1, v].imshow(xz, cmap="magma", aspect="auto",
                          extent=(-w / 2 * pixel, w / 2 * pixel, z[-1], z[0]))
        for axis in axes[:, v]:
            axis.tick_params(labelsize=7)
    axes[0, 0].set_ylabel(f"y ({unit})", fontsize=8)
    axes[1, 0].set_ylabel("z (um)" if depths_um is not None else "depth index", fontsize=8)
    for v in range(n_views):
        axes[1, v].set_xlabel(f"x ({unit})", fontsize=8)
    figure.suptitle(f"{title}: x-y (top) and x-z (bottom) maximum projections", fontsize=10)
    figure.tight_layout()
    path = Path(path)
    with atomic_path(path) as temporary:
        figure.savefig(temporary, dpi=110, format="png")
    plt.close(figure)
    return path
