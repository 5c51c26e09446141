"""Apparent tubule widths from line profiles (Note S8.2, Fig. 3j).

Note S8.2 measures the apparent width of mitochondrial tubules from intensity profiles placed
approximately perpendicular to locally isolated tubule segments: the local background is estimated
from the profile ends and subtracted, the profile is normalised to its peak, and the width is the
full width at half maximum (FWHM) from linear interpolation between the two half-maximum crossings.
The same segments are measured on the raw light-field view and on every reconstruction.

Images are ``(Y, X)`` arrays and volumes ``(Z, Y, X)`` arrays; segment coordinates are in pixels
(row ``y``, column ``x``, pixel centres at integer coordinates, as in scikit-image) and widths in
micrometres.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
import pandas as pd
from skimage.measure import profile_line

SEGMENT_COLUMNS = ("center_y", "center_x", "axis_angle_rad", "half_length_px")
"""Columns of a segment table accepted by :func:`tubule_widths`."""

_PEAK_RTOL = 1e-9  # a background-subtracted peak below this fraction of max |profile| is no peak
_PIXEL_RTOL = 1e-6  # tolerated relative difference between the y and x pixel sizes


@dataclass(frozen=True)
class FwhmResult:
    """Outcome of one profile's FWHM measurement (Note S8.2).

    Attributes
    ----------
    fwhm : float
        Full width at half maximum in samples; NaN when it cannot be measured.
    reason : str
        Why ``fwhm`` is NaN; empty when the measurement succeeded.
    peak : float
        Peak height of the background-subtracted profile (profile units), interpolated between
        samples; NaN when the profile has no positive peak.
    left, right : float
        Positions (in samples, from the first sample) of the half-maximum crossings left and right
        of the peak; NaN when missing.
    """

    fwhm: float
    reason: str = ""
    peak: float = math.nan
    left: float = math.nan
    right: float = math.nan


@dataclass(frozen=True)
class Segment:
    """One tubule segment to measure (Note S8.2).

    Attributes
    ----------
    center_yx : tuple of float
        ``(y, x)`` centre of the profile in pixels (row, column).
    axis_angle_rad : float
        Direction of the *tubule axis* in radians, measured from the +x (column) axis towards +y
        (row): the axis unit vector is ``(dy, dx) = (sin a, cos a)``. Since rows grow downwards,
        a positive angle turns clockwise on screen. The profile runs perpendicular to it, along
        ``(dy, dx) = (cos a, -sin a)``.
    half_length_px : float
        Half-length of the profile in pixels (>= 1): the profile spans ``2 * half_length_px``
        pixels centred on ``center_yx``. It should reach beyond the tubule into local background
        on both sides, which the profile ends estimate.
    """

    center_yx: tuple[float, float]
    axis_angle_rad: float
    half_length_px: float

    def __post_init__(self):
        center = tuple(float(c) for c in self.center_yx)
        if len(center) != 2 or not all(math.isfinite(c) for c in center):
            raise ValueError(f"Segment.center_yx must be two finite pixels (y, x), got {center}")
        object.__setattr__(self, "center_yx", center)
        if not math.isfinite(self.axis_angle_rad):
            raise ValueError(f"Segment.axis_angle_rad must be finite, got {self.axis_angle_rad}")
        if not self.half_length_px >= 1 or not math.isfinite(self.half_length_px):
            raise ValueError(
                f"Segment.half_length_px must be a finite length >= 1 pixel, "
                f"got {self.half_length_px}"
            )

    def profile_endpoints(self) -> tuple[np.ndarray, np.ndarray]:
        """``(src, dst)``: the profile's end points ``(y, x)`` in pixels, each ``(2,)``."""
        normal = np.array([math.cos(self.axis_angle_rad), -math.sin(self.axis_angle_rad)])
        center = np.asarray(self.center_yx)
        return center - self.half_length_px * normal, center + self.half_length_px * normal


def _check_profile(profile, end_fraction: float) -> np.ndarray:
    values = np.asarray(profile, dtype=np.float64)
    if values.ndim != 1 or values.size < 3:
        raise ValueError(
            f"profile must be a 1-D array of at least 3 samples, got shape {values.shape}"
        )
    if not np.all(np.isfinite(values)):
        raise ValueError("profile contains non-finite values (NaN or inf)")
    if not 0 < end_fraction < 0.5:
        raise ValueError(f"end_fraction must lie in (0, 0.5), got {end_fraction}")
    return values


