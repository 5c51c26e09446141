"""Depth-scale calibration from a bead z-stack: each view's parallax measured against the model's.

A sub-resolution bead imaged at known stage (or objective) positions moves in every view by the
view's parallax. The bead is tracked through the stack in every view (Gaussian-weighted
centroids, :func:`measure_view_centroids`) and each view's slope against the positions
(:func:`view_slopes`) is compared with the slope the same tracking finds in the JPGM's own
noise-free stack of an on-axis bead at those positions (:func:`render_bead_stack`), so the
windows, the crop and the diffraction of the lenslet edges affect both alike. One factor, the
depth scale, makes the model's parallax match every view (:func:`fit_depth_scale`); the fit is
refused when the views disagree with one factor by more than :data:`MAX_RESIDUAL` of the
parallax (a wrong pupil radius, lenslet pitch or refractive index changes the parallax ring by
ring, not by one factor).

Positions. A stage or objective z-stack changes the immersion layer's thickness, not the bead's
depth in the sample: its pupil phase per um is the immersion medium's (module docstring of
:mod:`fgat.optics.propagation`), whatever the sample medium, and the model renders it so (the
JPGM's ``depth_medium="immersion"``, with the emission apodization of the bead's medium).
``motion="stage"``: a position is how far the sample moved away from the objective (the
immersion layer grows); ``motion="objective"``: how far the objective moved towards the sample
(the layer shrinks), the opposite sign. The fitted factor multiplies the pupil phase per um, so
it applies unchanged to depths in the sample (:attr:`fgat.optics.systems.FLFMSystem.depth_scale`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from fgat.optics.patches import place_patches
from fgat.optics.psf import JPGM
from fgat.optics.systems import FLFMSystem

MOTIONS = {"stage": 1.0, "objective": -1.0}  # sign of the immersion-layer change per position
MAX_RESIDUAL = 0.05  # largest relative RMS misfit of the per-view parallax to one scale
MIN_BEAD_SNR = 8.0  # smallest peak of the brightest view's bead over the frame's noise
MIN_PARALLAX = 0.05  # views with less of the largest model parallax carry no depth information
SEARCH_FRACTION = 0.45  # the in-focus bead is looked for this fraction of a pitch from a centre


def render_bead_stack(
    system: FLFMSystem, positions_um, centers: np.ndarray, *, depth_medium: str = "immersion"
) -> np.ndarray:
    """Noise-free sensor frames ``(Z, H, W)`` of an on-axis bead at ``positions_um`` (um of
    ``depth_medium``, see :class:`~fgat.optics.psf.JPGM`): each view's PSF crop (Eq. S12)
    laid at its lenslet centre rounded to a pixel, the parts past the sensor's edge dropped;
    each frame sums to about 1 (the light the crops hold). Float64."""
    with torch.no_grad():
        model = JPGM(
            system,
            list(positions_um),
            centers_px=centers,
            zernike_indices=(),
            depth_medium=depth_medium,
            dtype=torch.float64,
        )
        psf = model().transpose(0, 1)  # (Z, V, h, w)
    r = model.radius
    height, width = system.sensor_shape
    origins = np.round(np.asarray(centers)).astype(int)  # crop origins on a grid padded by r
    padded = place_patches(psf, origins.tolist(), (height + 2 * r, width + 2 * r))
    return padded[:, r : r + height, r : r + width].numpy()


def airy_radius_px(system: FLFMSystem) -> float:
    """Airy radius ``1.22 lambda f_ML / d`` of one lenslet (aperture ``d``) on the camera, px."""
    return (
        1.22 * system.wavelength_um * system.f_mla_mm / system.lenslet_aperture_mm / system.pixel_um
    )


def _windowed_centroid(
    image: np.ndarray, start: np.ndarray, sigma: float, iterations: int = 30
) -> np.ndarray:
    """Gaussian-weighted centroid (row, col) of a spot in ``image``: from ``start``, the mean
    position under ``I exp(-|x - c|^2 / (2 sigma^2))`` in a window of half-width ``3 sigma +
    2``, re-centred until it moves less than 0.01 pixel (at most ``iterations`` times). The
    window border's median is subtracted first (not clipped, which would pull the centroid
    towards the window's centre); the weight keeps the noise of the window's far pixels out."""
    position = np.asarray(start, dtype=np.float64)
    height, width = image.shape
    half = int(math.ceil(3.0 * sigma)) + 2
    for _ in range(iterations):
        row, col = (int(round(v)) for v in position)
        top, left = max(row - half, 0), max(col - half, 0)
        window = image[top : min(row + half + 1, height), left : min(col + half + 1, width)]
        if window.shape[0] < 3 or window.shape[1] < 3:
            break
        border = np.concatenate([window[0], window[-1], window[1:-1, 0], window[1:-1, -1]])
        rows = np.arange(window.shape[0])[:, None] + top
        cols = np.arange(window.shape[1])[None, :] + left
        weight = np.exp(-((rows - position[0]) ** 2 + (cols - position[1]) ** 2) / (2 * sigma**2))
        signal = (window - np.median(border)) * weight
        total = signal.sum()
        if not total > 0:
            break
        moved = np.array([(signal * rows).sum() / total, (signal * cols).sum() / total])
        done = np.abs(moved - position).max() < 0.01
        position = moved
        if done:
            break
    return position


def _noise(image: np.ndarray) -> float:
    """Robust noise level of a frame: 1.4826 times the median absolute deviation."""
    return float(1.4826 * np.median(np.abs(image - np.median(image)))) or 1e-12


def measure_view_centroids(
    stack: np.ndarray, centers: np.ndarray, *, search_px: float, sigma_px: float
) -> tuple[np.ndarray, float]:
    """Track one bead through a z-stack in every view.

    In the frame with the brightest pixel (nearest focus) each view's bead is the brightest
    pixel within ``search_px`` of the lenslet centre; its Gaussian-weighted centroid (width
    ``sigma_px``) is then followed frame by frame towards both ends of the stack, each frame
    starting from its neighbour's centroid.

    Parameters
    ----------
    stack : numpy.ndarray
        ``(Z, H, W)`` sensor images, one per position.
    centers : numpy.ndarray
        ``(V, 2)`` lenslet centres (row, col), pixels.
    search_px : float
        Radius around each centre the in-focus bead is looked for in, pixels.
    sigma_px : float
        Width of the centroid weight, pixels.

    Returns
    -------
    centroids : numpy.ndarray
        ``(Z, V, 2)`` bead centroids (row, col), pixels.
    snr : float
        Peak of the brightest view's bead over the noise of the focus frame.
    """
    stack = np.asarray(stack, dtype=np.float64)
    focus = int(np.argmax(stack.reshape(len(stack), -1).max(axis=1)))
    image = stack[focus]
    background = float(np.median(image))
    rows, cols = np.indices(image.shape)
    centroids = np.zeros((len(stack), len(centers), 2))
    peaks = []
    for v, (row, col) in enumerate(np.asarray(centers, dtype=np.float64)):
        near = (rows - row) ** 2 + (cols - col) ** 2 <= search_px**2
        masked = np.where(near, image, -np.inf)
        peak = np.unravel_index(int(np.argmax(masked)), image.shape)
        peaks.append(image[peak] - background)
        centroids[focus, v] = _windowed_centroid(image, np.array(peak, dtype=np.float64), sigma_px)
    for order in (range(focus + 1, len(stack)), range(focus - 1, -1, -1)):
        previous = focus
        for z in order:
            for v in range(len(centers)):
                centroids[z, v] = _windowed_centroid(stack[z], centroids[previous, v], sigma_px)
            previous = z
    return centroids, float(max(peaks)) / _noise(image)


def view_slopes(positions_um: np.ndarray, centroids: np.ndarray) -> np.ndarray:
    """Least-squares slopes ``(V, 2)`` (row, col) px per um of centroids ``(Z, V, 2)`` against
    ``positions_um`` ``(Z,)``."""
    x = np.asarray(positions_um, dtype=np.float64)
    x = x - x.mean()
    flat = centroids.reshape(len(x), -1)
    slopes = x @ (flat - flat.mean(axis=0)) / (x @ x)
    return slopes.reshape(centroids.shape[1:])


@dataclass(frozen=True)
class DepthScaleFit:
    """Result of :func:`fit_depth_scale`.

    Attributes
    ----------
    scale : float
        Factor on the model's pupil phase per um (:attr:`FLFMSystem.depth_scale` relative to the
        system it was fitted with).
    scale_error : float
        Standard error of ``scale`` from the scatter of the views about the fit.
    residual : float
        RMS of the measured-minus-fitted slopes over the RMS of the fitted ones.
    measured, model : numpy.ndarray
        ``(V, 2)`` measured and model parallax (row, col), px per um of position.
    used : numpy.ndarray
        ``(V,)`` bool: the views that entered the fit.
    ring_ratios : dict
        Distance from view 0 (in units of the nearest lenslet distance, rounded to 0.01) ->
        mean ratio of measured to model radial parallax of that ring's views.
    snr : float
        Bead peak over the noise in the focus frame.
    """

    scale: float
    scale_error: float
    residual: float
    measured: np.ndarray
    model: np.ndarray
    used: np.ndarray
    ring_ratios: dict
    snr: float


def check_bead(snr: float) -> None:
    """Refuse (``ValueError``) a stack whose brightest bead peaks below :data:`MIN_BEAD_SNR`
    times the noise."""
    if not snr >= MIN_BEAD_SNR:
        raise ValueError(
            f"depth scale: no bead in the stack: its brightest view peaks at {snr:.1f} times the "
            f"noise (needs MIN_BEAD_SNR = {MIN_BEAD_SNR:g})"
        )


def fit_depth_scale(
    measured: np.ndarray, model: np.ndarray, centers: np.ndarray, *, snr: float = math.inf
) -> DepthScaleFit:
    """One factor ``a`` minimising ``sum_v |m_v - a s_v|^2`` over the views whose model
    parallax ``s_v`` is at least :data:`MIN_PARALLAX` of the largest; measured ``m_v``, both
    ``(V, 2)`` px per um. Refuses (``ValueError``, one line naming the threshold) a bead fainter
    than :data:`MIN_BEAD_SNR`, a factor that is not positive, or a misfit above
    :data:`MAX_RESIDUAL`."""
    check_bead(snr)
    measured = np.asarray(measured, dtype=np.float64)
    model = np.asarray(model, dtype=np.float64)
    size = np.linalg.norm(model, axis=1)
    used = size >= MIN_PARALLAX * size.max()
    if used.sum() < 2:
        raise ValueError("depth scale: fewer than two views have a parallax to measure")
    m, s = measured[used], model[used]
    scale = float((m * s).sum() / (s * s).sum())
    misfit = m - scale * s
    fitted = float(np.sqrt(np.mean((scale * s) ** 2))) if scale != 0 else 0.0
    residual = float(np.sqrt(np.mean(misfit**2))) / max(fitted, 1e-300)
    dof = max(2 * int(used.sum()) - 1, 1)
    scale_error = float(np.sqrt((misfit**2).sum() / dof / (s * s).sum()))
    offsets = np.asarray(centers, dtype=np.float64) - np.asarray(centers, dtype=np.float64)[0]
    distance = np.linalg.norm(offsets, axis=1)
    unit = distance[distance > 0].min() if (distance > 0).any() else 1.0
    rings: dict[float, list[float]] = {}
    for v in np.flatnonzero(used):
        direction = model[v] / size[v]
        ratio = float(measured[v] @ direction) / size[v]
        rings.setdefault(round(float(distance[v] / unit), 2), []).append(ratio)
    ring_ratios = {ring: float(np.mean(r)) for ring, r in sorted(rings.items())}
    result = DepthScaleFit(scale, scale_error, residual, measured, model, used, ring_ratios, snr)
    if scale <= 0:
        raise ValueError(
            f"depth scale: the views move against the model's parallax (factor {scale:.3f}): the "
            "positions run the other way (stage vs objective motion)"
        )
    if residual > MAX_RESIDUAL:
        rings_text = ", ".join(f"{k:g}: {r:.3f}" for k, r in ring_ratios.items())
        raise ValueError(
            f"depth scale: the per-view parallax misfits one factor {scale:.3f} by "
            f"{residual:.3f} of its size (threshold MAX_RESIDUAL = {MAX_RESIDUAL:g}; measured "
            f"over model by ring {rings_text})"
        )
    return result


def calibrate_depth_scale(
    stack: np.ndarray,
    positions_um,
    system: FLFMSystem,
    centers: np.ndarray,
    *,
    motion: str = "stage",
) -> DepthScaleFit:
    """Fit the depth scale of ``system`` to a bead z-stack.

    Parameters
    ----------
    stack : numpy.ndarray
        ``(Z, H, W)`` sensor images of one bead (the brightest, if several, is tracked), one
        per position, camera offset included or not.
    positions_um : sequence of float
        ``(Z,)`` stage or objective positions, um (see the module docstring for the signs).
    system : FLFMSystem
        The optics the scale is relative to (with its own ``depth_scale``).
    centers : numpy.ndarray
        ``(V, 2)`` lenslet centres (row, col), pixels, in fgat's view order.
    motion : {"stage", "objective"}
        What moved (:data:`MOTIONS`).

    Returns
    -------
    DepthScaleFit
        The factor relative to ``system`` (the absolute scale is
        ``system.depth_scale * fit.scale``).

    Raises
    ------
    ValueError
        One line: frames and positions that do not match, positions whose model bead leaves the
        PSF crops, or a fit that :func:`fit_depth_scale` refuses.
    """
    if motion not in MOTIONS:
        raise ValueError(f"motion must be one of {list(MOTIONS)}, got {motion!r}")
    stack = np.asarray(stack)
    positions = np.asarray(positions_um, dtype=np.float64).reshape(-1)
    if stack.ndim != 3 or len(stack) != len(positions):
        raise ValueError(
            f"the stack has shape {stack.shape}, expected ({len(positions)}, H, W): one frame "
            "per position"
        )
    if len(np.unique(positions)) < 3 or not np.isfinite(positions).all():
        raise ValueError("positions: need at least three distinct finite positions (um)")
    if stack.shape[1:] != tuple(system.sensor_shape):
        raise ValueError(
            f"the stack's frames are {stack.shape[1]} x {stack.shape[2]} pixels, but system "
            f"{system.name!r} has a {system.sensor_shape[0]} x {system.sensor_shape[1]} sensor"
        )
    centers = np.asarray(centers, dtype=np.float64)
    pitch = float(np.linalg.norm(centers[1:] - centers[0], axis=1).min())
    sigma = airy_radius_px(system)
    half = int(math.ceil(3.0 * sigma)) + 2
    track = {"search_px": SEARCH_FRACTION * pitch, "sigma_px": sigma}
    centroids, snr = measure_view_centroids(stack, centers, **track)
    check_bead(snr)
    rendered = render_bead_stack(system, MOTIONS[motion] * positions, centers)
    model_centroids, _ = measure_view_centroids(rendered, centers, **track)
    reach = np.abs(model_centroids - np.round(centers)).max() + half
    if reach > system.crop_radius_px:
        raise ValueError(
            f"positions: the model's bead moves {reach - half:.1f} px from a lenslet centre over "
            f"{positions.min():g}..{positions.max():g} um, past the {system.crop_radius_px}-px "
            f"crops less the {half}-px centroid window; take a narrower range of positions"
        )
    measured = view_slopes(positions, centroids)
    model = view_slopes(positions, model_centroids)
    return fit_depth_scale(measured, model, centers, snr=snr)


def calibrated_system(system: FLFMSystem, calibration) -> FLFMSystem:
    """``system`` with the calibration's ``depth_scale`` (unchanged when it has none)."""
    scale = getattr(calibration, "depth_scale", None)
    return system if scale is None else system.replace(depth_scale=float(scale))
