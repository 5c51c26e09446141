"""Lenslet centres from the data: a hexagonal-lattice fit for any lenslet count.

An FLFM image repeats itself from lenslet to lenslet, whether it is a brightfield image of the
MLA (bright disks) or the fluorescence image itself (the same field of view behind every lens),
so the lattice shows in the image's autocorrelation: its six strongest peaks around the origin
give the pitch and the rotation. The lattice's position is where the ``V`` lattice points of
fgat's view order (:func:`~fgat.optics.lenslets.hexagonal_offsets`) collect the most light;
each lenslet is then refined to the centroid of its own disk and the lattice is refitted to the
refined centres by least squares. Centres come back in fgat's view order, with each lens's
distance from the fitted lattice.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from fgat.optics.lenslets import hexagonal_offsets, lenslet_image, sort_lenslet_centers


@dataclass(frozen=True)
class HexLattice:
    """A hexagonal lenslet lattice on the camera.

    Attributes
    ----------
    center : (float, float)
        Centre of view 0 (row, col), pixels.
    pitch : float
        Distance between neighbouring lenslets, pixels.
    rotation_deg : float
        Rotation of the lattice in degrees in [-30, 30), counter-clockwise as the image is
        displayed (rows pointing down); 0: neighbours along the column axis.
    """

    center: tuple[float, float]
    pitch: float
    rotation_deg: float

    def centers(self, n_lenslets: int) -> np.ndarray:
        """``(V, 2)`` lattice points (row, col) of the first ``n_lenslets`` views, in view order."""
        offsets = hexagonal_offsets(n_lenslets, self.pitch)
        angle = math.radians(self.rotation_deg)
        cos, sin = math.cos(angle), math.sin(angle)
        # (col, -row) turns counter-clockwise by the rotation
        cols = cos * offsets[:, 1] + sin * offsets[:, 0]
        rows = -sin * offsets[:, 1] + cos * offsets[:, 0]
        return np.stack([rows, cols], axis=1) + np.asarray(self.center, dtype=np.float64)


@dataclass(frozen=True)
class LatticeFit:
    """Result of :func:`fit_hexagonal_lattice`.

    Attributes
    ----------
    lattice : HexLattice
        The lattice fitted to the refined centres.
    centers : numpy.ndarray
        ``(V, 2)`` refined lenslet centres (row, col), pixels, in view order.
    residuals : numpy.ndarray
        ``(V,)`` distance of each refined centre from its lattice point, pixels.
    missing : numpy.ndarray
        ``(V,)`` bool: lenslets found more than a fifth of the pitch off the lattice (dark or
        absent); their centres are the lattice points.
    """

    lattice: HexLattice
    centers: np.ndarray
    residuals: np.ndarray
    missing: np.ndarray


def lattice_pitch_and_rotation(
    image: np.ndarray, pitch_px: float | None = None
) -> tuple[float, float]:
    """Pitch (pixels) and rotation (degrees in [-30, 30)) of the hexagonal pattern of ``image``
    ``(H, W)`` from the six strongest peaks of its autocorrelation around the origin (searched
    between 0.7 and 1.3 times ``pitch_px`` when given)."""
    centred = image - image.mean()
    shape = (2 * image.shape[0], 2 * image.shape[1])
    spectrum = np.fft.rfft2(centred, s=shape)
    correlation = np.fft.fftshift(np.fft.irfft2(np.abs(spectrum) ** 2, s=shape))
    origin = np.array([image.shape[0], image.shape[1]], dtype=np.float64)
    peaks = np.argwhere(
        (correlation == ndimage.maximum_filter(correlation, size=5)) & (correlation > 0)
    ).astype(np.float64)
    offsets = peaks - origin
    distance = np.hypot(offsets[:, 0], offsets[:, 1])
    low, high = (
        (3.0, min(image.shape) / 2.0) if pitch_px is None else (0.7 * pitch_px, 1.3 * pitch_px)
    )
    keep = (distance >= low) & (distance <= high)
    if keep.sum() < 6:
        raise ValueError(
            "no hexagonal lattice in the image: fewer than six autocorrelation peaks around the "
            "origin (is the image an FLFM or MLA brightfield image?)"
        )
    offsets, distance = offsets[keep], distance[keep]
    strength = correlation[tuple((offsets + origin).astype(int).T)]
    nearest = np.argsort(-strength)[:6]
    pitch = float(np.median(distance[nearest]))
    angles = np.degrees(np.arctan2(-offsets[nearest, 0], offsets[nearest, 1]))
    # Mean of the six angles modulo 60 degrees (circular, so -29 and 29 average to -30/30).
    phase = np.angle(np.exp(1j * np.radians(angles) * 6.0).mean())
    rotation = math.degrees(phase) / 6.0
    return pitch, (rotation + 30.0) % 60.0 - 30.0


def _lattice_position(smooth: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """The pixel ``c`` (row, col) within a pitch of the light's centroid where the lattice
    points ``c + offsets`` ``(V, 2)`` collect the most of ``smooth``'s light."""
    steps = np.round(offsets).astype(int)
    reach = int(np.abs(steps).max()) + 1
    padded = np.pad(smooth, reach)
    score = np.zeros_like(smooth)
    for d_row, d_col in steps:
        score += padded[
            reach + d_row : reach + d_row + smooth.shape[0],
            reach + d_col : reach + d_col + smooth.shape[1],
        ]
    rows, cols = np.indices(smooth.shape)
    centroid = np.array([(rows * smooth).sum(), (cols * smooth).sum()]) / smooth.sum()
    pitch = np.median(np.linalg.norm(offsets[1:7] - offsets[0], axis=1)) if len(offsets) > 1 else 1
    near = (rows - centroid[0]) ** 2 + (cols - centroid[1]) ** 2 <= max(pitch, 2.0) ** 2
    index = np.argmax(np.where(near, score, -np.inf))
    return np.array(np.unravel_index(index, smooth.shape), dtype=np.float64)