def subtract_end_background(profile: np.ndarray, end_fraction: float = 0.1) -> np.ndarray:
    """Subtract the straight line through the means of the profile's two ends (Note S8.2).

    Parameters
    ----------
    profile : ndarray, shape (N,)
        Intensity samples along the profile, N >= 3.
    end_fraction : float
        Fraction of the samples at each end used for the background, in (0, 0.5); at least one
        sample per end. Each end's mean sits at its mean position, so a linear background is
        removed exactly.

    Returns
    -------
    ndarray, shape (N,)
        float64 profile minus the end background.
    """
    values = _check_profile(profile, end_fraction)
    return _remove_end_line(values, _end_samples(values.size, end_fraction))


def _end_samples(n: int, end_fraction: float) -> int:
    """Samples per profile end used for the background: ``end_fraction * n``, at least one."""
    return max(1, int(end_fraction * n))


def _remove_end_line(values: np.ndarray, k: int) -> np.ndarray:
    n = values.size
    x_left, x_right = (k - 1) / 2, n - 1 - (k - 1) / 2
    y_left, y_right = values[:k].mean(), values[-k:].mean()
    slope = (y_right - y_left) / (x_right - x_left)
    return values - (y_left + slope * (np.arange(n) - x_left))


def _crossing(normalised: np.ndarray, peak_index: int, step: int) -> float:
    """Position of the half-maximum crossing nearest the peak in direction ``step`` (+1 or -1);
    NaN when the profile does not fall to half maximum on that side."""
    below = np.flatnonzero(normalised[peak_index + step :: step] <= 0.5)
    if below.size == 0:
        return math.nan
    outer = peak_index + step * (below[0] + 1)
    inner = outer - step
    fraction = (0.5 - normalised[outer]) / (normalised[inner] - normalised[outer])
    return outer - step * fraction


def fwhm_with_reason(profile, *, end_fraction: float = 0.1) -> FwhmResult:
    """FWHM of a line profile with its diagnostics (Note S8.2).

    The local background (the straight line through the means of the first and last
    ``end_fraction`` of the samples, see :func:`subtract_end_background`) is subtracted and the
    profile is normalised to its peak. The peak height is taken at sub-sample precision from the
    parabola through the maximum sample and its neighbours, so that the width does not depend on
    where the samples fall on the peak. The FWHM is the distance between the half-maximum
    crossings nearest the peak on each side, each located by linear interpolation between the two
    samples that bracket it.

    Parameters
    ----------
    profile : array_like, shape (N,)
        Finite intensity samples, N >= 3, equally spaced.
    end_fraction : float
        Fraction of the samples at each end used for the background, in (0, 0.5).

    Returns
    -------
    FwhmResult
        ``fwhm`` in samples, or NaN with ``reason`` when the profile is monotone or flat, has no
        positive peak above the background, peaks at its first or last sample, does not fall to
        half maximum on one side, or crosses half maximum within the end samples used for the
        background (the profile is too short, or the peak too close to an edge, for the ends to
        be background).

    Raises
    ------
    ValueError
        For unusable input: not 1-D, fewer than 3 samples, non-finite values, or ``end_fraction``
        outside (0, 0.5).
    """
    values = _check_profile(profile, end_fraction)
    n_end = _end_samples(values.size, end_fraction)
    corrected = _remove_end_line(values, n_end)
    peak_index = int(np.argmax(corrected))
    steps = np.diff(values)
    if np.all(steps >= 0) or np.all(steps <= 0):
        return FwhmResult(math.nan, "profile is monotone or flat: no peak")
    if corrected[peak_index] <= _PEAK_RTOL * np.abs(values).max():
        return FwhmResult(math.nan, "no positive peak above the end background")
    if peak_index in (0, values.size - 1):
        reason = f"peak at the profile edge (sample {peak_index})"
        return FwhmResult(math.nan, reason, float(corrected[peak_index]))
    peak = _vertex(corrected[peak_index - 1 : peak_index + 2])
    if corrected[peak_index] <= peak / 2:
        return FwhmResult(math.nan, "peak sample below half the interpolated peak", peak)
    left = _crossing(corrected / peak, peak_index, -1)
    right = _crossing(corrected / peak, peak_index, 1)
    reason = _crossing_problem(left, right, values.size, n_end)
    return FwhmResult(math.nan if reason else right - left, reason, peak, left, right)


def _vertex(three: np.ndarray) -> float:
    """Peak of the parabola through a maximum sample and its two neighbours (``(3,)``): the
    sub-sample peak height, never below the middle sample."""
    before, middle, after = three
    curvature = before - 2 * middle + after
    return float(middle - (before - after) ** 2 / (8 * curvature) if curvature < 0 else middle)


