"""Lenslet lattice fitting on a calibration image: a hexagonal lattice (centre, pitch,
rotation) fitted to the view centres, refined centres, the fit's quality and its
agreement with a named optics system.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from fgat._core.resources import check_memory
from fgat.instrument.camera import dark_background
from fgat.optics.lenslets import (
    hexagonal_offsets,
    lattice_points,
    lenslet_image,
)
from fgat.optics.spec import OpticsSpec
from fgat.optics.systems import MLA_ORIENTATIONS, PITCH_CONVENTIONS


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
        Rotation of the lattice in degrees, counter-clockwise as the image is displayed (rows
        pointing down); 0: neighbours along the column axis. Fitted lattices are in [-30, 30)
        (up to the last refinement's step past +-30 degrees), or within 30 degrees of their
        system's rotation (:func:`number_like`).
    """

    center: tuple[float, float]
    pitch: float
    rotation_deg: float

    def centers(self, n_lenslets: int) -> np.ndarray:
        """``(V, 2)`` lattice points (row, col) of the first ``n_lenslets`` views, in view order."""
        return lattice_points(n_lenslets, self.pitch, self.rotation_deg, self.center)

    def cells(self, n_lenslets: int) -> np.ndarray:
        """``(V, 6, 2)`` corners (row, col) of the hexagonal cells of the first ``n_lenslets``
        views, in view order: each lattice point's Voronoi cell, a regular hexagon of
        circumradius ``pitch / sqrt(3)`` with its corners at 30 + 60 k degrees from the
        neighbour directions (counter-clockwise as displayed), so neighbouring cells share an
        edge at ``pitch / 2`` from both centres."""
        angles = np.radians(self.rotation_deg + 30.0 + 60.0 * np.arange(6))
        radius = self.pitch / math.sqrt(3.0)
        corners = radius * np.stack([-np.sin(angles), np.cos(angles)], axis=1)  # (row, col)
        return self.centers(n_lenslets)[:, None, :] + corners[None]


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
    brightfield : bool
        The image showed the lenslet apertures (a white-light MLA image), whose centroids fix the
        centres absolutely. Otherwise (a fluorescence image) the views' contents fix them only up
        to where the sample is: a common shift of all centres (the sample's mean lateral
        position) and a common radial scale about the axis (the parallax of its mean depth),
        which move the reconstructed volume by as much; per-lens offsets within that are the
        lenslet shifts the fit estimates (``optics.estimate: shifts``).
    """

    lattice: HexLattice
    centers: np.ndarray
    residuals: np.ndarray
    missing: np.ndarray
    brightfield: bool


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
    """The ``(2 half + 1)^2`` patch around the integer pixel ``center`` (moved onto the image
    when it lies off it: a lattice point off the sensor), edge-padded."""
    padded = np.pad(image, half, mode="edge")
    row, col = (int(np.clip(v, 0, n - 1)) + half for v, n in zip(center, image.shape))
    return padded[row - half : row + half + 1, col - half : col + half + 1]


def refine_centers(image: np.ndarray, points: np.ndarray, pitch: float) -> tuple[np.ndarray, bool]:
    """Sub-pixel lenslet centres ``(V, 2)`` near ``points``: every lenslet's patch is registered
    to the mean patch (cross-correlation, 1/20 px), and the mean patch's own centre is the
    intensity centroid above its half-maximum (the aperture disk of a brightfield image, the
    common field of view of a fluorescence one; a common offset of all views is equivalent to a
    lateral shift of the scene). Also returns whether the patches are aperture disks (more than
    a quarter of the mean patch above its half-maximum: a brightfield image), whose own
    centroids then give the centres."""
    from skimage.registration import (  # scikit-image loaded when used: keeps start-up fast
        phase_cross_correlation,
    )

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
    brightfield = bool((template > level).mean() > 0.25)
    if brightfield:
        centers = np.array(
            [_disk_centroid(image, center, 0.5 * pitch, level) for center in centers]
        )
    return centers, brightfield


def _disk_centroid(
    image: np.ndarray, center: np.ndarray, radius: float, level: float
) -> np.ndarray:
    """Centroid of the light above ``level`` within ``radius`` of ``center``, iterated three times
    (a bright aperture disk whose neighbours lie beyond ``radius``)."""
    for _ in range(3):
        low = np.maximum(np.floor(center - radius).astype(int), 0)
        high = np.minimum(np.ceil(center + radius).astype(int) + 1, image.shape)
        if (high <= low).any():  # off the image
            return center
        rows, cols = np.mgrid[low[0] : high[0], low[1] : high[1]]
        inside = (rows - center[0]) ** 2 + (cols - center[1]) ** 2 <= radius**2
        weights = np.where(
            inside, np.clip(image[low[0] : high[0], low[1] : high[1]] - level, 0, None), 0
        )
        if weights.sum() <= 0:
            return center
        center = np.array([(rows * weights).sum(), (cols * weights).sum()]) / weights.sum()
    return center


def least_squares_lattice(centers: np.ndarray, n_lenslets: int, trusted: np.ndarray) -> HexLattice:
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
    # Not wrapped into [-30, 30): the centres keep the numbering they came in, also near 30.
    rotation = math.degrees(math.atan2(b, a))
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
        A non-finite or constant image, no hexagonal pattern in it, more lenslets than the image
        holds (:func:`check_lenslet_count`), an array at the image's pitch of which less than
        :data:`MIN_VIEWS_FOUND` can lie on the image, or a fit larger than the memory.
    """
    image = lenslet_image(image, n_lenslets, "image", frames=True)
    check_lenslet_count(n_lenslets, image.shape)
    pitch, rotation = lattice_pitch_and_rotation(image, pitch_px)
    fitting = _views_fitting(image.shape, n_lenslets, pitch, rotation)
    if fitting < MIN_VIEWS_FOUND * n_lenslets:
        raise ValueError(
            f"{n_lenslets} lenslets {pitch:.1f} px apart (the image's lattice pitch) do not fit "
            f"on the {image.shape[0]} x {image.shape[1]} image: at most {fitting} of the "
            f"{n_lenslets} expected views can lie on it (share {fitting / n_lenslets:.2f}, at "
            f"least {MIN_VIEWS_FOUND:g} needed); is the lenslet count right?"
        )
    check_memory(
        f"the fit of {n_lenslets} lenslets {pitch:.1f} px apart",
        _fit_memory(image.shape, n_lenslets, pitch),
        hint="fewer lenslets",
    )
    smooth = ndimage.gaussian_filter(image, pitch / 4.0)
    best = _lattice_position(smooth, HexLattice((0.0, 0.0), pitch, rotation).centers(n_lenslets))
    lattice = HexLattice(tuple(best), pitch, rotation)
    centers = lattice.centers(n_lenslets)
    trusted = np.ones(n_lenslets, dtype=bool)
    for _ in range(3):
        refined, brightfield = refine_centers(image, centers, pitch)
        lattice = least_squares_lattice(refined, n_lenslets, trusted)
        centers = lattice.centers(n_lenslets)
        # far off the lattice: a dark or missing lenslet, not a displaced one (keeps its point)
        trusted = np.linalg.norm(refined - centers, axis=1) <= 0.2 * lattice.pitch
    refined[~trusted] = centers[~trusted]
    residuals = np.linalg.norm(refined - centers, axis=1)
    return LatticeFit(lattice, refined, residuals, ~trusted, brightfield)


