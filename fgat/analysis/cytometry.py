"""Volumetric cytometry: 3D blob detection, marker classification of cells and the comparison
of class fractions with a reference count (Notes S8.7-S8.8, Fig. 5e-g, Fig. S14).

The workflow of Note S8.7: the nuclear channel is the pan-cell reference, its objects found by a
classical 3D blob detector (scikit-image's scale-normalised Laplacian of Gaussian with
anisotropic voxels); each marker channel's objects are found by the same detector with their own
threshold; every nucleus gets, per marker, a local background-corrected signal from the marker
object matched to it in space, a +/- call, and a class such as ``"CD11b-/Ferritin+"``. Note S8.8
compares the class fractions with flow cytometry by a chi-squared test of homogeneity and a
two-sided Fisher's exact test per class (:func:`compare_fractions`).

Volumes are ``(Z, Y, X)`` arrays; ``voxel_size_um`` is ``(dz, dy, dx)`` in micrometres, and voxel
``i``'s centre lies at ``(i + 0.5) * voxel_size`` (the convention of :func:`fgat.gaussians.
voxelize` with the origin at 0). Positions and sizes in tables are in micrometres.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import ndimage, stats
from scipy.spatial import cKDTree
from skimage.feature import blob_log

from fgat.analysis.scales import BALL_DIAMETER_PER_SIGMA, check_length_um
from fgat.sim.phantoms import KEPLER_DENSITY

AXES = ("z", "y", "x")
BLOB_COLUMNS = ("z", "y", "x", "sigma_z", "sigma_y", "sigma_x", "intensity")
"""Columns of :func:`detect_blobs`: centre (um), LoG scale per axis (um), normalised intensity."""

NORMALISATION_PERCENTILES = (50.0, 99.99)
"""Percentiles mapped to 0 and 1 by :func:`normalise` (background level, brightest structures)."""

BACKGROUND_SHELL = (1.5, 2.5)
"""Inner and outer radius of the local-background shell, in units of the marker object's radius."""


def _voxel_size(voxel_size_um) -> np.ndarray:
    size = np.asarray(voxel_size_um, dtype=np.float64)
    if size.shape != (3,) or not np.all(np.isfinite(size)) or np.any(size <= 0):
        raise ValueError(f"voxel_size_um must be three positive numbers (dz, dy, dx), got {size}")
    return size


def _check_volume(volume, name: str = "volume") -> np.ndarray:
    """``volume`` as a float64 ``(Z, Y, X)`` array, or ``ValueError`` naming ``name`` when it has
    the wrong dimensionality, non-finite values or no contrast (all zero or constant)."""
    volume = np.asarray(volume, dtype=np.float64)
    if volume.ndim != 3:
        raise ValueError(f"{name} must be a (Z, Y, X) volume, got shape {volume.shape}")
    if volume.size == 0 or not np.all(np.isfinite(volume)):
        raise ValueError(f"{name} must be non-empty and finite")
    if volume.max() == volume.min():
        raise ValueError(f"{name} is empty: every voxel is {volume.flat[0]:g}, nothing to detect")
    return volume


def normalise(volume: np.ndarray) -> np.ndarray:
    """Robust intensity normalisation: ``(volume - p50) / (p99.99 - p50)`` (the median as the
    background level, the 99.99th percentile as the brightest structures; the maximum when
    fewer than 0.01% of the voxels are above the median).

    Parameters
    ----------
    volume : ndarray
        ``(Z, Y, X)`` with some contrast.

    Returns
    -------
    ndarray
        ``(Z, Y, X)`` float64, background ~0, bright objects ~1 (not clipped).
    """
    low, high = np.percentile(volume, NORMALISATION_PERCENTILES)
    if high <= low:
        high = volume.max()
    return (volume - low) / (high - low)


def _refine(smooth: np.ndarray, index: np.ndarray) -> np.ndarray:
    """Sub-voxel centres ``(N, 3)`` (voxels) from a three-point parabola per axis through the
    smoothed volume at the integer peaks ``index`` ``(N, 3)`` (no shift on the border)."""
    refined = index.astype(np.float64)
    for axis in range(3):
        inside = (index[:, axis] > 0) & (index[:, axis] < smooth.shape[axis] - 1)
        step = np.zeros(3, dtype=int)
        step[axis] = 1
        centre = tuple(index[inside].T)
        minus = tuple((index[inside] - step).T)
        plus = tuple((index[inside] + step).T)
        curvature = smooth[minus] - 2 * smooth[centre] + smooth[plus]
        peaked = curvature < 0
        offset = np.zeros(len(curvature))
        offset[peaked] = 0.5 * (smooth[minus] - smooth[plus])[peaked] / curvature[peaked]
        refined[inside, axis] += np.clip(offset, -0.5, 0.5)
    return refined


