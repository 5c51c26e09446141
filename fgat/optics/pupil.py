"""Pupil coordinates (Eq. S4) and lenslet apertures (the MLA of Eq. S7).

Pixel coordinates follow the array: ``y`` is the row index, ``x`` the column index, so
``theta = atan2(y - c_y, x - c_x)`` turns from +x towards +y (clockwise as an image is shown).
Aperture orientations are angles of the same kind.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor


def pupil_coordinates(
    rows: Tensor, cols: Tensor, center: tuple[float, float], radius: float
) -> tuple[Tensor, Tensor]:
    """Normalised pupil radius ``rho`` (dimensionless) and azimuth ``theta`` (radians) of
    Eq. S4 at coordinates ``rows``, ``cols`` (broadcastable tensors, camera pixels)
    around ``center`` (pixels) for a pupil of ``radius`` pixels; both of the broadcast shape."""
    theta = torch.atan2(rows - center[0], cols - center[1])
    return pupil_radius(rows, cols, center, radius), theta


def pupil_radius(rows: Tensor, cols: Tensor, center: tuple[float, float], radius: float) -> Tensor:
    """Normalised pupil radius ``rho`` of Eq. S4 alone: dimensionless, of the broadcast shape of
    ``rows`` and ``cols`` (camera pixels), ``center`` and ``radius`` in camera pixels too."""
    dy, dx = rows - center[0], cols - center[1]
    return torch.sqrt(dy * dy + dx * dx) / radius


def lenslet_aperture(
    dy: Tensor, dx: Tensor, *, shape: str, radius: float, angle: float = 0.0
) -> Tensor:
    """Clear aperture of one lenslet: ``True`` inside, same shape as ``dy`` and ``dx``.

    Parameters
    ----------
    dy, dx : Tensor
        Offsets (row, col) from the lenslet axis, in the unit of ``radius``.
    shape : {"circle", "hexagon"}
        A disk of radius ``radius``, or the regular hexagon of inradius ``radius`` (flat-to-flat
        width ``2 radius``) whose three flat normals point at ``angle + k 60`` degrees.
    radius : float
        Disk radius or hexagon inradius.
    angle : float
        Direction of one flat normal, radians, measured like ``theta`` (hexagon only).
    """
    if shape == "circle":
        return dy**2 + dx**2 <= radius**2
    if shape != "hexagon":
        raise ValueError(f"lenslet shape must be 'circle' or 'hexagon', got {shape!r}")
    inside = torch.ones_like(dy, dtype=torch.bool)
    for k in range(3):
        normal = angle + k * math.pi / 3.0
        inside &= (dx * math.cos(normal) + dy * math.sin(normal)).abs() <= radius
    return inside


def aperture_circumradius(shape: str, radius: float) -> float:
    """Largest distance from the axis to a point of :func:`lenslet_aperture`: ``radius`` for a
    disk, ``2 radius / sqrt(3)`` for a hexagon of inradius ``radius``."""
    return radius if shape == "circle" else 2.0 * radius / math.sqrt(3.0)


def zernike_disk_radius(
    disk: str, pupil_radius: float, centers: Tensor, lenslet_circumradius: float
) -> float:
    """Radius of the Zernike unit disk (Eq. S4) about view 0's axis, in the unit of the inputs.

    Parameters
    ----------
    disk : {"pupil", "aperture"}
        ``"pupil"``: the objective-pupil image, ``pupil_radius``. ``"aperture"``: the circle
        circumscribing the light-carrying mask M, ``max_v |c_v - c_0| + lenslet_circumradius``,
        capped at the pupil (where an outer lenslet reaches past it, M ends at the pupil edge).
    pupil_radius : float
        Radius of the objective-pupil image at the MLA plane.
    centers : Tensor
        ``(V, 2)`` lenslet axes (row, col), view 0 first, in the same unit.
    lenslet_circumradius : float
        :func:`aperture_circumradius` of one lenslet.
    """
    if disk == "pupil":
        return pupil_radius
    reach = float((centers - centers[0]).double().norm(dim=1).max()) + lenslet_circumradius
    return min(pupil_radius, reach)


def lattice_angle(centers: Tensor, default: float = 0.0) -> float:
    """Orientation (radians, in ``(-30, 30]`` degrees) of a hexagonal lattice of lenslet centres.

    The direction, modulo 60 degrees, from view 0 to its neighbours (the centres within 1.25
    times the nearest-neighbour distance), averaged as ``arg(sum exp(6 i alpha)) / 6`` so that a
    rotated or slightly irregular calibrated array gives its mean rotation. 0 for the unrotated
    arrays of :func:`fgat.optics.lenslets.hexagonal_offsets`; ``-radians(rotation)`` for a
    system's nominal array turned by its ``lattice_rotation_deg`` (counter-clockwise as
    displayed, while this angle turns like ``theta``).

    Parameters
    ----------
    centers : Tensor
        ``(V, 2)`` lenslet centres (row, col), view 0 first.
    default : float
        The angle (radians) of a single centre, which has no neighbours to show it (e.g. the
        system's ``-radians(lattice_rotation_deg)``).
    """
    offsets = (centers[1:] - centers[0]).double()
    if offsets.shape[0] == 0:
        return float(default)
    distance = offsets.norm(dim=1)
    near = offsets[distance <= 1.25 * distance.min()]
    alpha = 6.0 * torch.atan2(near[:, 0], near[:, 1])
    return float(torch.atan2(torch.sin(alpha).sum(), torch.cos(alpha).sum())) / 6.0
