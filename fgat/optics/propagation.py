"""Fields in the pupil/MLA plane and their propagation to the camera (Eqs. S7-S8).

Every function works on pixel grids of pitch ``pixel_um`` (the angular-spectrum method keeps the
sampling of the plane it starts from: the camera pitch, or a fraction of it when the pupil plane
is oversampled) and returns phases in radians.
Constant (piston) phases are removed everywhere: they do not change an intensity and would
cost float32 precision.

Depth convention. A depth ``z`` (um) is the displacement of the point source inside the sample
medium (index ``n_s``) from the plane whose pupil phase is flat, positive away from the
objective: its pupil phase per um is ``2 pi / lambda sqrt(n_s^2 - (NA rho)^2)``
(:func:`defocus_phase_per_um`). A z-stack taken by moving the stage or the objective does not
step that depth: it changes the thickness of the immersion layer (Gibson-Lanni), whose pupil
phase per um is ``2 pi / lambda sqrt(n_i^2 - (NA rho)^2)``, the same function with
``sample_index = immersion_index``. With ``n_s != n_i`` the two differ in their dependence on
``rho``, not by one factor: at NA 1.3 with ``n_i = 1.406`` and ``n_s = 1.33`` a lenslet at
``rho = 0.3`` moves 0.94 times as far per stage um as per sample um, the pupil at ``rho = 0.9``
0.81 times and the outer views of ``small37`` (0.75 to 1.0) 0.75 times (the paraxial focal-shift
ratio ``n_s / n_i`` is 0.946), so a stage um is not a sample um of any fixed length
(:mod:`fgat.optics.depth_scale` calibrates against stage z-stacks with the immersion-layer
phase).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

APODIZATION_COS_FLOOR = 0.1  # smallest cos(theta) of emission_apodization (weight <= 3.16)


def _one_minus_sqrt_one_minus(q: Tensor) -> Tensor:
    """``1 - sqrt(1 - q)`` without cancellation for small ``q`` (``q`` clamped to [0, 1])."""
    q = q.clamp(0.0, 1.0)
    return q / (1.0 + torch.sqrt(1.0 - q))


def defocus_phase_per_um(
    rho: Tensor,
    *,
    wavelength_um: float,
    na: float,
    immersion_index: float,
    sample_index: float | None = None,
) -> Tensor:
    """High-NA defocus phase of an on-axis point per micrometre of depth (radians / um).

    Planar interfaces conserve ``NA rho = n sin(theta)`` (the sine condition), so the pupil
    field of a point source displaced by ``z`` along the axis in a sample of index ``n_s``
    carries the phase ``2 pi z / lambda * sqrt(n_s^2 - (NA rho)^2)``; this returns its derivative
    in ``z`` with the piston at ``rho = 0`` removed, so ``phase(z) = z * defocus_phase_per_um``.
    With ``n_s`` different from the immersion index this is not a paraxial defocus: the
    difference is the depth-dependent spherical aberration of the index mismatch. Where
    ``NA rho >= n_s`` (supercritical angles) the wave is evanescent in the sample and the phase
    is held at its critical-angle value; :func:`propagating_pupil` marks those points, which
    carry no light. ``z`` is a depth in the sample (module docstring); the phase per um of a
    stage or objective step is this function with ``sample_index = immersion_index``.

    Parameters
    ----------
    rho : Tensor
        Normalised pupil radius (1 at the pupil edge, where ``n sin(theta) = NA``).
    wavelength_um, na, immersion_index : float
        Vacuum wavelength (um), numerical aperture and refractive index of the immersion medium.
    sample_index : float, optional
        Refractive index ``n_s`` of the medium the point lies in; ``None``: the immersion index.
    """
    if na >= immersion_index:
        raise ValueError(f"na ({na}) must be smaller than the immersion index ({immersion_index})")
    index = immersion_index if sample_index is None else sample_index
    q = (na * rho / index) ** 2
    return -2.0 * math.pi * index / wavelength_um * _one_minus_sqrt_one_minus(q)


def emission_apodization(
    rho: Tensor, *, na: float, sample_index: float, cos_floor: float = APODIZATION_COS_FLOOR
) -> Tensor:
    """Pupil amplitude of an isotropic point emitter behind an aplanatic objective (relative).

    The sine condition maps the solid angle ``dOmega`` around the polar angle ``theta_s`` in the
    sample onto the pupil area ``dA ~ cos(theta_s) dOmega``, so light emitted evenly over
    angles arrives with intensity ``1 / cos(theta_s)`` per pupil area and amplitude
    ``cos(theta_s)^(-1/2)``, ``cos(theta_s) = sqrt(1 - (NA rho / n_s)^2)`` (the emission
    counterpart of the Richards-Wolf ``sqrt(cos)`` factor). The Fresnel transmission of the
    sample-coverslip-immersion interfaces is left out: for an isotropic emitter in water under
    a 1.406 immersion and a 1.518 coverslip its polarisation-averaged power transmittance is
    0.99-0.97 up to ``NA rho = 1.17`` and 0.80 at ``NA rho = 1.3``, which moves the parallax
    of a lenslet at ``rho = 0.9`` (NA 1.3) by 1%. ``cos(theta_s)`` is held at ``cos_floor``
    or above, so samples at the critical angle keep a finite weight.

    Parameters
    ----------
    rho : Tensor
        Normalised pupil radius (any shape).
    na, sample_index : float
        Numerical aperture and refractive index of the medium the emitter lies in.
    cos_floor : float
        Smallest ``cos(theta_s)`` used.

    Returns
    -------
    Tensor
        ``cos(theta_s)^(-1/2)``, 1 on the axis, the shape of ``rho``.
    """
    q = (na * rho / sample_index) ** 2
    return torch.sqrt(1.0 - q.clamp(0.0, 1.0)).clamp(min=cos_floor).rsqrt()


def propagating_pupil(rho: Tensor, *, na: float, sample_index: float) -> Tensor:
    """``True`` where the pupil point's plane wave propagates in the sample, ``NA rho < n_s``.

    Points with ``NA rho >= n_s`` collect only supercritical (evanescent) light of a point
    inside the sample, which this scalar far-field model does not describe; they are dark.
    """
    return na * rho < sample_index


def thin_lens_phase(
    rows: Tensor,
    cols: Tensor,
    center: Tensor,
    *,
    focal_um: float,
    pixel_um: float,
    wavelength_um: float,
) -> Tensor:
    """Converging thin-lens phase ``-pi |r - c|^2 / (lambda f)`` (radians) on a pixel grid.

    ``center`` is the lens axis ``(row, col)`` in pixels; it broadcasts against ``rows``/``cols``.
    """
    r2 = (rows - center[..., 0, None, None]) ** 2 + (cols - center[..., 1, None, None]) ** 2
    return -math.pi * r2 * pixel_um**2 / (wavelength_um * focal_um)


def frequency_grid(
    shape: tuple[int, int],
    pixel_um: float,
    *,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> tuple[Tensor, Tensor]:
    """Spatial frequencies ``(f_y, f_x)`` in cycles/um of an FFT grid, shape ``(H, W)``."""
    fy = torch.fft.fftfreq(shape[0], d=pixel_um, dtype=dtype, device=device)
    fx = torch.fft.fftfreq(shape[1], d=pixel_um, dtype=dtype, device=device)
    return torch.meshgrid(fy, fx, indexing="ij")


def angular_spectrum_transfer(
    shape: tuple[int, int],
    *,
    pixel_um: float,
    wavelength_um: float,
    distance_um: float,
    dtype: torch.dtype = torch.complex64,
    device: torch.device | str | None = None,
) -> Tensor:
    """Angular-spectrum transfer function ``H_ASM(f_x, f_y)`` of Eq. S8, FFT order, ``(H, W)``.

    ``exp(i 2 pi d (sqrt(1/lambda^2 - f^2) - 1/lambda))`` for propagating frequencies (the
    constant ``exp(i 2 pi d / lambda)`` is dropped) and zero for evanescent ones.
    """
    real = torch.float64
    fy, fx = frequency_grid(shape, pixel_um, dtype=real, device=device)
    q = (wavelength_um**2) * (fx * fx + fy * fy)
    phase = -2.0 * math.pi * distance_um / wavelength_um * _one_minus_sqrt_one_minus(q)
    transfer = torch.polar(torch.ones_like(phase), phase) * (q < 1.0)
    return transfer.to(dtype)


def angular_spectrum_propagate(field: Tensor, transfer: Tensor) -> Tensor:
    """Propagate complex fields ``(..., H, W)`` with a transfer function ``(H, W)`` (Eq. S8)."""
    return torch.fft.ifft2(torch.fft.fft2(field) * transfer)


def quartic_phase_coefficient(*, wavelength_um: float, distance_um: float) -> float:
    """Leading angular-spectrum phase beyond the Fresnel (paraxial) term: ``-K |f|^4``.

    ``2 pi d (sqrt(1/lambda^2 - f^2) - 1/lambda + lambda f^2 / 2) = -K |f|^4 (1 + O(q))`` with
    ``K = pi d lambda^3 / 4`` (radians um^4) for ``f`` in cycles/um and ``q = lambda^2 f^2``;
    the relative error of the quartic term is below ``q / 2`` (``< 1e-3`` for frequencies under
    the Nyquist limit of 6.5-um pixels at visible wavelengths).
    """
    return math.pi * distance_um * wavelength_um**3 / 4.0