def detect_blobs(
    volume: np.ndarray,
    *,
    voxel_size_um,
    sigma_um,
    threshold: float,
    scale_span: float = np.sqrt(2.0),
    num_sigma: int = 5,
) -> pd.DataFrame:
    """Bright 3D blobs by the scale-normalised Laplacian of Gaussian (the classical blob
    workflow of Note S8.7), with anisotropic voxels.

    The volume is first normalised robustly (:func:`normalise`); ``skimage.feature.blob_log``
    then scans ``num_sigma`` scales from ``sigma_um / scale_span`` to ``sigma_um * scale_span``
    (converted per axis to voxels, so a physically round blob is round in micrometres), keeps
    the scale-space maxima above ``threshold`` of the largest response (``threshold_rel``; the
    threshold is relative, so a channel's absolute brightness does not matter), prunes
    overlapping blobs and keeps blobs on the border (``exclude_border=False``). Centres are
    refined to sub-voxel precision by a parabola per axis through the volume smoothed at
    ``sigma_um``.

    Parameters
    ----------
    volume : ndarray
        ``(Z, Y, X)`` intensities.
    voxel_size_um : sequence of float
        ``(dz, dy, dx)`` in um.
    sigma_um : float or sequence of float
        Expected blob standard deviation in um (one value, or one per axis ``(z, y, x)``); a
        Gaussian blob of standard deviation ``s`` answers best at ``s``, a uniform ball of radius
        ``r`` at ``r / sqrt(3)``.
    threshold : float
        In ``(0, 1]``: the fraction of the volume's largest scale-normalised LoG response a blob
        must reach.
    scale_span : float
        Factor (> 1) between ``sigma_um`` and the smallest and largest scale searched.
    num_sigma : int
        Number of scales searched.

    Returns
    -------
    DataFrame
        One row per blob, brightest first, with columns :data:`BLOB_COLUMNS`: ``z, y, x`` the
        centre (um, voxel centres at ``(i + 0.5) * voxel_size``), ``sigma_z, sigma_y, sigma_x``
        the detected scale (um) and ``intensity`` the normalised volume at the centre voxel. No
        blobs give an empty table with these columns.

    Raises
    ------
    ValueError
        Wrong dimensionality, non-finite or constant (empty) volume, non-positive voxel sizes or
        sigmas, a threshold outside ``(0, 1]``.
    """
    volume = _check_volume(volume)
    voxel = _voxel_size(voxel_size_um)
    sigma = check_length_um(
        "sigma_um",
        sigma_um,
        voxel,
        volume.shape,
        diameter_per_value=BALL_DIAMETER_PER_SIGMA,
        axes="YX",
    )
    if not 0 < threshold <= 1:
        raise ValueError(f"threshold is relative and must be in (0, 1], got {threshold}")
    if not scale_span > 1 or int(num_sigma) < 1:
        raise ValueError(f"need scale_span > 1 and num_sigma >= 1, got {scale_span}, {num_sigma}")
    image = normalise(volume)
    sigma_voxels = sigma / voxel
    blobs = blob_log(
        image,
        min_sigma=tuple(sigma_voxels / scale_span),
        max_sigma=tuple(sigma_voxels * scale_span),
        num_sigma=int(num_sigma),
        threshold=None,
        threshold_rel=threshold,
        exclude_border=False,
    )
    if len(blobs) == 0:
        return pd.DataFrame({name: pd.Series(dtype=np.float64) for name in BLOB_COLUMNS})
    index = blobs[:, :3].astype(int)
    centres = _refine(ndimage.gaussian_filter(image, sigma_voxels), index)
    table = pd.DataFrame(
        np.column_stack(
            [
                (centres + 0.5) * voxel,
                blobs[:, 3:6] * voxel,
                image[tuple(index.T)],
            ]
        ),
        columns=list(BLOB_COLUMNS),
    )
    return table.sort_values("intensity", ascending=False, ignore_index=True)


