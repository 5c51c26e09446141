"""Is a PSF stack sampled finely enough for its system? Parallax per plane and crop overlap.

In FLFM an off-axis view sees a point at depth ``z`` displaced by ``z tan(theta_v)`` (the
parallax of Fig. S5); at high NA the outer views move several pixels per micrometre of depth.
If neighbouring PSF planes are further apart than about one pixel of that motion, the planes
of a volume reproject as stepped copies of every edge instead of a continuous blur, so the
depth spacing must follow the parallax. And the per-view crops of a PSF stack (Eq. S12) are
model windows: when a crop is wider than the lenslet pitch it reaches into a neighbour's
elemental image, and the same light is counted in both views' crops.
"""

from __future__ import annotations

import numpy as np

MAX_STEP_PX = 1.0  # largest parallax step between neighbouring planes, pixels
ROUNDING = 1e-9  # relative slack of the advice's rounding down
STEP_SLACK = 1e-6  # relative slack of the spacing check, above ROUNDING


def psf_centroids(psf_stack: np.ndarray) -> np.ndarray:
    """Intensity centroids ``(V, Z, 2)`` (row, col) of each crop of a PSF stack ``(V, Z, h, w)``,
    in pixels relative to the crop centre ``(h // 2, w // 2)``; NaN for an empty crop."""
    stack = np.asarray(psf_stack, dtype=np.float64)
    h, w = stack.shape[-2:]
    total = stack.sum(axis=(-2, -1))
    safe = np.where(total > 0, total, np.nan)
    rows = (stack.sum(axis=-1) * (np.arange(h) - h // 2)).sum(axis=-1) / safe
    cols = (stack.sum(axis=-2) * (np.arange(w) - w // 2)).sum(axis=-1) / safe
    return np.stack([rows, cols], axis=-1)


def parallax_px_per_um(psf_stack: np.ndarray, depths_um) -> np.ndarray:
    """Lateral motion of each view's PSF per micrometre of depth, ``(V,)`` pixels/um.

    The slope of a least-squares line through the crop centroids (:func:`psf_centroids`) against
    depth, as the length of the (row, col) slope vector. Zero for a single plane.
    """
    depths = np.asarray(depths_um, dtype=np.float64).reshape(-1)
    stack = np.asarray(psf_stack)
    if stack.ndim != 4 or stack.shape[1] != depths.size:
        raise ValueError(
            f"psf_stack (V, Z, h, w) with Z = {depths.size} depths expected, got {stack.shape}"
        )
    if depths.size < 2:
        return np.zeros(stack.shape[0])
    centroids = psf_centroids(stack)
    centred = depths - depths.mean()
    slopes = np.nansum(
        (centroids - np.nanmean(centroids, axis=1, keepdims=True)) * centred[None, :, None],
        axis=1,
    ) / np.sum(centred**2)
    return np.hypot(slopes[:, 0], slopes[:, 1])


def plane_steps_px(psf_stack: np.ndarray, depths_um) -> tuple[np.ndarray, np.ndarray]:
    """How far each view's PSF moves between neighbouring planes, in pixels and per micrometre.

    Parameters
    ----------
    psf_stack : numpy.ndarray
        ``(V, Z, h, w)`` PSF stack, planes in the order of ``depths_um``.
    depths_um : array_like
        ``(Z,)`` plane depths, um (any order; distinct).

    Returns
    -------
    (numpy.ndarray, numpy.ndarray)
        ``(V, Z - 1)`` the centroid displacement (:func:`psf_centroids`) between neighbouring
        planes in depth order, pixels, and the same divided by their spacing (the local
        parallax), px/um; NaN where a crop is empty.
    """
    depths = np.asarray(depths_um, dtype=np.float64).reshape(-1)
    stack = np.asarray(psf_stack)
    if stack.ndim != 4 or stack.shape[1] != depths.size:
        raise ValueError(
            f"psf_stack (V, Z, h, w) with Z = {depths.size} depths expected, got {stack.shape}"
        )
    order = np.argsort(depths)
    centroids = psf_centroids(stack[:, order])
    spacing = np.diff(depths[order])
    if depths.size > 1 and not bool((spacing > 0).all()):
        raise ValueError("depths_um must be distinct")
    steps = np.hypot(*np.diff(centroids, axis=1).transpose(2, 0, 1))
    return steps, steps / spacing[None, :]


def parallax_bound_px_per_um(psf_stack: np.ndarray, depths_um) -> tuple[float, int, float]:
    """The largest local parallax over the views and the whole depth range, px/um.

    The local parallax between neighbouring planes (:func:`plane_steps_px`) is the average of
    its derivative over their interval; where it changes with depth (high NA, crops truncating
    a wide defocused spot) the derivative inside an interval can exceed that average by up to
    the change to the next interval, so the bound is the largest local parallax plus the largest
    change between neighbouring intervals of the same view.

    Returns
    -------
    (float, int, float)
        The bound (px/um), the view and the depth (um, the interval's midpoint) where the local
        parallax is largest; ``(0.0, 0, depth)`` for a single plane.
    """
    depths = np.sort(np.asarray(depths_um, dtype=np.float64).reshape(-1))
    if depths.size < 2:
        return 0.0, 0, float(depths[0]) if depths.size else 0.0
    _, rates = plane_steps_px(psf_stack, depths_um)
    rates = np.nan_to_num(rates, nan=0.0)
    view, interval = np.unravel_index(int(np.argmax(rates)), rates.shape)
    change = np.abs(np.diff(rates, axis=1)).max() if rates.shape[1] > 1 else 0.0
    midpoint = 0.5 * (depths[interval] + depths[interval + 1])
    return float(rates.max() + change), int(view), float(midpoint)


def advised_plane_spacing_um(
    psf_stack: np.ndarray, depths_um, max_step_px: float = MAX_STEP_PX
) -> float:
    """The plane spacing that keeps every view's parallax step within ``max_step_px`` over the
    whole depth range: ``max_step_px`` over :func:`parallax_bound_px_per_um`, rounded down to
    two significant digits (so a stack sampled at the advised spacing passes
    :func:`depth_spacing_warning`); ``inf`` when nothing moves."""
    bound, _, _ = parallax_bound_px_per_um(psf_stack, depths_um)
    if not bound > 0:
        return float("inf")
    spacing = max_step_px / bound
    scale = 10.0 ** (np.floor(np.log10(spacing)) - 1)
    return float(np.floor(spacing / scale * (1 + ROUNDING)) * scale)


def depth_spacing_warning(
    psf_stack: np.ndarray, depths_um, max_step_px: float = MAX_STEP_PX
) -> str | None:
    """A warning when some view's PSF moves more than ``max_step_px`` between neighbouring
    planes (:func:`plane_steps_px`).

    Returns
    -------
    str or None
        The message (the largest step, its view and depth, and one spacing valid over the whole
        depth range, :func:`advised_plane_spacing_um`), or ``None`` when the sampling is fine.
    """
    depths = np.sort(np.asarray(depths_um, dtype=np.float64).reshape(-1))
    if depths.size < 2:
        return None
    steps, rates = plane_steps_px(psf_stack, depths_um)
    steps = np.nan_to_num(steps, nan=0.0)
    if steps.max() <= max_step_px * (1 + STEP_SLACK):
        return None
    view, interval = np.unravel_index(int(np.argmax(steps)), steps.shape)
    advised = advised_plane_spacing_um(psf_stack, depths_um, max_step_px)
    return (
        f"depth spacing too coarse for the parallax: view {view} moves "
        f"{rates[view, interval]:.2f} px per um between {depths[interval]:g} and "
        f"{depths[interval + 1]:g} um, so neighbouring planes are {steps[view, interval]:.1f} px "
        f"apart and edges reproject as stepped copies; use planes at most {advised:g} um apart "
        f"over the whole range (the largest parallax over all views and depths)"
    )


def crop_overlap_note(centers_px: np.ndarray, crop_radius_px: int) -> str | None:
    """Why the energy captured by the crops can exceed 1: a note when crops of ``2r + 1`` pixels
    (the cells of their samples span ``2r + 1`` px) are wider than the smallest distance between
    lenslet centres ``(V, 2)``, so neighbouring views' crops hold the same light; ``None``
    otherwise. The advised radius (:func:`largest_separate_radius`) passes this check."""
    centers = np.asarray(centers_px, dtype=np.float64)
    if len(centers) < 2:
        return None
    distance = np.hypot(*(centers[:, None] - centers[None]).transpose(2, 0, 1))
    pitch = float(distance[~np.eye(len(centers), dtype=bool)].min())
    width = 2 * int(crop_radius_px) + 1
    if width <= pitch:
        return None
    return (
        f"the {width} px crops (radius {int(crop_radius_px)}) are wider than the {pitch:.1f} px "
        "lenslet pitch: each crop also holds part of its neighbours' elemental images, so light "
        "is counted in more than one view and the sum over views can exceed 1 (a crop radius <= "
        f"{largest_separate_radius(pitch)} px keeps the views apart)"
    )


def largest_separate_radius(pitch_px: float) -> int:
    """The largest crop radius ``r`` whose crops of ``2r + 1`` pixels (each pixel a unit cell,
    so a crop spans ``2r + 1`` px) fit within the lenslet pitch: ``floor((pitch - 1) / 2)``."""
    return max(int(np.floor((float(pitch_px) - 1.0) / 2.0)), 0)
