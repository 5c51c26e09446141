"""Hexagonal microlens-array geometry and lenslet-center detection (Fig. S5a).

View order, used everywhere in fgat: the lenslet closest to the array centre first (view 0, on
the optical axis), then ring by ring outwards (increasing distance), and within a ring by
increasing angle ``atan2(-d_row, d_col)`` in ``[-5, 355)`` degrees, i.e. from +column turning
counter-clockwise as the image is displayed (rows pointing down). A rotated array (by less than
30 degrees either way) keeps the numbering of the unrotated one (:func:`lattice_points`), and a
system's nominal array that of its lattice turned by ``mla_orientation`` and
``mla_rotation_deg`` (:class:`fgat.optics.systems.FLFMSystem`). For the 7-lens MLA: centre,
right, upper right, upper left, left, lower left, lower right.
"""

from __future__ import annotations

import math

import numpy as np


def _ring_and_angle_order(offsets: np.ndarray, pitch: float) -> np.ndarray:
    """Indices sorting ``(N, 2)`` (row, col) offsets from the centre in the documented view
    order."""
    distance = np.round(np.hypot(offsets[:, 0], offsets[:, 1]) / pitch * 4.0) / 4.0
    # Angles from 5 degrees below +column: a detected lenslet at -0.1 degrees still comes first.
    degrees = np.mod(np.degrees(np.arctan2(-offsets[:, 0], offsets[:, 1])) + 5.0, 360.0)
    angle = np.round(degrees * 1000.0).astype(np.int64)
    angle = np.where(distance == 0, 0, angle)
    return np.lexsort((angle, distance))


def hexagonal_offsets(n_lenslets: int, pitch: float = 1.0) -> np.ndarray:
    """Offsets ``(V, 2)`` (row, col) of the first ``n_lenslets`` lenslets of a hexagonal array.

    Neighbours lie along the column axis and at multiples of 60 degrees from it, ``pitch`` apart;
    the lenslets are taken in the view order of this module, so 7 gives the centre and its first
    ring (the MLA of Note S1).
    """
    if not isinstance(n_lenslets, (int, np.integer)) or n_lenslets < 1:
        raise ValueError(f"n_lenslets must be a positive integer, got {n_lenslets!r}")
    rings = 1
    while 1 + 3 * rings * (rings + 1) < n_lenslets:
        rings += 1
    rings += 1  # a partial outer ring needs the next one too to order by distance
    q, r = np.meshgrid(np.arange(-rings, rings + 1), np.arange(-rings, rings + 1), indexing="ij")
    q, r = q.ravel(), r.ravel()
    rows = -(math.sqrt(3.0) / 2.0) * r
    cols = q + 0.5 * r
    offsets = np.stack([rows, cols], axis=1)
    order = _ring_and_angle_order(offsets, 1.0)
    return offsets[order[:n_lenslets]] * pitch


def lattice_points(
    n_lenslets: int,
    pitch: float,
    rotation_deg: float = 0.0,
    center: tuple[float, float] = (0.0, 0.0),
) -> np.ndarray:
    """Points ``(V, 2)`` (row, col) of the first ``n_lenslets`` lenslets of a hexagonal array of
    ``pitch`` (centre-to-centre) whose view 0 lies at ``center``, turned by ``rotation_deg``
    degrees counter-clockwise as the image is displayed (rows pointing down); 0 puts neighbours
    along the column axis (:func:`hexagonal_offsets`). The view order is the unrotated
    array's, so the numbering follows the array as it turns."""
    offsets = hexagonal_offsets(n_lenslets, pitch)
    angle = math.radians(rotation_deg)
    cos, sin = math.cos(angle), math.sin(angle)
    # (col, -row) turns counter-clockwise by the rotation
    cols = cos * offsets[:, 1] + sin * offsets[:, 0]
    rows = -sin * offsets[:, 1] + cos * offsets[:, 0]
    return np.stack([rows, cols], axis=1) + np.asarray(center, dtype=np.float64)