def _crop(image: np.ndarray, center: np.ndarray, half: int) -> np.ndarray:
    """The ``(2 half + 1)^2`` patch around the integer pixel ``center``, edge-padded."""
    padded = np.pad(image, half, mode="edge")
    row, col = (int(v) + half for v in center)
    return padded[row - half : row + half + 1, col - half : col + half + 1]


def refine_centers(image: np.ndarray, points: np.ndarray, pitch: float) -> np.ndarray:
    """Sub-pixel lenslet centres ``(V, 2)`` near ``points``: every lenslet's patch is registered
    to the mean patch (cross-correlation, 1/20 px), and the mean patch's own centre is the
    intensity centroid above its half-maximum (the aperture disk of a brightfield image, the
    common field of view of a fluorescence one; a common offset of all views is equivalent to a
    lateral shift of the scene)."""
    from skimage.registration import phase_cross_correlation

    half = max(2, int(round(0.5 * pitch)))
    anchors = np.round(points).astype(int)
    patches = np.stack([_crop(image, anchor, half) for anchor in anchors])
    template = patches.mean(axis=0)
    level = (template.min() + template.max()) / 2.0
    weights = np.clip(template - level, 0, None)
    rows, cols = np.indices(template.shape)
    middle = np.array([(rows * weights).sum(), (cols * weights).sum()]) / weights.sum() - half
    reference = template - template.mean()
    shifts = np.array(
        [
            phase_cross_correlation(
                reference, patch - patch.mean(), upsample_factor=20, normalization=None
            )[0]
            for patch in patches
        ]
    )
    centers = anchors + middle - shifts
    if (template > level).mean() > 0.25:  # aperture disks (brightfield): their own centroids
        centers = np.array(
            [_disk_centroid(image, center, 0.5 * pitch, level) for center in centers]
        )
    return centers


def _disk_centroid(
    image: np.ndarray, center: np.ndarray, radius: float, level: float
) -> np.ndarray:
    """Centroid of the light above ``level`` within ``radius`` of ``center``, iterated three times
    (a bright aperture disk whose neighbours lie beyond ``radius``)."""
    for _ in range(3):
        low = np.maximum(np.floor(center - radius).astype(int), 0)
        high = np.minimum(np.ceil(center + radius).astype(int) + 1, image.shape)
        rows, cols = np.mgrid[low[0] : high[0], low[1] : high[1]]
        inside = (rows - center[0]) ** 2 + (cols - center[1]) ** 2 <= radius**2
        weights = np.where(
            inside, np.clip(image[low[0] : high[0], low[1] : high[1]] - level, 0, None), 0
        )
        if weights.sum() <= 0:
            return center
        center = np.array([(rows * weights).sum(), (cols * weights).sum()]) / weights.sum()
    return center


def _least_squares_lattice(centers: np.ndarray, n_lenslets: int, trusted: np.ndarray) -> HexLattice:
    """The lattice (centre, pitch, rotation) closest to the ``trusted`` ones of ``centers``
    ``(V, 2)`` in view order: a similarity transform of the unit hexagonal offsets, by linear
    least squares."""
    unit = hexagonal_offsets(n_lenslets, 1.0)
    # (row, col) = c + s [[cos, sin], [-sin, cos]] (row_u, col_u) in (col, -row) terms:
    # row = c_r + a row_u - b col_u, col = c_c + b row_u + a col_u, a = s cos, b = s sin
    design = np.zeros((2 * n_lenslets, 4))
    design[0::2] = np.column_stack(
        [np.ones(n_lenslets), np.zeros(n_lenslets), unit[:, 0], -unit[:, 1]]
    )
    design[1::2] = np.column_stack(
        [np.zeros(n_lenslets), np.ones(n_lenslets), unit[:, 1], unit[:, 0]]
    )
    rows = np.repeat(trusted, 2)
    (c_row, c_col, a, b), *_ = np.linalg.lstsq(design[rows], centers.reshape(-1)[rows], rcond=None)
    rotation = (math.degrees(math.atan2(b, a)) + 30.0) % 60.0 - 30.0
    return HexLattice((float(c_row), float(c_col)), float(math.hypot(a, b)), rotation)