def _crossing_problem(left: float, right: float, n: int, n_end: int) -> str:
    """Why the crossings ``left`` and ``right`` (samples) give no width; empty when they do."""
    missing = [side for side, x in (("left", left), ("right", right)) if math.isnan(x)]
    if missing:
        return f"profile does not fall to half maximum {' or '.join(missing)} of the peak"
    inside = [
        side for side, bad in (("left", left <= n_end - 1), ("right", right >= n - n_end)) if bad
    ]
    if inside:
        return (
            f"half-maximum crossing within the {' and '.join(inside)} end samples used for the "
            "background: profile too short or peak too close to the edge"
        )
    return ""


def profile_fwhm(profile, *, end_fraction: float = 0.1) -> float:
    """FWHM of a line profile in samples after end-background subtraction (Note S8.2).

    Parameters
    ----------
    profile : array_like, shape (N,)
        Finite intensity samples, N >= 3, equally spaced.
    end_fraction : float
        Fraction of the samples at each end used for the linear background, in (0, 0.5).

    Returns
    -------
    float
        FWHM in samples; NaN when it cannot be measured, e.g. a half-maximum crossing is missing
        (:func:`fwhm_with_reason` gives the reason).

    Raises
    ------
    ValueError
        For unusable input (see :func:`fwhm_with_reason`); never for a profile without a
        measurable peak.
    """
    return fwhm_with_reason(profile, end_fraction=end_fraction).fwhm


def _lateral_pixel_um(voxel_size_um, ndim: int) -> float:
    expected = "(dz, dy, dx)" if ndim == 3 else "(dy, dx)"
    if voxel_size_um is None:
        raise ValueError(f"voxel_size_um is required: {expected} in micrometres")
    sizes = np.asarray(voxel_size_um, dtype=np.float64).ravel()
    if sizes.size != ndim or not np.all(np.isfinite(sizes)) or np.any(sizes <= 0):
        raise ValueError(
            f"voxel_size_um must be {ndim} positive sizes {expected} in micrometres for a "
            f"{ndim}-D input, got {voxel_size_um}"
        )
    dy, dx = sizes[-2:]
    if abs(dy - dx) > _PIXEL_RTOL * max(dy, dx):
        raise ValueError(
            f"voxel_size_um: tubule widths need square pixels (dy == dx), got dy={dy}, dx={dx}"
        )
    return float(dx)


def _measured_image(image_or_volume, plane: int | None) -> np.ndarray:
    data = np.asarray(image_or_volume)
    if data.ndim not in (2, 3):
        raise ValueError(
            f"image_or_volume must be a (Y, X) image or a (Z, Y, X) volume, got shape {data.shape}"
        )
    if data.size == 0:
        raise ValueError(f"image_or_volume is empty (shape {data.shape})")
    data = data.astype(np.float64)
    if not np.all(np.isfinite(data)):
        raise ValueError("image_or_volume contains non-finite values (NaN or inf)")
    if data.ndim == 2:
        if plane is not None:
            raise ValueError(f"plane={plane} is only for (Z, Y, X) volumes; got a 2-D image")
        image, name = data, "image_or_volume"
    elif plane is None:
        image, name = data.max(axis=0), "the x-y maximum-intensity projection"
    else:
        if not isinstance(plane, (int, np.integer)) or not -len(data) <= plane < len(data):
            raise ValueError(f"plane must be an index into the {len(data)} planes, got {plane}")
        image, name = data[plane], f"plane {plane}"
    if not np.any(image):
        raise ValueError(f"{name} is all zero: nothing to measure")
    return image


def _as_segments(segments) -> list[Segment]:
    if isinstance(segments, pd.DataFrame):
        missing = [c for c in SEGMENT_COLUMNS if c not in segments.columns]
        if missing:
            raise ValueError(
                f"segments table lacks columns {missing}; expected {list(SEGMENT_COLUMNS)}"
            )
        rows = segments.itertuples(index=False)
        segments = [
            Segment((r.center_y, r.center_x), r.axis_angle_rad, r.half_length_px) for r in rows
        ]
    elif isinstance(segments, Segment):
        segments = [segments]
    elif isinstance(segments, Iterable):
        segments = list(segments)
    if not isinstance(segments, list) or not all(isinstance(s, Segment) for s in segments):
        raise ValueError(
            f"segments must be Segment objects or a DataFrame with columns {list(SEGMENT_COLUMNS)}"
        )
    if not segments:
        raise ValueError("segments is empty: nothing to measure")
    return segments


