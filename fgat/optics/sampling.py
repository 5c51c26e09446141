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


def depth_spacing_warning(
    psf_stack: np.ndarray, depths_um, max_step_px: float = MAX_STEP_PX
) -> str | None:
    """A warning when neighbouring planes are further apart than ``max_step_px`` of parallax.

    Returns
    -------
    str or None
        The message (the view, its parallax in px/um, the largest spacing, the spacing that
        would keep the step below ``max_step_px``), or ``None`` when the sampling is fine.
    """
    depths = np.sort(np.asarray(depths_um, dtype=np.float64).reshape(-1))
    if depths.size < 2:
        return None
    parallax = parallax_px_per_um(psf_stack, depths_um)
    view = int(np.argmax(parallax))
    spacing = float(np.diff(depths).max())
    step = float(parallax[view]) * spacing
    if step <= max_step_px:
        return None
    return (
        f"depth spacing {spacing:g} um is too coarse for the parallax: view {view} moves "
        f"{parallax[view]:.2f} px per um, so neighbouring planes are {step:.1f} px apart and "
        f"edges reproject as stepped copies; use planes at most "
        f"{max_step_px / parallax[view]:.2g} um apart"
    )


def crop_overlap_note(centers_px: np.ndarray, crop_radius_px: int) -> str | None:
    """Why the energy captured by the crops can exceed 1: a note when crops of ``2r + 1`` pixels
    are wider than the smallest distance between lenslet centres ``(V, 2)``, so neighbouring
    views' crops hold the same light; ``None`` otherwise."""
    centers = np.asarray(centers_px, dtype=np.float64)
    if len(centers) < 2:
        return None
    distance = np.hypot(*(centers[:, None] - centers[None]).transpose(2, 0, 1))
    pitch = float(distance[~np.eye(len(centers), dtype=bool)].min())
    width = 2 * int(crop_radius_px) + 1
    if width <= pitch:
        return None
    return (
        f"the {width} px crops are wider than the {pitch:.1f} px lenslet pitch: each crop also "
        "holds part of its neighbours' elemental images, so light is counted in more than one "
        f"view and the sum over views can exceed 1 (a crop radius <= {int(pitch // 2)} px keeps "
        "the views apart)"
    )
