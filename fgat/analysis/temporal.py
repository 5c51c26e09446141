"""Volume time series: image-space temporal interpolation and kymographs (Fig. S12).

Series are ``(T, Z, Y, X)`` arrays sampled at increasing times ``(T,)`` (any unit, e.g. the
normalised sequence time of the dynamic stage).
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import CubicSpline


def _check_times(series: np.ndarray, times: np.ndarray) -> None:
    if len(times) != len(series) or len(times) < 2 or np.any(np.diff(times) <= 0):
        raise ValueError(
            f"need two or more strictly increasing times, one per frame; got {len(times)} times "
            f"for {len(series)} frames"
        )


def cubic_interpolation(series: np.ndarray, times, query) -> np.ndarray:
    """Cubic-spline interpolation in time of every voxel (not-a-knot ends), clipped at zero:
    ``(len(query), ...)`` float32 (Fig. S12's conventional 10x upsampling)."""
    series, times = np.asarray(series), np.asarray(times, dtype=np.float64)
    _check_times(series, times)
    return np.clip(
        CubicSpline(times, series, axis=0)(np.asarray(query, dtype=np.float64)), 0, None
    ).astype(np.float32)


def sample_and_hold(series: np.ndarray, times, query) -> np.ndarray:
    """The latest frame at or before each query time (the acquisition as it was recorded);
    queries before the first frame get the first."""
    series, times = np.asarray(series), np.asarray(times, dtype=np.float64)
    _check_times(series, times)
    index = np.searchsorted(
        times, np.asarray(query, dtype=np.float64) + 1e-9 * (times[-1] - times[0]), side="right"
    )
    return series[np.clip(index - 1, 0, len(times) - 1)]


def kymograph(series: np.ndarray, row: int | None = None, half_width: int = 1) -> np.ndarray:
    """``(T, X)``: per time, the maximum over rows ``row +- half_width`` (default the central row)
    of the x-y maximum projection of each ``(Z, Y, X)`` volume."""
    series = np.asarray(series)
    if series.ndim != 4:
        raise ValueError(f"expected a (T, Z, Y, X) series, got shape {series.shape}")
    row = series.shape[2] // 2 if row is None else row
    band = series.max(axis=1)[:, max(row - half_width, 0) : row + half_width + 1]
    if band.shape[1] == 0:
        raise ValueError(f"row {row} is outside the {series.shape[2]} rows")
    return band.max(axis=1)