def fit_hexagonal_lattice(image, n_lenslets: int, pitch_px: float | None = None) -> LatticeFit:
    """Fit a hexagonal lattice of ``n_lenslets`` lenslets to an FLFM or MLA brightfield image.

    Parameters
    ----------
    image : array-like
        ``(H, W)`` image, or ``(T, H, W)`` frames (summed), lenslets or their views brighter
        than the background.
    n_lenslets : int
        Lenslets of the MLA (7, 19, 37, ...; any count, taken in view order).
    pitch_px : float, optional
        Expected lenslet pitch in pixels (e.g. from the system), which narrows the search.

    Returns
    -------
    LatticeFit
        The lattice, the refined centres ``(V, 2)`` in view order, and their residuals.

    Raises
    ------
    ValueError
        A non-finite or constant image, or no hexagonal pattern in it.
    """
    image = lenslet_image(image, n_lenslets, "image", frames=True)
    pitch, rotation = lattice_pitch_and_rotation(image, pitch_px)
    smooth = ndimage.gaussian_filter(image, pitch / 4.0)
    best = _lattice_position(smooth, HexLattice((0.0, 0.0), pitch, rotation).centers(n_lenslets))
    lattice = HexLattice(tuple(best), pitch, rotation)
    centers = lattice.centers(n_lenslets)
    trusted = np.ones(n_lenslets, dtype=bool)
    for _ in range(3):
        refined = refine_centers(image, centers, pitch)
        lattice = _least_squares_lattice(refined, n_lenslets, trusted)
        centers = lattice.centers(n_lenslets)
        # far off the lattice: a dark or missing lenslet, not a displaced one (keeps its point)
        trusted = np.linalg.norm(refined - centers, axis=1) <= 0.2 * lattice.pitch
    refined[~trusted] = centers[~trusted]
    residuals = np.linalg.norm(refined - centers, axis=1)
    return LatticeFit(lattice, refined, residuals, ~trusted)


def write_calibration(fit: LatticeFit, folder, image: np.ndarray, source: str) -> dict:
    """Write a calibration folder: ``centers.csv`` (view order, row,col, 0-based),
    ``lattice.yaml`` (centre, pitch, rotation, per-view residuals and missing views, the image
    it came from) and ``overlay.png`` (the image with the lattice, each view's circle and
    number). Returns the paths by name."""
    from pathlib import Path

    import yaml

    from fgat.io import atomic_path
    from fgat.plots import plot_lenslet_overlay
    from fgat.simulation import write_centers

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = {name: folder / name for name in ("centers.csv", "lattice.yaml", "overlay.png")}
    write_centers(paths["centers.csv"], fit.centers)
    lattice = fit.lattice
    record = {
        "source": source,
        "n_lenslets": len(fit.centers),
        "center_px": [float(v) for v in lattice.center],
        "pitch_px": float(lattice.pitch),
        "rotation_deg": float(lattice.rotation_deg),
        "residuals_px": [round(float(r), 4) for r in fit.residuals],
        "missing_views": [int(v) for v in np.flatnonzero(fit.missing)],
        "view_order": "view 0 nearest the array centre, then ring by ring, counter-clockwise "
        "from +column as displayed (fgat.optics.lenslets)",
    }
    with atomic_path(paths["lattice.yaml"]) as temporary:
        temporary.write_text(yaml.safe_dump(record, sort_keys=False))
    plot_lenslet_overlay(image, fit.centers, 0.45 * lattice.pitch, paths["overlay.png"])
    return paths


def _lattice_misfit(centers: np.ndarray) -> np.ndarray:
    """``(V,)`` bool: centres more than a quarter pitch from a hexagonal lattice fitted to them
    in the order given."""
    lattice = _least_squares_lattice(centers, len(centers), np.ones(len(centers), dtype=bool))
    misfit = np.linalg.norm(centers - lattice.centers(len(centers)), axis=1)
    return misfit > 0.25 * max(lattice.pitch, 1e-9)


def check_view_order(centers: np.ndarray, source: str) -> None:
    """Raise ``ValueError`` naming ``source`` when the centres ``(V, 2)`` (row, col) form a
    hexagonal array listed in another order than fgat's view order (the order of every PSF stack
    fgat makes), which would pair each view with another lenslet's PSF. Centres that form no
    hexagonal array in any order are left to the checks of their geometry."""
    centers = np.asarray(centers, dtype=np.float64)
    if len(centers) < 3 or not _lattice_misfit(centers).any():
        return
    ordered = sort_lenslet_centers(centers)
    if _lattice_misfit(ordered).any():
        return
    v = int(np.flatnonzero(np.any(ordered != centers, axis=1))[0])
    view = int(np.flatnonzero(np.all(ordered == centers[v], axis=1))[0])
    raise ValueError(
        f"{source}: lenslet centres are not in fgat's view order: line {v + 1} "
        f"({centers[v, 0]:g}, {centers[v, 1]:g}) is view {view} (view 0 nearest the array "
        "centre, then ring by ring counter-clockwise from +column); 'python -m fgat calibrate' "
        "writes them in order"
    )
