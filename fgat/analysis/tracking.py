"""Cell tracking, speed classes and anomalous diffusion (Note S8.9, Eq. S62; Fig. 5h-j).

Pipeline: ``track`` locates cells in every ``(Z, Y, X)`` volume of a ``(T, Z, Y, X)`` series with
trackpy's 3D locate (anisotropic diameters) and links them with trackpy's linker in micrometres;
``sliding_speeds`` / ``mean_speeds`` give the speed traces and the per-cell mean speeds;
``speed_threshold`` splits slow from fast cells at the density minimum between the two modes of
the log mean-speed distribution (the paper's 8.27 um/s); ``msd`` (Eq. S62) and
``anomalous_exponent`` summarise each trajectory's motion mode. ``driven_and_free_tracks`` is the
phantom with a known answer: a 1:5 mixture of magnetically driven and free cells.

Positions are in micrometres, ordered ``(z, y, x)``; voxel ``i`` along an axis has its centre at
``(i + 0.5) * voxel_size_um``, as everywhere in fgat (the volume's corner at 0 um). Times are in
seconds.
"""

from __future__ import annotations

import warnings
from contextlib import contextmanager

import numpy as np
import pandas as pd
import trackpy as tp
from scipy.stats import gaussian_kde

from fgat.analysis.scales import check_length_um

POSITION_COLUMNS = ["z", "y", "x"]
TRAJECTORY_COLUMNS = ["frame", "particle", "t_s", "z", "y", "x", "mass"]


def _positive_triple(value, name: str) -> np.ndarray:
    triple = np.broadcast_to(np.asarray(value, dtype=np.float64), (3,))
    if not np.all(np.isfinite(triple) & (triple > 0)):
        raise ValueError(f"{name} must be positive (one value or dz, dy, dx); got {value!r}")
    return triple


