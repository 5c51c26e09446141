"""Lengths of the volume analyses (object diameters, blob scales, displacements) checked against
the volume they are measured in, before any detection (Notes S8.7-S8.9).

An object narrower than two voxels laterally is below the sampling (Nyquist: it spans fewer than
two samples, so its size and centre are not resolved); an object, or a displacement, larger than
the volume's extent cannot be found in it (trackpy's locate, for one, keeps only features whose
whole mask fits inside the volume; ``skimage.feature.blob_log``'s filters then span the volume
and answer at its centre). A length outside that range gives an answer that looks like a result:
a few huge "cells", or many noise "cells", after a long computation.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

AXES = "ZYX"

BALL_DIAMETER_PER_SIGMA = 2.0 * math.sqrt(3.0)
"""Diameter of the uniform ball the Laplacian of Gaussian of scale ``s`` answers best to
(radius ``sqrt(3) s``; a Gaussian blob of s.d. ``s`` fills about the same ball)."""

MIN_DIAMETER_VOXELS = 2.0
"""Smallest object diameter along ``y`` and ``x``, in voxels (two samples across)."""


def _triple(name: str, value) -> np.ndarray:
    """``value`` (one number or ``(z, y, x)``) as a ``(3,)`` float64 array of finite positive
    numbers; ``ValueError`` naming ``name`` otherwise."""
    try:
        array = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        array = np.array([math.nan])
    if array.size not in (1, 3) or not np.all(np.isfinite(array) & (array > 0)):
        raise ValueError(
            f"{name} must be one or three (z, y, x) finite numbers > 0 (um), got {value!r}"
        )
    return np.broadcast_to(array, (3,)).copy()


def _format(values: Sequence[float]) -> str:
    return "(" + ", ".join(f"{v:.4g}" for v in values) + ")"


def check_length_um(
    name: str,
    value,
    voxel_size_um,
    shape: Sequence[int],
    *,
    diameter_per_value: float = 1.0,
    min_voxels: float = MIN_DIAMETER_VOXELS,
    axes: str = AXES,
) -> np.ndarray:
    """Check a length option against the voxel size and the extent of the volume it measures.

    The object the length describes has the diameter ``D = diameter_per_value * value`` (per
    axis when ``value`` has three entries). Along ``y`` and ``x`` it must span at least
    ``min_voxels`` voxels (``D >= min_voxels * voxel``; the axial sampling of light-field
    volumes is coarse, so ``z`` has no lower bound), and along each of ``axes`` it must fit in
    the volume (``D <= extent``, the extent being ``shape * voxel_size_um``).

    Parameters
    ----------
    name : str
        The option or argument, named in the error (e.g. ``"--diameter-um"``).
    value : float or (3,) float
        The length in um, one value or ``(z, y, x)``.
    voxel_size_um : (3,) float
        Voxel size ``(dz, dy, dx)`` in um.
    shape : (3,) int
        Volume shape ``(Z, Y, X)`` in voxels (a series' last three).
    diameter_per_value : float
        The object's diameter per unit of ``value``: 1 for a diameter or a distance,
        :data:`BALL_DIAMETER_PER_SIGMA` for a Laplacian-of-Gaussian scale.
    min_voxels : float
        Smallest diameter along ``y`` and ``x`` in voxels (0: none, for displacements).
    axes : str
        The axes, among ``"ZYX"``, along which the diameter must fit in the extent.

    Returns
    -------
    (3,) ndarray
        ``value`` per axis ``(z, y, x)``, um.

    Raises
    ------
    ValueError
        One line naming ``name``, its value, the voxel size, the extent and the valid range.
    """
    length = _triple(name, value)
    voxel = _triple("voxel size", voxel_size_um)
    extent = np.asarray(shape[-3:], dtype=np.float64) * voxel
    low = np.where(np.arange(3) > 0, min_voxels * voxel, 0.0) / diameter_per_value
    high = np.where([axis in axes for axis in AXES], extent, np.inf) / diameter_per_value
    bad = [i for i in range(3) if not low[i] <= length[i] <= high[i]]
    if bad:
        i = bad[0]
        given = f"{length[0]:.4g}" if np.ptp(length) == 0 else _format(length)
        limit = (
            f"below {min_voxels:g} voxels of {voxel[i]:.4g} um, not resolved"
            if length[i] < low[i]
            else f"beyond the volume's extent of {extent[i]:.4g} um"
        )
        upper = f"at most {high[i]:.4g} um" if math.isfinite(high[i]) else "any length"
        valid = f"{low[i]:.4g} to {high[i]:.4g} um" if low[i] > 0 else upper
        scale = (
            "" if diameter_per_value == 1 else f" (an object {diameter_per_value:.3g} x as wide)"
        )
        raise ValueError(
            f"{name} {given} um: along {AXES[i].lower()} {length[i]:.4g} um{scale} is {limit}; "
            f"expected {valid} for voxel size {_format(voxel)} um and extent {_format(extent)} "
            f"um (z, y, x) of shape {tuple(int(n) for n in shape[-3:])}"
        )
    return length
