"""Pupil coordinates (Eq. S4).

Pixel coordinates follow the array: ``y`` is the row index, ``x`` the column index, so
``theta = atan2(y - c_y, x - c_x)`` turns from +x towards +y (clockwise as an image is shown).
"""

from __future__ import annotations

import torch
from torch import Tensor


def pupil_coordinates(
    rows: Tensor, cols: Tensor, center: tuple[float, float], radius: float
) -> tuple[Tensor, Tensor]:
    """Normalised pupil radius ``rho`` and azimuth ``theta`` (radians) of Eq. S4."""
    dy, dx = rows - center[0], cols - center[1]
    return torch.sqrt(dy * dy + dx * dx) / radius, torch.atan2(dy, dx)
