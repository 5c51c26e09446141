"""Pupil aperture and complex pupil (Eqs. S4 and S6).

Pixel coordinates follow the array: ``y`` is the row index, ``x`` the column index, so
``theta = atan2(y - c_y, x - c_x)`` turns from +x towards +y (clockwise as an image is shown).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor


def pixel_grid(
    shape: tuple[int, int],
    origin: tuple[float, float] = (0.0, 0.0),
    *,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> tuple[Tensor, Tensor]:
    """Row and column coordinates ``(H, W)`` of pixel centres, offset by ``origin`` (row, col)."""
    rows = torch.arange(shape[0], dtype=dtype, device=device) + origin[0]
    cols = torch.arange(shape[1], dtype=dtype, device=device) + origin[1]
    return torch.meshgrid(rows, cols, indexing="ij")


def circular_mask(rows: Tensor, cols: Tensor, center: tuple[float, float], radius: float) -> Tensor:
    """Binary disk: ``True`` where the pixel centre lies within ``radius`` of ``center`` (row, col)."""
    return (rows - center[0]) ** 2 + (cols - center[1]) ** 2 <= radius**2


def aperture_geometry(mask: Tensor) -> tuple[tuple[float, float], float]:
    """Centre ``(c_y, c_x)`` and radius ``R`` (pixels) of a binary aperture mask (Eq. S4).

    The centre is the centroid of the aperture pixels and the radius that of the disk with the
    same area, ``R = sqrt(area / pi)``.
    """
    if mask.ndim != 2:
        raise ValueError(f"aperture mask must be 2D (H, W), got shape {tuple(mask.shape)}")
    weights = mask.to(torch.float64)
    area = float(weights.sum())
    if area == 0:
        raise ValueError("aperture mask is empty: no pixel is inside the aperture")
    rows, cols = pixel_grid(tuple(mask.shape), dtype=torch.float64, device=mask.device)
    center = (float((rows * weights).sum()) / area, float((cols * weights).sum()) / area)
    return center, math.sqrt(area / math.pi)


def pupil_coordinates(
    rows: Tensor, cols: Tensor, center: tuple[float, float], radius: float
) -> tuple[Tensor, Tensor]:
    """Normalised pupil radius ``rho`` and azimuth ``theta`` (radians) of Eq. S4."""
    dy, dx = rows - center[0], cols - center[1]
    return torch.sqrt(dy * dy + dx * dx) / radius, torch.atan2(dy, dx)


def complex_pupil(mask: Tensor, phase: Tensor) -> Tensor:
    """Complex pupil ``P = M exp(i phi)`` (Eq. S6); ``phase`` in radians, broadcast with ``mask``."""
    return mask.to(phase.dtype) * torch.polar(torch.ones_like(phase), phase)