def marker_classes(marker_names: Sequence[str]) -> list[str]:
    """All ``2 ** M`` class labels of ``M`` markers in the order of Note S8.5, e.g.
    ``["CD11b-/Ferritin-", "CD11b-/Ferritin+", "CD11b+/Ferritin-", "CD11b+/Ferritin+"]``."""
    return [
        _class_label(marker_names, signs)
        for signs in itertools.product((False, True), repeat=len(marker_names))
    ]


def _class_label(marker_names: Sequence[str], positive: Sequence[bool]) -> str:
    return "/".join(f"{name}{'+' if sign else '-'}" for name, sign in zip(marker_names, positive))


def _region(
    volume: np.ndarray,
    centre_um: np.ndarray,
    semi_axes_um: np.ndarray,
    voxel: np.ndarray,
    inner: float,
    outer: float,
) -> np.ndarray:
    """Values of ``volume`` whose voxel centres lie at normalised ellipsoidal radius
    ``inner <= rho < outer`` from ``centre_um`` (``rho = |(p - centre) / semi_axes|``)."""
    low = np.maximum(np.floor((centre_um - outer * semi_axes_um) / voxel - 0.5), 0).astype(int)
    high = np.minimum(
        np.ceil((centre_um + outer * semi_axes_um) / voxel - 0.5) + 1, volume.shape
    ).astype(int)
    axes = [
        ((np.arange(lo, hi) + 0.5) * v - c) / a
        for lo, hi, v, c, a in zip(low, high, voxel, centre_um, semi_axes_um)
    ]
    rho2 = axes[0][:, None, None] ** 2 + axes[1][None, :, None] ** 2 + axes[2][None, None, :] ** 2
    box = volume[low[0] : high[0], low[1] : high[1], low[2] : high[2]]
    return box[(rho2 >= inner**2) & (rho2 < outer**2)]


def _noise_level(image: np.ndarray) -> float:
    """Robust noise standard deviation of a normalised channel: 1.4826 times the median
    absolute deviation from the median (0 for a noise-free channel with a flat background)."""
    return float(1.4826 * np.median(np.abs(image - np.median(image))))