def _check_inside(segment: Segment, index: int, shape: tuple[int, int], width_px: int) -> None:
    """Raise when the sampled strip (profile +- (width_px - 1) / 2 along the axis) leaves the
    image's pixel centres."""
    axis = np.array([math.sin(segment.axis_angle_rad), math.cos(segment.axis_angle_rad)])
    half_width = (width_px - 1) / 2 * axis
    corners = np.array(
        [end + s * half_width for end in segment.profile_endpoints() for s in (-1, 1)]
    )
    limits = np.array(shape) - 1
    if np.any(corners < -1e-9) or np.any(corners > limits + 1e-9):
        raise ValueError(
            f"segments[{index}] (center {segment.center_yx}, half-length "
            f"{segment.half_length_px} px, width {width_px} px) reaches outside the "
            f"{shape[0]} x {shape[1]} image"
        )


def tubule_widths(
    image_or_volume,
    segments,
    *,
    voxel_size_um,
    width_px: int = 1,
    plane: int | None = None,
    end_fraction: float = 0.1,
) -> pd.DataFrame:
    """Apparent tubule widths (FWHM) across segments, in micrometres (Note S8.2, Fig. 3j).

    For each segment, one intensity profile perpendicular to the tubule axis through the segment
    centre is sampled with :func:`skimage.measure.profile_line` (bilinear interpolation, averaged
    over ``width_px`` parallel lines) and measured with :func:`fwhm_with_reason`.

    Parameters
    ----------
    image_or_volume : array_like, shape (Y, X) or (Z, Y, X)
        Image, or volume measured on its x-y maximum-intensity projection (or on ``plane``).
    segments : Segment, sequence of Segment, or pandas.DataFrame
        Segments to measure; a DataFrame needs the columns ``center_y, center_x`` (pixels),
        ``axis_angle_rad`` and ``half_length_px`` (see :class:`Segment`).
    voxel_size_um : sequence of float
        ``(dy, dx)`` for an image or ``(dz, dy, dx)`` for a volume, in micrometres; ``dy`` must
        equal ``dx`` (square pixels).
    width_px : int
        Width of the profile strip in pixels (``linewidth`` of ``profile_line``), >= 1.
    plane : int, optional
        For volumes: measure this z-plane instead of the maximum-intensity projection.
    end_fraction : float
        Fraction of each profile's samples at each end used for the local background.

    Returns
    -------
    pandas.DataFrame
        One row per segment with columns ``segment`` (index), ``center_y_px``, ``center_x_px``,
        ``axis_angle_rad``, ``half_length_px``, ``width_um``, ``fwhm_px``, ``peak``
        (background-subtracted peak, image units) and ``reason`` (empty when the width was
        measured, else why ``width_um`` is NaN).

    Raises
    ------
    ValueError
        For a wrong dimensionality, an empty, non-finite or all-zero image, a missing or
        non-positive voxel size, non-square pixels, a bad ``plane`` or ``width_px``, no segments,
        or a segment whose profile leaves the image.
    """
    image = _measured_image(image_or_volume, plane)
    pixel_um = _lateral_pixel_um(voxel_size_um, np.ndim(image_or_volume))
    if not isinstance(width_px, (int, np.integer)) or width_px < 1:
        raise ValueError(f"width_px must be an integer >= 1 pixel, got {width_px}")
    segments = _as_segments(segments)
    for index, segment in enumerate(segments):
        _check_inside(segment, index, image.shape, width_px)
    return pd.DataFrame(
        [
            _measure(image, segment, index, width_px, end_fraction, pixel_um)
            for index, segment in enumerate(segments)
        ]
    )


def _measure(
    image: np.ndarray,
    segment: Segment,
    index: int,
    width_px: int,
    end_fraction: float,
    pixel_um: float,
) -> dict:
    """One row of :func:`tubule_widths`' table."""
    src, dst = segment.profile_endpoints()
    profile = profile_line(
        image, src, dst, linewidth=width_px, order=1, mode="reflect", reduce_func=np.mean
    )
    # profile_line spaces its samples evenly from src to dst, at most one pixel apart
    spacing_px = 2 * segment.half_length_px / (profile.size - 1)
    result = fwhm_with_reason(profile, end_fraction=end_fraction)
    fwhm_px = result.fwhm * spacing_px
    return {
        "segment": index,
        "center_y_px": segment.center_yx[0],
        "center_x_px": segment.center_yx[1],
        "axis_angle_rad": segment.axis_angle_rad,
        "half_length_px": segment.half_length_px,
        "width_um": fwhm_px * pixel_um,
        "fwhm_px": fwhm_px,
        "peak": result.peak,
        "reason": result.reason,
    }