def _positive(value: float, name: str) -> float:
    if not (np.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be positive; got {value!r}")
    return float(value)


def odd_diameter_px(diameter_um, voxel_size_um) -> tuple[int, int, int]:
    """Feature diameters in voxels as trackpy needs them: one odd integer per axis.

    Each ``diameter_um / voxel_size_um`` is rounded to the nearest odd integer (halfway values,
    the even integers, go up: 4 -> 5, 5.9 -> 5, 6 -> 7), and to at least 3 voxels.

    Parameters
    ----------
    diameter_um : float or (3,) float
        Cell diameter in um, one value or ``(dz, dy, dx)``-ordered per axis.
    voxel_size_um : float or (3,) float
        Voxel size ``(dz, dy, dx)`` in um.

    Returns
    -------
    (3,) tuple of int
        Odd diameters in voxels, ``(z, y, x)``.
    """
    pixels = _positive_triple(diameter_um, "diameter_um") / _positive_triple(
        voxel_size_um, "voxel_size_um"
    )
    return tuple(max(3, 2 * int(np.floor(p / 2)) + 1) for p in pixels)


@contextmanager
def _trackpy_quiet():
    """``trackpy.quiet()`` for the duration of the block; the caller's level comes back after."""
    level = tp.logger.level
    tp.quiet()
    try:
        yield
    finally:
        tp.logger.setLevel(level)


def _locate(volumes: np.ndarray, diameter_px, minmass, separation_px) -> pd.DataFrame:
    """trackpy's 3D locate on every frame, in voxel coordinates; the trackpy warnings that
    ``track`` answers itself (no maxima, 3- or 4-long axes read as colour) are silenced."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="No maxima found")
        warnings.filterwarnings("ignore", message="I am interpreting the image")
        return tp.batch(
            list(volumes),
            diameter_px,
            minmass=minmass,
            separation=separation_px,
            processes=1,
        )


def track(
    volumes,
    *,
    voxel_size_um,
    frame_interval_s: float,
    diameter_um,
    search_range_um: float,
    memory: int = 0,
    minmass: float | None = None,
    separation_um=None,
) -> pd.DataFrame:
    """Locate and link cells in a volume time series (Note S8.9).

    Every ``(Z, Y, X)`` frame goes through ``trackpy.batch`` (3D ``trackpy.locate``) with
    anisotropic diameters (``odd_diameter_px``); voxel coordinates are converted to um before
    ``trackpy.link``, so ``search_range_um`` is isotropic in sample space.

    Parameters
    ----------
    volumes : (T, Z, Y, X) array
        Volume series (e.g. reconstructed volumes of the ferritin channel).
    voxel_size_um : float or (3,) float
        Voxel size ``(dz, dy, dx)`` in um.
    frame_interval_s : float
        Time between frames in s.
    diameter_um : float or (3,) float
        Cell diameter in um (``(z, y, x)`` when per axis); rounded per axis to odd voxel counts.
        It should span the whole cell image (about 7 standard deviations of a Gaussian blob per
        axis): a narrower mask pixel-locks trackpy's centroid (about 0.4 voxel bias at 3
        standard deviations, 0.03 at 7).
    search_range_um : float
        Largest displacement between linked frames, in um.
    memory : int
        Frames a cell may vanish for and keep its identity.
    minmass : float, optional
        Smallest integrated brightness of a located feature (trackpy's ``minmass``; default 0),
        in the volumes' intensity units. trackpy's band pass also zeroes values below its
        default ``threshold`` (1/255 for float volumes), so scale very dim volumes up.
    separation_um : float or (3,) float, optional
        Smallest distance between features in um (default: trackpy's, the diameter plus one
        voxel).

    Returns
    -------
    pandas.DataFrame
        One row per located cell and frame, columns ``frame``, ``particle``, ``t_s``
        (``frame * frame_interval_s``), ``z``, ``y``, ``x`` (um) and ``mass``.

    Raises
    ------
    ValueError
        Not a ``(T, Z, Y, X)`` series, an empty series, non-positive voxel sizes, frame interval,
        diameters or search range, or no cell located in any frame.
    """
    volumes = np.asarray(volumes)
    if volumes.ndim != 4:
        raise ValueError(f"expected a (T, Z, Y, X) volume series; got shape {volumes.shape}")
    if volumes.size == 0:
        raise ValueError(f"the volume series is empty; got shape {volumes.shape}")
    voxel = _positive_triple(voxel_size_um, "voxel_size_um")
    frame_interval_s = _positive(frame_interval_s, "frame_interval_s")
    search_range_um = _positive(search_range_um, "search_range_um")
    check_length_um("diameter_um", diameter_um, voxel, volumes.shape)
    check_length_um(
        "search_range_um", search_range_um, voxel, volumes.shape, min_voxels=0, axes="YX"
    )
    diameter_px = odd_diameter_px(diameter_um, voxel)
    separation_px = (
        None
        if separation_um is None
        else tuple(_positive_triple(separation_um, "separation_um") / voxel)
    )
    with _trackpy_quiet():
        features = _locate(volumes, diameter_px, minmass, separation_px)
        if features.empty:
            raise ValueError(
                f"no objects detected in any of the {len(volumes)} frames; lower minmass "
                f"(now {minmass}) or check diameter_um (now {diameter_px} voxels (z, y, x))"
            )
        features[POSITION_COLUMNS] = (features[POSITION_COLUMNS].to_numpy(np.float64) + 0.5) * voxel
        linked = tp.link(features, search_range_um, pos_columns=POSITION_COLUMNS, memory=memory)
    linked["t_s"] = linked["frame"] * frame_interval_s
    linked = linked[TRAJECTORY_COLUMNS].astype({"frame": int, "particle": int})
    return linked.sort_values(["particle", "frame"]).reset_index(drop=True)


def _position_columns(trajectories: pd.DataFrame) -> list[str]:
    columns = [c for c in POSITION_COLUMNS if c in trajectories.columns]
    missing = {"frame", "particle"} - set(trajectories.columns)
    if not columns or missing:
        raise ValueError(
            "trajectories need columns frame, particle and some of z, y, x (um); got "
            f"{list(trajectories.columns)}"
        )
    return columns


def sliding_speeds(
    trajectories: pd.DataFrame, window: int, *, frame_interval_s: float | None = None
) -> pd.DataFrame:
    """Speed traces from sliding-window displacements (Note S8.9, Fig. 5h).

    For every particle and every frame ``t`` at which the particle is also found at frame
    ``t + window``: speed ``= |r(t + window) - r(t)| / (time from t to t + window)``. Windows whose
    end frame is missing (a gap bridged by ``memory``, or the end of the track) are skipped.

    Parameters
    ----------
    trajectories : pandas.DataFrame
        ``track``'s table: columns ``frame``, ``particle``, positions ``z``, ``y``, ``x`` in um
        (any subset, e.g. ``y``, ``x`` for 2D), and ``t_s`` (s) unless ``frame_interval_s`` is
        given.
    window : int
        Window length in frames (>= 1).
    frame_interval_s : float, optional
        Time between frames in s; default: the times in the ``t_s`` column.

    Returns
    -------
    pandas.DataFrame
        One row per particle and window start, columns ``particle``, ``frame`` and ``t_s`` (of the
        window start) and ``speed_um_s``, sorted by particle and frame.
    """
    columns = _position_columns(trajectories)
    if int(window) != window or window < 1:
        raise ValueError(f"window must be a whole number of frames >= 1; got {window!r}")
    table = trajectories[["particle", "frame", *columns]].copy()
    if frame_interval_s is not None:
        table["t_s"] = table["frame"] * _positive(frame_interval_s, "frame_interval_s")
    elif "t_s" in trajectories.columns:
        table["t_s"] = trajectories["t_s"]
    else:
        raise ValueError("trajectories have no t_s column; pass frame_interval_s")
    ends = table.assign(frame=table["frame"] - int(window))
    pairs = table.merge(ends, on=["particle", "frame"], suffixes=("", "_end"))
    displacement = np.sqrt(
        sum((pairs[f"{c}_end"] - pairs[c]).to_numpy(np.float64) ** 2 for c in columns)
    )
    pairs["speed_um_s"] = displacement / (pairs["t_s_end"] - pairs["t_s"]).to_numpy(np.float64)
    pairs = pairs[["particle", "frame", "t_s", "speed_um_s"]]
    return pairs.sort_values(["particle", "frame"]).reset_index(drop=True)


def mean_speeds(
    trajectories: pd.DataFrame, window: int, *, frame_interval_s: float | None = None
) -> pd.Series:
    """Per-particle mean of the sliding-window speeds (``sliding_speeds``), in um/s.

    Returns
    -------
    pandas.Series
        Indexed by particle, named ``mean_speed_um_s``; particles tracked for fewer than
        ``window + 1`` frames have no window and are left out.
    """
    speeds = sliding_speeds(trajectories, window, frame_interval_s=frame_interval_s)
    return speeds.groupby("particle")["speed_um_s"].mean().rename("mean_speed_um_s")


def _local_maxima(density: np.ndarray) -> np.ndarray:
    rising = np.diff(density) > 0
    return np.flatnonzero(rising[:-1] & ~rising[1:]) + 1


def speed_threshold(mean_speeds, *, grid_points: int = 4096) -> float:
    """Slow/fast split at the density minimum between the two modes of the log mean speeds.

    The distribution of ``log(mean speed)`` is estimated with ``scipy.stats.gaussian_kde``
    (Scott's bandwidth) on a grid of ``grid_points`` spanning the data plus three bandwidths on
    each side; the two highest local maxima are the modes and the threshold is ``exp`` of the
    lowest-density grid point between them (Note S8.9: 8.27 um/s in the paper).

    Parameters
    ----------
    mean_speeds : (N,) array-like
        Per-cell mean speeds in um/s (``mean_speeds``), positive and finite; N >= 4.
    grid_points : int
        Grid size of the density evaluation.

    Returns
    -------
    float
        The threshold speed in um/s.

    Raises
    ------
    ValueError
        Fewer than 4 speeds, non-positive or non-finite speeds, or a distribution with fewer than
        two modes.
    """
    speeds = np.asarray(mean_speeds, dtype=np.float64).ravel()
    if speeds.size < 4:
        raise ValueError(f"need at least 4 mean speeds for a density estimate; got {speeds.size}")
    if not np.all(np.isfinite(speeds) & (speeds > 0)):
        raise ValueError("mean speeds must be positive and finite (their logarithm is used)")
    logs = np.log(speeds)
    if np.ptp(logs) == 0:
        raise ValueError("all mean speeds are equal: the distribution is not bimodal")
    kde = gaussian_kde(logs)
    pad = 3 * np.sqrt(kde.covariance[0, 0])
    grid = np.linspace(logs.min() - pad, logs.max() + pad, grid_points)
    density = kde(grid)
    peaks = _local_maxima(density)
    if peaks.size < 2:
        raise ValueError(
            "the log mean-speed distribution is not bimodal (one mode); no slow/fast threshold"
        )
    low, high = np.sort(peaks[np.argsort(density[peaks])[-2:]])
    return float(np.exp(grid[low + np.argmin(density[low : high + 1])]))


def msd(positions) -> tuple[np.ndarray, np.ndarray]:
    """Time-averaged mean squared displacement of one trajectory (Eq. S62).

    ``MSD(tau) = < |r(t + tau) - r(t)|^2 >_t``, averaged over all valid windows: pairs of frames
    ``tau`` apart where both positions are known. Equals ``trackpy.imsd`` on the same track.

    Parameters
    ----------
    positions : (T, D) array
        Positions in um per frame, consecutive frames; a row with a NaN is a missing frame.

    Returns
    -------
    lags : (T - 1,) int array
        Lags in frames, ``1 .. T - 1``.
    values : (T - 1,) float array
        MSD in um^2; NaN at lags with no valid window.
    """
    positions = np.asarray(positions, dtype=np.float64)
    if positions.ndim != 2 or positions.shape[0] < 2 or positions.shape[1] < 1:
        raise ValueError(f"expected (T, D) positions with T >= 2; got shape {positions.shape}")
    valid = np.all(np.isfinite(positions), axis=1)
    lags = np.arange(1, positions.shape[0])
    values = np.full(lags.shape, np.nan)
    for i, lag in enumerate(lags):
        both = valid[lag:] & valid[:-lag]
        if both.any():
            step = positions[lag:][both] - positions[:-lag][both]
            values[i] = np.mean(np.sum(step**2, axis=1))
    return lags, values


def anomalous_exponent(lags, values, *, max_lag: float | None = None) -> float:
    """Anomalous-diffusion exponent alpha: the least-squares slope of ``log MSD`` on ``log lag``.

    ``MSD ~ tau^alpha``: alpha ~ 1 for Brownian diffusion, ~ 2 for ballistic (directed) motion,
    < 1 for confined motion (Note S8.9).

    Parameters
    ----------
    lags : (L,) array
        Lags (frames or s; alpha does not depend on the unit).
    values : (L,) array
        MSD at those lags (``msd``); NaN and non-positive values are left out of the fit.
    max_lag : float, optional
        Fit only lags ``<= max_lag``; default: the first quarter of the lags, at least 3.

    Returns
    -------
    float
        alpha.
    """
    lags, values = np.asarray(lags, np.float64), np.asarray(values, np.float64)
    if lags.shape != values.shape or lags.ndim != 1:
        raise ValueError(
            f"lags and values must be 1D of one length; got {lags.shape}, {values.shape}"
        )
    if max_lag is None:
        max_lag = np.sort(lags)[min(lags.size, max(3, lags.size // 4)) - 1] if lags.size else 0
    keep = (lags > 0) & (lags <= max_lag) & np.isfinite(values) & (values > 0)
    if keep.sum() < 2:
        raise ValueError(
            f"need two or more positive MSD values at lags <= {max_lag} for a log-log fit; "
            f"got {keep.sum()}"
        )
    return float(np.polyfit(np.log(lags[keep]), np.log(values[keep]), 1)[0])


def driven_and_free_tracks(
    n_cells: int,
    *,
    fraction_driven: float = 1 / 6,
    n_frames: int,
    frame_interval_s: float,
    diffusion_um2_s: float,
    drift_um_s: float,
    seed: int,
    extent_um: float = 100.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Phantom of magnetically driven and free cells (Note S8.9's 1:5 mixture, Fig. 5h-j).

    Every cell does a 3D Brownian random walk with diffusion coefficient ``diffusion_um2_s``
    (per-axis step variance ``2 D dt``); driven cells also drift at ``drift_um_s`` along +x.
    Starting points are uniform in a cube of side ``extent_um``.

    Parameters
    ----------
    n_cells : int
        Number of cells N.
    fraction_driven : float
        Fraction of driven cells, rounded to a whole number (default 1/6, the 1:5 mixture).
    n_frames : int
        Frames T (>= 2).
    frame_interval_s : float
        Time between frames dt in s.
    diffusion_um2_s : float
        Diffusion coefficient D in um^2/s (>= 0).
    drift_um_s : float
        Drift speed of the driven cells in um/s.
    seed : int
        Seed of the random generator.
    extent_um : float
        Side of the cube of starting points in um.

    Returns
    -------
    positions : (N, T, 3) float64 array
        Positions ``(z, y, x)`` in um.
    driven : (N,) bool array
        True for the driven cells.
    """
    if n_cells < 1 or n_frames < 2 or not 0 <= fraction_driven <= 1 or diffusion_um2_s < 0:
        raise ValueError(
            "need n_cells >= 1, n_frames >= 2, 0 <= fraction_driven <= 1 and diffusion_um2_s >= 0"
        )
    dt = _positive(frame_interval_s, "frame_interval_s")
    rng = np.random.default_rng(seed)
    driven = np.zeros(n_cells, dtype=bool)
    driven[rng.permutation(n_cells)[: round(n_cells * fraction_driven)]] = True
    steps = rng.normal(scale=np.sqrt(2 * diffusion_um2_s * dt), size=(n_cells, n_frames - 1, 3))
    steps[driven, :, 2] += drift_um_s * dt
    start = rng.uniform(0, extent_um, size=(n_cells, 1, 3))
    walk = np.concatenate([np.zeros((n_cells, 1, 3)), np.cumsum(steps, axis=1)], axis=1)
    return start + walk, driven