def sort_lenslet_centers(centers: np.ndarray) -> np.ndarray:
    """Put lenslet centres ``(V, 2)`` (row, col) of a hexagonal array in the documented view order.

    The centre lenslet is the one closest to the centroid of all centres, the pitch the median
    nearest-neighbour distance and the array's rotation (within 30 degrees either way) the mean
    direction of the centre's neighbours modulo 60 degrees; every centre is matched to the
    nearest point of the unrotated unit lattice, whose order is the view order, so a centre may
    sit up to a third of the pitch off its lattice point.
    """
    centers = np.asarray(centers, dtype=np.float64)
    if centers.ndim != 2 or centers.shape[1] != 2:
        raise ValueError(f"lenslet centers must have shape (V, 2) (row, col), got {centers.shape}")
    if len(centers) == 1:
        return centers.copy()
    middle = centers[np.argmin(np.linalg.norm(centers - centers.mean(0), axis=1))]
    distances = np.linalg.norm(centers[:, None] - centers[None], axis=2)
    np.fill_diagonal(distances, np.inf)
    pitch = np.median(distances.min(axis=1))
    offsets = (centers - middle) / pitch
    radius = np.hypot(offsets[:, 0], offsets[:, 1])
    neighbours = offsets[(radius > 0.5) & (radius < 1.5)]
    angle = 0.0
    if len(neighbours):
        phases = np.exp(6j * np.arctan2(-neighbours[:, 0], neighbours[:, 1]))
        angle = float(np.angle(phases.mean()) / 6.0)
    cos, sin = math.cos(angle), math.sin(angle)
    # turn the (col, -row) plane back by the array's rotation
    cols = cos * offsets[:, 1] - sin * offsets[:, 0]
    rows = sin * offsets[:, 1] + cos * offsets[:, 0]
    unit = hexagonal_offsets(1 + 3 * (int(radius.max()) + 2) * (int(radius.max()) + 3))
    nearest = np.linalg.norm(np.stack([rows, cols], axis=1)[:, None] - unit[None], axis=2)
    index = nearest.argmin(axis=1)
    if len(set(index.tolist())) < len(index) or nearest.min(axis=1).max() > 1 / 3:
        return centers[_ring_and_angle_order(centers - middle, pitch)]  # not a clean lattice
    return centers[np.argsort(index)]


def largest_view_size(centers: np.ndarray, sensor_shape: tuple[int, int]) -> int:
    """Side (pixels) of the largest square views centred on ``centers`` (V, 2) that neither overlap
    nor leave the sensor; a centre outside the sensor raises ``ValueError``."""
    centers = np.asarray(centers, dtype=np.float64)
    outside = [
        v
        for v, (r, c) in enumerate(np.round(centers))
        if not (0 <= r < sensor_shape[0] and 0 <= c < sensor_shape[1])
    ]
    if outside:
        v = outside[0]
        raise ValueError(
            f"lenslet centre {v} ({centers[v, 0]:g}, {centers[v, 1]:g}) lies outside the "
            f"{sensor_shape[0]} x {sensor_shape[1]} sensor"
        )
    size = min(sensor_shape)
    if len(centers) > 1:
        spacing = np.linalg.norm(centers[:, None] - centers[None], axis=2)
        np.fill_diagonal(spacing, np.inf)
        size = int(spacing.min())
    edge = min(
        min(r, c, sensor_shape[0] - 1 - r, sensor_shape[1] - 1 - c) for r, c in np.round(centers)
    )
    return max(1, min(size, 2 * int(edge) + 1))


def lenslet_image(image, n_lenslets: int, name: str, frames: bool = False) -> np.ndarray:
    """``image`` as a float64 ``(H, W)`` array to find ``n_lenslets`` lenslets in (``(T, H, W)``
    frames summed when ``frames``); ``ValueError`` naming ``name`` for another shape, NaN/Inf
    values, a constant image or a lenslet count that is not a positive integer."""
    image = np.asarray(image, dtype=np.float64)
    if frames and image.ndim == 3:
        image = image.sum(axis=0)
    if image.ndim != 2:
        axes = "(H, W) or (T, H, W)" if frames else "2D (H, W)"
        raise ValueError(f"{name} must be {axes}, got shape {image.shape}")
    if not np.isfinite(image).all():
        raise ValueError(f"{name} contains NaN or Inf values")
    if np.ptp(image) == 0:
        raise ValueError(f"{name} is constant: no lenslets to find")
    if not isinstance(n_lenslets, (int, np.integer)) or n_lenslets < 1:
        raise ValueError(f"n_lenslets must be a positive integer, got {n_lenslets!r}")
    return image