def _marker_signals(
    image: np.ndarray,
    nuclei_um: np.ndarray,
    objects: pd.DataFrame,
    voxel: np.ndarray,
    match_radius_um: float,
    background_percentile: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Per nucleus ``(N,)``: whether a marker object lies within ``match_radius_um`` and the
    background-corrected signal of the nearest one (NaN when none)."""
    matched = np.zeros(len(nuclei_um), dtype=bool)
    signal = np.full(len(nuclei_um), np.nan)
    if len(objects) == 0 or len(nuclei_um) == 0:
        return matched, signal
    distance, nearest = cKDTree(objects[list(AXES)].to_numpy()).query(nuclei_um)
    matched = distance <= match_radius_um
    for i in np.flatnonzero(matched):
        obj = objects.iloc[nearest[i]]
        centre = obj[list(AXES)].to_numpy(dtype=np.float64)
        semi_axes = np.maximum(
            np.sqrt(3.0) * obj[["sigma_z", "sigma_y", "sigma_x"]].to_numpy(np.float64), voxel
        )
        inside = _region(image, centre, semi_axes, voxel, 0.0, 1.0)
        shell = _region(image, nuclei_um[i], semi_axes, voxel, *BACKGROUND_SHELL)
        background = np.percentile(shell, background_percentile) if shell.size else 0.0
        signal[i] = inside.mean() - background
    return matched, signal


def classify_cells(
    nuclei: np.ndarray,
    markers: Mapping[str, np.ndarray],
    *,
    voxel_size_um,
    sigma_um,
    thresholds: Mapping[str, float],
    match_radius_um: float,
    nucleus_threshold: float = 0.2,
    marker_sigma_um=None,
    background_percentile: float = 10.0,
    min_snr: float = 3.0,
) -> pd.DataFrame:
    """Single-cell marker classification in 3D (Note S8.7, Fig. 5e-f).

    1. Nuclei are detected in ``nuclei`` (the pan-cell reference) by :func:`detect_blobs` with
       ``sigma_um`` and ``nucleus_threshold``.
    2. Each marker channel's objects are detected by :func:`detect_blobs` with
       ``marker_sigma_um`` (one value for all markers or one per marker name; default
       ``sigma_um``) and the channel's own ``thresholds[name]``.
    3. Each nucleus is matched to the nearest marker object whose centre lies within
       ``match_radius_um`` (a k-d tree in um).
    4. The signal of a matched object is the mean of the normalised marker channel
       (:func:`normalise`) inside the object's ellipsoid (semi-axes ``sqrt(3)`` times its LoG
       scale per axis, at least one voxel: the radius of a uniform ball) minus the local
       background, the ``background_percentile``-th percentile of the channel in an ellipsoidal
       shell around the nucleus between :data:`BACKGROUND_SHELL` times those semi-axes (a low
       percentile so that touching neighbours do not raise it).
    5. A cell is positive for a marker iff it has a matched object and its signal exceeds
       ``min_snr`` times the channel's robust noise level (1.4826 x MAD of the normalised
       channel; the floor is 0 for noise-free channels, where a positive signal suffices).

    Parameters
    ----------
    nuclei : ndarray
        ``(Z, Y, X)`` nuclear channel.
    markers : mapping of str to ndarray
        Marker name -> ``(Z, Y, X)`` channel of the same shape; the class label follows its order.
    voxel_size_um : sequence of float
        ``(dz, dy, dx)`` in um.
    sigma_um : float or sequence of float
        Expected nucleus blob standard deviation (um), see :func:`detect_blobs`.
    thresholds : mapping of str to float
        Relative detection threshold per marker name (see :func:`detect_blobs`).
    match_radius_um : float
        Largest nucleus-to-marker-object distance (um) for a match; keep it below the smallest
        distance between cell centres.
    nucleus_threshold : float
        Relative detection threshold of the nuclei.
    marker_sigma_um : float, sequence of float or mapping, optional
        Expected marker-object standard deviation (um); for a cell-sized object of radius ``R``
        about ``R / sqrt(3)`` (a uniform ball) to ``0.7 R`` (a ball with a bright membrane rim;
        a hollow shell alone answers on its rim, not at its centre).
    background_percentile : float
        Percentile of the background shell taken as the local background.
    min_snr : float
        Signal floor in units of the channel's noise level.

    Returns
    -------
    DataFrame
        One row per detected nucleus: ``nucleus`` (id), ``z, y, x`` (um), then per marker
        ``{name}_matched`` (bool), ``{name}_signal`` (normalised units; NaN when unmatched),
        ``{name}_positive`` (bool), and ``class`` (e.g. ``"CD11b-/Ferritin+"``).

    Raises
    ------
    ValueError
        No markers, channels of other shapes, missing thresholds, or any error of
        :func:`detect_blobs` (naming the channel).
    """
    names = list(markers)
    if not names:
        raise ValueError("markers must name at least one marker channel")
    if set(thresholds) != set(names):
        raise ValueError(
            f"thresholds must have one entry per marker {names}, got {list(thresholds)}"
        )
    if not match_radius_um > 0:
        raise ValueError(f"match_radius_um must be positive, got {match_radius_um}")
    nuclei = _check_volume(nuclei, "nuclei")
    channels = {name: _check_volume(markers[name], f"marker {name!r}") for name in names}
    for name, channel in channels.items():
        if channel.shape != nuclei.shape:
            raise ValueError(
                f"marker {name!r} has shape {channel.shape}, the nuclei {nuclei.shape}"
            )
    voxel = _voxel_size(voxel_size_um)
    check_length_um(
        "match_radius_um", match_radius_um, voxel, nuclei.shape, min_voxels=0, axes="YX"
    )
    found = detect_blobs(
        nuclei, voxel_size_um=voxel, sigma_um=sigma_um, threshold=nucleus_threshold
    )
    centres = found[list(AXES)].to_numpy()
    table = pd.DataFrame({"nucleus": np.arange(len(found))}).join(found[list(AXES)])
    for name, channel in channels.items():
        sigma = (
            marker_sigma_um.get(name) if isinstance(marker_sigma_um, Mapping) else marker_sigma_um
        )
        objects = detect_blobs(
            channel,
            voxel_size_um=voxel,
            sigma_um=sigma_um if sigma is None else sigma,
            threshold=thresholds[name],
        )
        image = normalise(channel)
        matched, signal = _marker_signals(
            image, centres, objects, voxel, match_radius_um, background_percentile
        )
        table[f"{name}_matched"] = matched
        table[f"{name}_signal"] = signal
        table[f"{name}_positive"] = matched & (
            np.nan_to_num(signal, nan=-np.inf) > max(min_snr * _noise_level(image), 0.0)
        )
    positives = table[[f"{name}_positive" for name in names]].to_numpy()
    table["class"] = [_class_label(names, row) for row in positives]
    return table


@dataclass(frozen=True)
class FractionComparison:
    """Class fractions against a reference count (Note S8.8, Fig. 5g).

    Attributes
    ----------
    classes : tuple
        The ``K`` classes (the dict keys, or ``0..K-1`` for sequences).
    counts, reference_counts : ndarray
        ``(K,)`` int counts.
    fractions, reference_fractions : ndarray
        ``(K,)`` counts over their totals.
    chi2, chi2_dof, chi2_pvalue : float, int, float
        Chi-squared test of homogeneity on the ``2 x K`` table.
    fisher_odds_ratios, fisher_pvalues : ndarray
        ``(K,)`` two-sided Fisher's exact test of each class against the rest.
    """

    classes: tuple
    counts: np.ndarray
    reference_counts: np.ndarray
    fractions: np.ndarray
    reference_fractions: np.ndarray
    chi2: float
    chi2_dof: int
    chi2_pvalue: float
    fisher_odds_ratios: np.ndarray
    fisher_pvalues: np.ndarray


def _counts(values, name: str) -> np.ndarray:
    counts = np.asarray(values, dtype=np.float64)
    if counts.ndim != 1 or not np.all(np.isfinite(counts)):
        raise ValueError(f"{name} must be a flat sequence of finite counts, got {values!r}")
    if np.any(counts < 0) or np.any(counts != np.round(counts)):
        raise ValueError(f"{name} must be non-negative whole numbers, got {values!r}")
    if counts.sum() == 0:
        raise ValueError(f"{name} has a zero total")
    return counts.astype(np.int64)


def _aligned(counts, reference_counts) -> tuple[tuple, np.ndarray, np.ndarray]:
    """The classes and both count vectors in one class order, or ``ValueError``."""
    if isinstance(counts, Mapping) != isinstance(reference_counts, Mapping):
        raise ValueError("counts and reference_counts must both be dicts or both be sequences")
    if isinstance(counts, Mapping):
        if set(counts) != set(reference_counts):
            raise ValueError(
                f"counts and reference_counts name different classes: {sorted(map(str, counts))} "
                f"vs {sorted(map(str, reference_counts))}"
            )
        classes = tuple(counts)
        values = [counts[c] for c in classes], [reference_counts[c] for c in classes]
    else:
        values = list(counts), list(reference_counts)
        if len(values[0]) != len(values[1]):
            raise ValueError(
                f"counts has {len(values[0])} classes, reference_counts {len(values[1])}"
            )
        classes = tuple(range(len(values[0])))
    if len(classes) < 2:
        raise ValueError(f"need at least two classes to compare fractions, got {len(classes)}")
    return classes, _counts(values[0], "counts"), _counts(values[1], "reference_counts")


def compare_fractions(counts, reference_counts) -> FractionComparison:
    """Compare class fractions with a reference count (Note S8.8: the overall chi-squared test and
    the two-sided per-class Fisher's exact tests of Fig. 5g).

    The chi-squared test of homogeneity is ``scipy.stats.chi2_contingency`` on the ``2 x K``
    table ``[counts, reference_counts]`` with its default ``correction=True`` (Yates' continuity
    correction, which scipy applies only when the table has one degree of freedom, i.e.
    ``K = 2``). Classes with zero counts in both rows carry no information and are left out of
    that table (scipy cannot form their expected frequencies); if fewer than two classes remain
    the samples agree trivially and ``chi2_pvalue`` is 1. Each class ``k`` is also tested
    against the rest by ``scipy.stats.fisher_exact`` (two-sided) on
    ``[[count_k, total - count_k], [ref_k, ref_total - ref_k]]``.

    Parameters
    ----------
    counts, reference_counts : dict or sequence
        Class -> count dicts with the same keys (in ``counts``' order), or two sequences of
        ``K`` counts in the same class order; non-negative whole numbers, non-zero totals.

    Returns
    -------
    FractionComparison

    Raises
    ------
    ValueError
        Negative or fractional counts, mismatched classes, fewer than two classes, zero totals.
    """
    classes, counts, reference = _aligned(counts, reference_counts)
    table = np.stack([counts, reference])
    informative = table.sum(axis=0) > 0
    if informative.sum() >= 2:
        chi2 = stats.chi2_contingency(table[:, informative], correction=True)
        statistic, dof, pvalue = float(chi2.statistic), int(chi2.dof), float(chi2.pvalue)
    else:
        statistic, dof, pvalue = 0.0, 0, 1.0
    fisher = [
        stats.fisher_exact(
            [[c, counts.sum() - c], [r, reference.sum() - r]], alternative="two-sided"
        )
        for c, r in zip(counts, reference)
    ]
    return FractionComparison(
        classes=classes,
        counts=counts,
        reference_counts=reference,
        fractions=counts / counts.sum(),
        reference_fractions=reference / reference.sum(),
        chi2=statistic,
        chi2_dof=dof,
        chi2_pvalue=pvalue,
        fisher_odds_ratios=np.array([float(f.statistic) for f in fisher]),
        fisher_pvalues=np.array([float(f.pvalue) for f in fisher]),
    )


def _class_sizes(n_cells: int, class_ratio: Sequence[float], n_classes: int) -> np.ndarray:
    """Cells per class ``(K,)`` summing to ``n_cells`` in proportion to ``class_ratio`` (largest
    remainders)."""
    ratio = np.asarray(class_ratio, dtype=np.float64)
    if ratio.shape != (n_classes,) or np.any(ratio < 0) or not ratio.sum() > 0:
        raise ValueError(
            f"class_ratio needs {n_classes} non-negative weights, not all 0; got {class_ratio!r}"
        )
    exact = n_cells * ratio / ratio.sum()
    sizes = np.floor(exact).astype(int)
    sizes[np.argsort(sizes - exact)[: n_cells - sizes.sum()]] += 1
    return sizes


def _cell_centres(
    extent_um: np.ndarray, n_cells: int, margin_um: float, spacing_um: float, rng
) -> np.ndarray:
    """``(N, 3)`` random centres (um) at least ``spacing_um`` apart and ``margin_um`` from the
    border, by rejection sampling (1000 draws per cell at most). Requests beyond the densest
    packing of spheres of diameter ``spacing_um`` in the region are refused before sampling."""
    room = extent_um - 2 * margin_um
    fit = KEPLER_DENSITY * np.prod(room + spacing_um) / (np.pi * spacing_um**3 / 6)
    if np.any(room <= 0) or n_cells > fit:
        raise ValueError(
            f"{n_cells} non-overlapping cells of radius {margin_um} um cannot fit in "
            f"{extent_um} um; lower n_cells or the cell radius"
        )
    centres = np.empty((n_cells, 3))
    placed = 0
    for _ in range(1000 * n_cells):
        candidate = rng.uniform(margin_um, extent_um - margin_um)
        if placed == 0 or np.linalg.norm(centres[:placed] - candidate, axis=1).min() >= spacing_um:
            centres[placed] = candidate
            placed += 1
            if placed == n_cells:
                return centres
    raise ValueError(
        f"could not place {n_cells} non-overlapping cells of radius {margin_um} um in "
        f"{extent_um} um (placed {placed}); lower n_cells or the cell radius"
    )


def _distance_um(shape, voxel: np.ndarray, centre_um: np.ndarray) -> np.ndarray:
    """``(Z, Y, X)`` distance (um) of every voxel centre from ``centre_um``."""
    axes = [(np.arange(n) + 0.5) * v - c for n, v, c in zip(shape, voxel, centre_um)]
    return np.sqrt(axes[0][:, None, None] ** 2 + axes[1][None, :, None] ** 2 + axes[2] ** 2)


def cell_phantom(
    shape: Sequence[int],
    *,
    voxel_size_um,
    n_cells: int,
    marker_names: Sequence[str] = ("CD11b", "Ferritin"),
    class_ratio: Sequence[float] = (1, 1, 1, 1),
    nucleus_radius_um: float,
    cell_radius_um: float,
    seed: int,
    marker_layout: str | Sequence[str] = ("membrane", "cytoplasm"),
    background: float = 0.0,
    noise_std: float = 0.0,
) -> tuple[dict[str, np.ndarray], pd.DataFrame]:
    """Multichannel cytometry phantom with a known class per cell (Notes S8.5, S8.7).

    Cells sit at random non-overlapping positions (centres at least ``2 * cell_radius_um``
    apart and ``cell_radius_um`` from the border). Every cell has a nucleus, a Gaussian ball of
    standard deviation ``nucleus_radius_um / 2`` and peak 1 in the ``"nuclei"`` channel. Each
    marker a cell is positive for adds, in that marker's channel, a ``"cytoplasm"`` (a uniform
    ball of value 0.6 and the cell radius, tanh edge of width ``cell_radius_um / 8``) or a
    ``"membrane"`` (that ball plus a rim of peak 0.4 at the cell radius, Gaussian profile of
    standard deviation ``cell_radius_um / 8``: a surface stain seen with the cell's diffuse
    signal; a bare shell would be detected on its rim). The classes, in the order of
    :func:`marker_classes`, get cell numbers in proportion to ``class_ratio`` (largest
    remainders), shuffled over the positions. Every channel then gets ``background`` added
    and Gaussian noise of standard deviation ``noise_std``.

    Parameters
    ----------
    shape : sequence of int
        ``(Z, Y, X)`` voxels.
    voxel_size_um : sequence of float
        ``(dz, dy, dx)`` in um.
    n_cells : int
        Number of cells.
    marker_names : sequence of str
        The markers (channel names).
    class_ratio : sequence of float
        ``2 ** M`` weights of the classes of :func:`marker_classes`.
    nucleus_radius_um, cell_radius_um : float
        Nucleus and cell radii in um (nucleus smaller than the cell).
    seed : int
        Seed of the random positions, class assignment and noise.
    marker_layout : str or sequence of str
        ``"membrane"`` or ``"cytoplasm"`` for all markers or one per marker.
    background, noise_std : float
        Additive background level and Gaussian noise standard deviation of every channel.

    Returns
    -------
    channels : dict of str to ndarray
        ``"nuclei"`` and each marker name -> ``(Z, Y, X)`` float32.
    truth : DataFrame
        One row per cell: ``cell``, ``z, y, x`` (um), ``{name}_positive`` per marker and
        ``class``.
    """
    shape = tuple(int(n) for n in shape)
    voxel = _voxel_size(voxel_size_um)
    names = list(marker_names)
    layouts = (
        [marker_layout] * len(names) if isinstance(marker_layout, str) else list(marker_layout)
    )
    if len(shape) != 3 or min(shape) < 1 or not names or len(layouts) != len(names):
        raise ValueError(
            f"need a (Z, Y, X) shape, at least one marker and one layout per marker; got shape "
            f"{shape}, markers {names}, layouts {layouts}"
        )
    if not set(layouts) <= {"membrane", "cytoplasm"}:
        raise ValueError(f"marker_layout must be 'membrane' or 'cytoplasm', got {layouts}")
    if not 0 < nucleus_radius_um < cell_radius_um or n_cells < 1 or noise_std < 0:
        raise ValueError(
            "need 0 < nucleus_radius_um < cell_radius_um, n_cells >= 1 and noise_std >= 0"
        )
    rng = np.random.default_rng(seed)
    sizes = _class_sizes(n_cells, class_ratio, 2 ** len(names))
    centres = _cell_centres(
        np.asarray(shape) * voxel, n_cells, cell_radius_um, 2 * cell_radius_um, rng
    )
    signs = np.array(list(itertools.product((False, True), repeat=len(names))))
    cell_signs = signs[rng.permutation(np.repeat(np.arange(len(sizes)), sizes))]
    channels = {name: np.zeros(shape) for name in ["nuclei", *names]}
    edge = cell_radius_um / 8
    for centre, positive in zip(centres, cell_signs):
        distance = _distance_um(shape, voxel, centre)
        channels["nuclei"] += np.exp(-0.5 * (distance / (nucleus_radius_um / 2)) ** 2)
        for name, layout, sign in zip(names, layouts, positive):
            if sign:
                channels[name] += 0.3 * (1 - np.tanh((distance - cell_radius_um) / edge))
            if sign and layout == "membrane":
                channels[name] += 0.4 * np.exp(-0.5 * ((distance - cell_radius_um) / edge) ** 2)
    for name in channels:
        noise = rng.normal(0.0, noise_std, shape) if noise_std > 0 else 0.0
        channels[name] = (channels[name] + background + noise).astype(np.float32)
    truth = pd.DataFrame(centres, columns=list(AXES))
    truth.insert(0, "cell", np.arange(n_cells))
    for name, column in zip(names, cell_signs.T):
        truth[f"{name}_positive"] = column
    truth["class"] = [_class_label(names, row) for row in cell_signs]
    return channels, truth