MIN_LENSLET_PITCH_PX = 5.0
"""Smallest lenslet pitch (pixels) a lattice fit can resolve: each lenslet is refined on a patch
of at least 5 x 5 pixels, and the autocorrelation search starts at 3 px. ``n`` lenslets need
``n sqrt(3) / 2 MIN_LENSLET_PITCH_PX^2`` pixels (a hexagonal cell each) of the image."""


def check_lenslet_count(n_lenslets: int, shape: tuple[int, int], name: str = "n_lenslets") -> None:
    """Refuse, naming ``name``, more lenslets than an image of ``shape`` ``(H, W)`` can hold at
    the smallest pitch :data:`MIN_LENSLET_PITCH_PX` (one hexagonal cell of
    ``sqrt(3) / 2 pitch^2`` pixels each), before anything is allocated for them."""
    cell = math.sqrt(3.0) / 2.0 * MIN_LENSLET_PITCH_PX**2
    most = int(shape[0] * shape[1] // cell)
    if n_lenslets > most:
        raise ValueError(
            f"{name} {n_lenslets}: {n_lenslets} lenslets of at least {MIN_LENSLET_PITCH_PX:g} px "
            f"pitch need {n_lenslets * cell:.3g} px ({cell:.1f} px each), but the image is "
            f"{shape[0]} x {shape[1]} = {shape[0] * shape[1]} px: at most {most} lenslets fit"
        )


def _views_fitting(shape: tuple[int, int], n_lenslets: int, pitch: float, rotation: float) -> int:
    """The most of ``n_lenslets`` lattice points ``pitch`` px apart, turned by ``rotation``
    degrees, that lie on an ``(H, W)`` image, over positions of view 0 on a 21 x 21 grid
    spanning the image."""
    offsets = lattice_points(n_lenslets, pitch, rotation)
    if (np.ptp(offsets, axis=0) <= np.array(shape) - 1).all():
        return n_lenslets  # the whole array fits
    high = np.array(shape, dtype=np.float64) - 0.5
    most = 0
    for row in np.linspace(0.0, shape[0] - 1.0, 21):
        for col in np.linspace(0.0, shape[1] - 1.0, 21):
            points = offsets + (row, col)
            most = max(most, int(((points >= -0.5) & (points <= high)).all(axis=1).sum()))
    return most


def _fit_memory(shape: tuple[int, int], n_lenslets: int, pitch: float) -> int:
    """Bytes :func:`fit_hexagonal_lattice` holds at its peak for ``n_lenslets`` lenslets
    ``pitch`` px apart on an ``(H, W)`` image: the smoothed image padded by the array's radius
    (:func:`_lattice_position`), a few image-sized arrays and two stacks of lenslet patches
    (:func:`refine_centers`), float64."""
    reach = int(np.abs(hexagonal_offsets(n_lenslets, pitch)).max()) + 2
    patch = (2 * max(2, int(round(0.5 * pitch))) + 1) ** 2
    padded = (shape[0] + 2 * reach) * (shape[1] + 2 * reach)
    return 8 * (padded + 4 * shape[0] * shape[1] + 2 * n_lenslets * patch)


MIN_VIEW_CONTRAST = 7.0
"""Smallest contrast (:func:`view_contrast`) at which a lenslet counts as found, in standard
deviations of the background noise after a 1-px Gaussian smoothing. The brightest smoothed pixel
of pure noise over a view's disk (0.4 pitch) stands 3-5 noise standard deviations above the
background (the extreme of 10^2-10^4 independent samples; skewed low-count Poisson noise
rarely reaches 6); the centres of views fainter than about 7 scatter by pixels, while an
aperture disk of a white-light image, or a bead of a few hundred photons in a fluorescence
view, stands tens to thousands above."""
MIN_VIEWS_FOUND = 0.8
"""Smallest share of the expected views that must be found (bright, :data:`MIN_VIEW_CONTRAST`,
and on the lattice, within a fifth of the pitch) for ``python -m fgat calibrate`` to accept the
fit: a lattice fitted to fewer is not that array (a lenslet count larger than the image's, or
noise), and every view not found would be modelled without its light; one dark or blocked lens
in five is tolerated and reported."""
MAX_RESIDUAL_RMS = 0.1
"""Largest RMS distance of the found centres from the fitted lattice, as a fraction of the
pitch: an MLA is made to micrometres (residuals of a few per cent of the pitch, the fit's own
error 0.01 pitch), and a lens more than 0.2 pitch off is not counted as found; a spread beyond
0.1 pitch is no hexagonal array."""
VIEW_RADIUS = 0.4
"""Radius (pitches) of the disk around each lattice point whose brightest pixel is the view's
peak in :func:`view_contrast`."""
CONTRAST_SMOOTHING_PX = 1.0
"""Standard deviation (pixels) of the Gaussian that smooths the image before the contrast is
measured: about a Nyquist-sampled PSF's, which keeps a bead's peak and averages a pixel's
noise over about 12 pixels."""


def view_contrast(image, points: np.ndarray, pitch: float, hot_pixels=None) -> np.ndarray:
    """Contrast of each view ``(V,)``: the brightest pixel within :data:`VIEW_RADIUS` pitch of
    its lattice point ``points`` ``(V, 2)`` (row, col), less the background level, over the
    background noise, in the ``image`` ``(H, W)`` smoothed by :data:`CONTRAST_SMOOTHING_PX`.

    The background is the smoothed image's dark region
    (:func:`~fgat.instrument.camera.dark_background`: the gaps between the views and the sensor's
    corners of an FLFM image, most of an image of noise), found without the lattice, so that a wrong
    lattice cannot bias it. Pixels marked in
    ``hot_pixels`` ``(H, W)`` are replaced by the median of their 3 x 3 neighbours first, so that
    a hot pixel is no view. A view without pixels on the image has contrast 0; a noise-free
    background gives ``inf`` for views brighter than it.
    """
    image = np.asarray(image, dtype=np.float64)
    if hot_pixels is not None:
        image = np.where(hot_pixels, ndimage.median_filter(image, size=3, mode="mirror"), image)
    smooth = ndimage.gaussian_filter(image, CONTRAST_SMOOTHING_PX)
    level, noise = dark_background(smooth)
    radius = VIEW_RADIUS * pitch
    peaks = []
    for center in np.asarray(points, dtype=np.float64):
        low = np.maximum(np.floor(center - radius).astype(int), 0)
        high = np.maximum(np.minimum(np.ceil(center + radius).astype(int) + 1, image.shape), low)
        rows, cols = np.mgrid[low[0] : high[0], low[1] : high[1]]
        disk = (rows - center[0]) ** 2 + (cols - center[1]) ** 2 <= radius**2
        window = smooth[low[0] : high[0], low[1] : high[1]]
        peaks.append(float(window[disk].max()) if disk.any() else level)  # off the image: 0
    excess = np.clip(np.array(peaks) - level, 0.0, None)
    if noise > 0:
        return excess / noise
    return np.where(excess > 0, np.inf, 0.0)


@dataclass(frozen=True, eq=False)
class LatticeQuality:
    """How well a lattice fit describes its image (:func:`lattice_quality`).

    Attributes
    ----------
    contrast : numpy.ndarray
        ``(V,)`` contrast of each view in background noise standard deviations
        (:func:`view_contrast`).
    found : numpy.ndarray
        ``(V,)`` bool: views bright enough (:data:`MIN_VIEW_CONTRAST`) and on the lattice
        (not :attr:`LatticeFit.missing`).
    residual_rms_px : float
        RMS distance of the found views' centres from their lattice points, pixels (NaN when
        none is found).
    pitch_px : float
        The fitted lattice's pitch, pixels.
    """

    contrast: np.ndarray
    found: np.ndarray
    residual_rms_px: float
    pitch_px: float

    @property
    def n_views(self) -> int:
        """Views expected ``V``."""
        return len(self.found)

    @property
    def views_found(self) -> int:
        """Views found."""
        return int(self.found.sum())

    @property
    def share_found(self) -> float:
        """Share of the expected views found."""
        return self.views_found / self.n_views

    @property
    def residual_rms_pitch(self) -> float:
        """:attr:`residual_rms_px` as a fraction of the pitch."""
        return self.residual_rms_px / self.pitch_px if self.pitch_px > 0 else math.nan

    @property
    def median_contrast(self) -> float:
        """Median contrast of the views (noise standard deviations)."""
        return float(np.median(self.contrast))

    def problem(self) -> str | None:
        """One line naming each measure below its threshold (:data:`MIN_VIEWS_FOUND`,
        :data:`MIN_VIEW_CONTRAST`, :data:`MAX_RESIDUAL_RMS`) with its value, or ``None``."""
        problems = []
        if self.share_found < MIN_VIEWS_FOUND:
            problems.append(
                f"{self.views_found} of {self.n_views} expected views found (share "
                f"{self.share_found:.2f}, at least {MIN_VIEWS_FOUND:g} needed: a view counts when "
                f"it stands {MIN_VIEW_CONTRAST:g} noise std above the background and lies within "
                "0.2 pitch of the lattice)"
            )
        if not self.median_contrast >= MIN_VIEW_CONTRAST:
            problems.append(
                f"median view contrast {self.median_contrast:.1f} noise std (at least "
                f"{MIN_VIEW_CONTRAST:g})"
            )
        if self.residual_rms_pitch > MAX_RESIDUAL_RMS:
            problems.append(
                f"found centres {self.residual_rms_px:.2f} px RMS off the lattice "
                f"({self.residual_rms_pitch:.3f} pitch, at most {MAX_RESIDUAL_RMS:g})"
            )
        return "; ".join(problems) if problems else None

    def summary(self) -> str:
        """One short line: views found, residual and contrast."""
        return (
            f"lattice quality: {self.views_found} of {self.n_views} views found, residual RMS "
            + (
                f"{self.residual_rms_px:.2f} px ({self.residual_rms_pitch:.3f} pitch)"
                if self.views_found
                else "none (no view found)"
            )
            + f", median view contrast {self.median_contrast:.1f} noise std"
        )

    def record(self) -> dict:
        """The measures and their thresholds as plain numbers (for ``lattice.yaml``)."""
        return {
            "views_found": self.views_found,
            "n_views": self.n_views,
            "min_views_found": MIN_VIEWS_FOUND,
            "residual_rms_px": round(self.residual_rms_px, 4),
            "residual_rms_pitch": round(self.residual_rms_pitch, 5),
            "max_residual_rms_pitch": MAX_RESIDUAL_RMS,
            "median_contrast": round(self.median_contrast, 2),
            "view_contrast": [round(float(c), 2) for c in self.contrast],
            "min_view_contrast": MIN_VIEW_CONTRAST,
        }


def lattice_quality(image, fit: LatticeFit, hot_pixels=None) -> LatticeQuality:
    """The quality of ``fit`` on the ``image`` ``(H, W)`` or frames ``(T, H, W)`` (summed) it
    was fitted to: each view's contrast (:func:`view_contrast`, ``hot_pixels`` ``(H, W)``
    replaced), which views are found and their RMS residual from the lattice. Its
    :meth:`LatticeQuality.problem` says why a fit is not to be trusted."""
    image = np.asarray(image, dtype=np.float64)
    image = image.sum(axis=0) if image.ndim == 3 else image
    points = fit.lattice.centers(len(fit.centers))
    contrast = view_contrast(image, points, fit.lattice.pitch, hot_pixels)
    found = ~fit.missing & (contrast >= MIN_VIEW_CONTRAST)
    residual = math.sqrt(float(np.mean(fit.residuals[found] ** 2))) if found.any() else math.nan
    return LatticeQuality(contrast, found, residual, float(fit.lattice.pitch))


PITCH_TOLERANCE = 0.05
"""Largest relative difference between a fitted lattice's pitch and the system's
(:attr:`~fgat.optics.systems.FLFMSystem.pitch_px`) that ``python -m fgat calibrate`` accepts.
The fit measures the pitch to about 0.1 %; real optics differ from their nominal values by a
few per cent (MLA pitch and focal-length tolerances, a relay lens between the MLA and the
camera), and a fluorescence image's lattice also scales with its sample's mean depth
(parallax); a datasheet read in another convention is off by ``sqrt(3) / 2`` or
``2 / sqrt(3)`` (13 % or 15 %, :data:`~fgat.optics.systems.PITCH_CONVENTIONS`)."""
ROTATION_TOLERANCE_DEG = math.degrees(PITCH_TOLERANCE)
"""Largest rotation (degrees, 2.9) between a fitted lattice and the system's nominal one that
``python -m fgat calibrate`` accepts: it moves a lenslet by the same fraction of its distance
from the axis as a pitch error of :data:`PITCH_TOLERANCE`. A flat-top array taken for a
pointy-top one (or a transposed image) is 30 degrees off."""
_FACTOR_NAMES = {"0.866": "sqrt(3)/2", "1.155": "2/sqrt(3)"}
_CONVENTION_MEANINGS = {
    "center": "the centre-to-centre spacing",
    "row": "the distance between rows of lenslets",
    "corner": "the corner-to-corner width of the hexagonal lenslets",
}


def _pitch_mismatch(lattice: HexLattice, system, brightfield: bool) -> str | None:
    """Why the fitted pitch is off the system's by more than :data:`PITCH_TOLERANCE`, naming
    the pitch convention that would explain it; ``None`` when it is within."""
    ratio = lattice.pitch / system.pitch_px
    if abs(ratio - 1.0) <= PITCH_TOLERANCE:
        return None
    text = (
        f"measured lenslet pitch {lattice.pitch:.1f} px, system {system.name!r} "
        f"{system.pitch_px:.1f} px (mla_pitch_mm {system.mla_pitch_mm:g}, mla_pitch_convention "
        f"{system.mla_pitch_convention}): ratio {ratio:.3f}"
    )
    current = PITCH_CONVENTIONS[system.mla_pitch_convention]
    for name, factor in PITCH_CONVENTIONS.items():
        expected = factor / current
        if name == system.mla_pitch_convention or abs(ratio / expected - 1) > PITCH_TOLERANCE:
            continue
        label = _FACTOR_NAMES.get(f"{expected:.3f}", f"{expected:.3f}")
        return (
            f"{text} = {label} within {abs(ratio / expected - 1):.1%}: mla_pitch_mm is probably "
            f"{_CONVENTION_MEANINGS[name]}; set mla_pitch_convention: {name} (or mla_pitch_mm: "
            f"{lattice.pitch * system.pixel_um / 1000.0:.4g} with mla_pitch_convention: center, "
            "the measured spacing)"
        )
    text += (
        ", no pitch convention (sqrt(3)/2, 2/sqrt(3)) explains it: check mla_pitch_mm and "
        "pixel_um (a relay lens of magnification m between the MLA and the camera: divide "
        "pixel_um by m)"
    )
    if not brightfield:
        text += (
            "; a fluorescence image's lattice also scales with its sample's mean depth, a "
            "white-light image of the MLA shows the pitch itself"
        )
    return text


def rotation_from_system_deg(lattice: HexLattice, system) -> float:
    """Rotation (degrees in ``[-30, 30)``, counter-clockwise as displayed) of a fitted lattice
    from a system's nominal one, modulo the 60 degrees of the hexagonal array."""
    return (lattice.rotation_deg - system.lattice_rotation_deg + 30.0) % 60.0 - 30.0


def _rotation_mismatch(lattice: HexLattice, system) -> str | None:
    """Why the fitted rotation is off the system's by more than :data:`ROTATION_TOLERANCE_DEG`
    (modulo 60 degrees), with the ``mla_orientation`` and ``mla_rotation_deg`` that match it;
    ``None`` when it is within."""
    difference = rotation_from_system_deg(lattice, system)
    if abs(difference) <= ROTATION_TOLERANCE_DEG:
        return None
    turns = {
        name: (lattice.rotation_deg - turn + 30.0) % 60.0 - 30.0
        for name, turn in MLA_ORIENTATIONS.items()
    }
    orientation = min(turns, key=lambda name: abs(turns[name]))
    return (
        f"measured lattice rotation {lattice.rotation_deg:.1f} deg, system {system.name!r} "
        f"{system.lattice_rotation_deg:.1f} deg (mla_orientation {system.mla_orientation}, "
        f"mla_rotation_deg {system.mla_rotation_deg:g}): {difference:+.1f} deg apart"
        + (
            " (near 30: the array is the other way up, or the image is transposed or turned by "
            "90 degrees)"
            if abs(difference) > 20.0
            else ""
        )
        + f"; set mla_orientation: {orientation} and mla_rotation_deg: {turns[orientation]:.1f}"
    )


def lattice_mismatch(fit: LatticeFit, system) -> str | None:
    """One line saying how a fitted lattice disagrees with a system's nominal one, or ``None``.

    The pitch must lie within :data:`PITCH_TOLERANCE` of the system's centre-to-centre
    :attr:`~fgat.optics.systems.FLFMSystem.pitch_px`, the rotation (modulo 60 degrees) within
    :data:`ROTATION_TOLERANCE_DEG` of its
    :attr:`~fgat.optics.systems.FLFMSystem.lattice_rotation_deg`; the line names both values
    and the system fields (``mla_pitch_convention``, ``mla_orientation``,
    ``mla_rotation_deg``) that would reconcile them.

    Parameters
    ----------
    fit : LatticeFit
        A lattice fitted to the system's image (:func:`fit_hexagonal_lattice`).
    system : FLFMSystem
        The system the image is said to come from.
    """
    problems = [_pitch_mismatch(fit.lattice, system, fit.brightfield)]
    if len(fit.centers) > 1:
        problems.append(_rotation_mismatch(fit.lattice, system))
    problems = [problem for problem in problems if problem is not None]
    return "; ".join(problems) if problems else None


def number_like(fit: LatticeFit, rotation_deg: float) -> LatticeFit:
    """The fit with its lenslets numbered like a lattice turned by ``rotation_deg`` (a system's
    :attr:`~fgat.optics.systems.FLFMSystem.lattice_rotation_deg`): its rotation is taken, modulo
    60 degrees, nearest ``rotation_deg``, and the views follow. fgat's view order numbers an
    array turned by less than 30 degrees like the unrotated one, which leaves a flat-top array
    (30 degrees) numbered one way or the other by the noise; numbered like the system's nominal
    lattice, its views keep the numbers of the PSF stacks made from that system. Unchanged
    when the rotation already is the nearest, or when the lattice's points do not map onto each
    other (a partly filled outer ring)."""
    lattice = fit.lattice
    turn = rotation_deg + (lattice.rotation_deg - rotation_deg + 30.0) % 60.0 - 30.0
    if abs(turn - lattice.rotation_deg) < 1e-6:
        return fit
    turned = HexLattice(lattice.center, lattice.pitch, turn)
    n_views = len(fit.centers)
    distance = np.linalg.norm(
        turned.centers(n_views)[:, None] - lattice.centers(n_views)[None], axis=2
    )
    order = distance.argmin(axis=1)
    if len(set(order.tolist())) < n_views or distance.min(axis=1).max() > 0.25 * lattice.pitch:
        return fit
    return LatticeFit(
        turned, fit.centers[order], fit.residuals[order], fit.missing[order], fit.brightfield
    )


def view_psf_energy(system, centers, depth_um: float = 0.0) -> np.ndarray:
    """Share ``(V,)`` of a point's light at ``depth_um`` that each view receives in the PSF
    model (Eq. S7) with the lenslets on ``centers`` ``(V, 2)`` (row, col) pixels: the measured
    ones, since a lens's share depends on where it sits in the pupil image (the outer ones are
    partly vignetted), so that :func:`gains_from_image` divides each view's flux by its own."""
    spec = OpticsSpec(system, (float(depth_um),), np.asarray(centers, dtype=np.float64))
    psf = spec.psf(zernike_indices=())  # aberration-free: no Zernike basis to build
    return psf.sum(axis=(-2, -1), dtype=np.float64)[:, 0]