def _estimate_radius(image: np.ndarray, n_lenslets: int) -> float:
    """Radius (pixels) of the lenslet disks from the areas of the brightest Otsu regions."""
    from skimage.filters import threshold_otsu  # scikit-image loaded when used: keeps start-up fast
    from skimage.measure import (  # scikit-image loaded when used: keeps start-up fast
        label,
        regionprops,
    )

    regions = sorted(
        regionprops(label(image > threshold_otsu(image))), key=lambda r: r.area, reverse=True
    )
    if len(regions) < n_lenslets:
        raise ValueError(
            f"found {len(regions)} bright region(s) in the brightfield image, expected "
            f"{n_lenslets} lenslet disks; pass radius_px explicitly"
        )
    return float(np.median([math.sqrt(r.area / math.pi) for r in regions[:n_lenslets]]))


def _fit_circle(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Algebraic least-squares circle through ``(N, 2)`` points (Kasa fit): centre, radius."""
    a = np.column_stack([points, np.ones(len(points))])
    b = (points**2).sum(axis=1)
    (p, q, c), *_ = np.linalg.lstsq(a, b, rcond=None)
    center = np.array([p / 2.0, q / 2.0])
    return center, math.sqrt(max(c + center @ center, 0.0))


def detect_lenslet_centers(image, n_lenslets: int, radius_px: float | None = None) -> np.ndarray:
    """Lenslet centres from a brightfield image of the MLA (Fig. S5a), sub-pixel.

    An edge map (Canny) of the image feeds scikit-image's circular Hough transform, which finds
    the ``n_lenslets`` strongest circles of radius near ``radius_px``; each centre is then refined
    by a least-squares circle fit to the full-resolution edge pixels near its circle.

    Parameters
    ----------
    image : array-like
        ``(H, W)`` brightfield image, lenslet apertures brighter than the background.
    n_lenslets : int
        Number of lenslet apertures to find.
    radius_px : float, optional
        Aperture radius in pixels; estimated from the bright regions when omitted.

    Returns
    -------
    numpy.ndarray
        ``(V, 2)`` float64 centres (row, col) in the view order of this module.
    """
    from skimage.feature import canny  # scikit-image loaded when used: keeps start-up fast
    from skimage.transform import (  # scikit-image loaded when used: keeps start-up fast
        hough_circle,
        hough_circle_peaks,
        rescale,
    )

    image = lenslet_image(image, n_lenslets, "brightfield image")
    image = (image - image.min()) / np.ptp(image)
    radius = _estimate_radius(image, n_lenslets) if radius_px is None else float(radius_px)
    if not radius > 2:
        raise ValueError(f"radius_px must be larger than 2 pixels, got {radius}")
    scale = min(1.0, 40.0 / radius)  # the Hough search runs with radii near 40 pixels
    small = rescale(image, scale, anti_aliasing=scale < 1) if scale < 1 else image
    radii = np.arange(
        max(3, math.floor(0.85 * radius * scale)), math.ceil(1.15 * radius * scale) + 1
    )
    accumulator = hough_circle(canny(small, sigma=2.0), radii)
    separation = max(1, int(radius * scale))
    _, cols, rows, found = hough_circle_peaks(
        accumulator,
        radii,
        min_xdistance=separation,
        min_ydistance=separation,
        total_num_peaks=n_lenslets,
    )
    if len(rows) < n_lenslets:
        raise ValueError(
            f"found {len(rows)} circle(s) in the brightfield image, expected {n_lenslets}"
        )
    edges = np.argwhere(canny(image, sigma=2.0)).astype(np.float64)
    centers = []
    for row, col, r in zip(rows / scale, cols / scale, found / scale):
        center = np.array([row, col])
        for tolerance in (max(3.0, 0.1 * r), 3.0, 1.5):  # refit on a narrowing band of edges
            near = edges[np.abs(np.linalg.norm(edges - center, axis=1) - r) < tolerance]
            if len(near) < 8:
                break
            center, r = _fit_circle(near)
        centers.append(center)
    return sort_lenslet_centers(np.array(centers))
