"""Noll-indexed Zernike polynomials on the unit disk (Noll 1976).

Conventions: Noll index ``j >= 1`` maps to radial order ``n`` and azimuthal frequency ``m``;
polynomials are RMS-normalised over the unit disk (``sqrt(n + 1)`` for ``m = 0``,
``sqrt(2 (n + 1))`` otherwise), use ``cos(m theta)`` for even ``j`` and ``sin(|m| theta)`` for
odd ``j`` when ``m != 0``, and are zero outside ``rho > 1``. With this normalisation the RMS of
an aberration ``sum_j c_j Z_j`` over the pupil is the 2-norm of ``c``.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from functools import cache

import torch
from torch import Tensor

DEFAULT_INDICES = tuple(range(5, 22))
"""The active Noll set J = {5, ..., 21} of Eq. S5 (K = 17)."""


@cache
def noll_to_nm(j: int) -> tuple[int, int]:
    """Radial order ``n`` and signed azimuthal frequency ``m`` of Noll index ``j``.

    ``m > 0`` for even ``j`` (cosine terms), ``m < 0`` for odd ``j`` (sine terms).
    """
    if not isinstance(j, int) or j < 1:
        raise ValueError(f"Noll index must be an integer >= 1, got {j!r}")
    n, remaining = 0, j - 1
    while remaining > n:
        n += 1
        remaining -= n
    m_abs = (n % 2) + 2 * ((remaining + ((n + 1) % 2)) // 2)
    return n, m_abs if (j % 2 == 0 or m_abs == 0) else -m_abs


FAMILIES = {
    (0, 0): "Piston",
    (1, 1): "Tilt",
    (2, 0): "Defocus",
    (2, 2): "Astigmatism",
    (3, 1): "Coma",
    (3, 3): "Trefoil",
    (4, 0): "Spherical",
    (4, 2): "Sec. astigmatism",
    (4, 4): "Quadrafoil",
    (5, 1): "Sec. coma",
    (5, 3): "Sec. trefoil",
    (5, 5): "Pentafoil",
    (6, 0): "Sec. spherical",
    (6, 2): "Ter. astigmatism",
    (6, 4): "Sec. quadrafoil",
    (6, 6): "Hexafoil",
}
"""Aberration family of each ``(n, |m|)`` up to the sixth radial order (Tables S2-S5)."""


def zernike_family(j: int) -> str:
    """Family name of Noll index ``j`` (``"Coma"`` for 7 and 8, ``"Sec. trefoil"`` for 18 and
    19, ...; ``"n=7, |m|=1"`` beyond the sixth radial order)."""
    n, m = noll_to_nm(j)
    return FAMILIES.get((n, abs(m)), f"n={n}, |m|={abs(m)}")


@cache
def _radial_coefficients(n: int, m_abs: int) -> tuple[int, ...]:
    """Coefficients of R_n^m as a polynomial in rho^2, highest power first, times rho^|m|."""
    return tuple(
        (-1) ** k
        * math.factorial(n - k)
        // (
            math.factorial(k)
            * math.factorial((n + m_abs) // 2 - k)
            * math.factorial((n - m_abs) // 2 - k)
        )
        for k in range((n - m_abs) // 2 + 1)
    )


def zernike_radial(n: int, m: int, rho: Tensor) -> Tensor:
    """Radial polynomial ``R_n^|m|(rho)`` (un-normalised, ``R(1) = 1``), by Horner's rule."""
    rho2 = rho * rho
    value = torch.zeros_like(rho)
    for coefficient in _radial_coefficients(n, abs(m)):
        value = value * rho2 + coefficient
    return value * rho ** abs(m)


def zernike(j: int, rho: Tensor, theta: Tensor) -> Tensor:
    """Noll Zernike polynomial ``Z_j(rho, theta)``, RMS-normalised, zero where ``rho > 1``.

    Parameters
    ----------
    j : int
        Noll index, ``j >= 1``.
    rho, theta : Tensor
        Normalised radius (1 at the aperture edge) and azimuth in radians, same shape.

    Returns
    -------
    Tensor
        ``Z_j`` with the shape, dtype and device of ``rho``.
    """
    n, m = noll_to_nm(j)
    radial = zernike_radial(n, m, rho)
    if m == 0:
        value = math.sqrt(n + 1) * radial
    else:
        angular = torch.cos(m * theta) if m > 0 else torch.sin(-m * theta)
        value = math.sqrt(2 * (n + 1)) * radial * angular
    return torch.where(rho <= 1, value, torch.zeros_like(value))


def zernike_basis(indices: Iterable[int], rho: Tensor, theta: Tensor) -> Tensor:
    """Stack ``Z_j`` for every Noll index in ``indices``: shape ``(K, *rho.shape)``."""
    indices = tuple(indices)
    if not indices:
        return rho.new_zeros((0, *rho.shape))
    return torch.stack([zernike(j, rho, theta) for j in indices])


def zernike_phase(coefficients_waves: Tensor, basis: Tensor) -> Tensor:
    """Pupil phase ``phi_Z = 2 pi sum_j c_j Z_j`` in radians (Eq. S5).

    Parameters
    ----------
    coefficients_waves : Tensor
        ``(K,)`` Zernike coefficients in waves.
    basis : Tensor
        ``(K, H, W)`` basis from :func:`zernike_basis`.

    Returns
    -------
    Tensor
        ``(H, W)`` phase in radians.
    """
    if coefficients_waves.shape != basis.shape[:1]:
        raise ValueError(
            f"zernike coefficients have shape {tuple(coefficients_waves.shape)}, "
            f"expected ({basis.shape[0]},) to match the basis"
        )
    return 2.0 * math.pi * torch.tensordot(coefficients_waves.to(basis.dtype), basis, dims=1)


def wavefront_map(indices: Iterable[int], coefficients_waves, size: int = 128) -> Tensor:
    """The wavefront ``sum_j c_j Z_j`` in waves over the unit pupil, sampled on a ``(size, size)``
    grid of pixel centres spanning [-1, 1]; NaN outside the pupil (float64, for display).

    Parameters
    ----------
    indices : iterable of int
        ``(K,)`` Noll indices.
    coefficients_waves : array-like
        ``(K,)`` coefficients in waves.
    size : int
        Pixels across the pupil.
    """
    coefficients = (
        torch.as_tensor(coefficients_waves, dtype=torch.float64).detach().cpu().reshape(-1)
    )
    axis = (torch.arange(size, dtype=torch.float64) + 0.5) / size * 2 - 1
    rows, cols = torch.meshgrid(axis, axis, indexing="ij")
    rho, theta = torch.sqrt(rows**2 + cols**2), torch.atan2(rows, cols)
    basis = zernike_basis(indices, rho, theta)
    if coefficients.shape != basis.shape[:1]:
        raise ValueError(
            f"{coefficients.numel()} coefficients for {basis.shape[0]} Zernike indices"
        )
    waves = torch.tensordot(coefficients, basis, dims=1)
    return torch.where(rho <= 1, waves, torch.full_like(waves, float("nan")))
