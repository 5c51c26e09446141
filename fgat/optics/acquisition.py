"""The FLFM forward model of a real acquisition: per-view gains and a lateral guard band.

A real camera's view ``v`` is the ideal view of Eqs. S3/S52 scaled by a gain ``g_v`` (vignetting,
MLA transmission: outer views of a real MLA are dimmer, 0.7-1.0). And a real sample does not end
at the edge of the field of view: objects just outside it send light into the views, which a
reconstruction on a grid the size of the views can only explain with its border voxels (a bright
square frame). :class:`MeasuredOperator` therefore reconstructs on a grid padded laterally by a
guard band of ``g`` voxels on each side, ``(Z, Y + 2g, X + 2g)``, predicts only the central
``(V, Y, X)`` views, and :meth:`MeasuredOperator.crop` returns the central ``(Z, Y, X)`` volume::

    forward(V) = G C A V          adjoint(r) = A^T C^T G r

with ``A`` the :class:`~fgat.optics.operator.FLFMOperator` of the padded grid (Eqs. S52, S53),
``C`` the central crop of its views, ``C^T`` zero-padding by ``g`` and ``G = diag(g_v)`` the
gains. The guard band that holds
(almost) all of the light of an object just outside the field is the PSF's support radius,
:func:`psf_support_radius`.
"""

from __future__ import annotations

import copy

import numpy as np
import torch
from torch import Tensor

from fgat.optics.operator import FLFMOperator


def padded_shape(volume_shape: tuple[int, int, int], guard_px: int) -> tuple[int, int, int]:
    """The reconstruction grid ``(Z, Y + 2g, X + 2g)`` of an output grid ``(Z, Y, X)``."""
    z, y, x = (int(n) for n in volume_shape)
    return (z, y + 2 * guard_px, x + 2 * guard_px)


def crop_guard(volume: Tensor | np.ndarray, guard_px: int) -> Tensor | np.ndarray:
    """The central ``(..., Z, Y, X)`` of a volume ``(..., Z, Y + 2g, X + 2g)`` padded by a guard
    band of ``g = guard_px`` voxels (a view, not a copy)."""
    g = int(guard_px)
    return volume[..., g : volume.shape[-2] - g, g : volume.shape[-1] - g]


def psf_support_radius(psf_stack: Tensor | np.ndarray, fraction: float = 0.999) -> int:
    """Smallest Chebyshev radius around the PSF crops' centre that holds ``fraction`` of the light.

    For each view ``v`` and depth ``z``, the energy of ``H_{v,z}`` inside the square
    ``|i - h // 2| <= r, |j - w // 2| <= r`` (Chebyshev distance ``r`` from the crop centre, the
    PSF origin of :class:`~fgat.optics.operator.FLFMOperator`) grows with ``r``; the radius is the
    smallest ``r`` at which it reaches ``fraction`` of that crop's total, maximised over views and
    depths (all-zero crops are skipped). A lateral guard band of this many voxels catches that
    fraction of the light an object just outside the field of view sends into it (the guard band
    is a square frame, hence the Chebyshev distance). The parallax shift of a defocused view's
    PSF is part of its radius.

    Parameters
    ----------
    psf_stack : Tensor or numpy.ndarray
        ``(V, Z, h, w)`` PSF stack (intensity; the absolute value is used).
    fraction : float
        Energy fraction in ``(0, 1]``.

    Returns
    -------
    int
        Radius in pixels (= lateral voxels), ``0 <= r <= max(h // 2, w // 2, ...)``.
    """
    if not 0 < fraction <= 1:
        raise ValueError(f"fraction must be in (0, 1], got {fraction!r}")
    if isinstance(psf_stack, Tensor):
        psf_stack = psf_stack.detach().cpu().numpy()
    psf = np.abs(np.asarray(psf_stack, dtype=np.float64))
    if psf.ndim != 4:
        raise ValueError(f"psf_stack must have shape (V, Z, h, w), got {psf.shape}")
    h, w = psf.shape[2:]
    ring = np.maximum(
        np.abs(np.arange(h) - h // 2)[:, None], np.abs(np.arange(w) - w // 2)[None, :]
    ).ravel()
    order = np.argsort(ring, kind="stable")
    # Cumulative energy over pixels sorted by ring, read at each ring's last pixel: (V Z, R).
    ends = np.searchsorted(ring[order], np.arange(int(ring.max()) + 1), side="right") - 1
    cumulative = np.cumsum(psf.reshape(-1, h * w)[:, order], axis=1)[:, ends]
    total = cumulative[:, -1]
    lit = total > 0
    if not lit.any():
        return 0
    inside = cumulative[lit] >= fraction * total[lit, None]
    return int(inside.argmax(axis=1).max())


GUARD_ENERGY = 0.99  # PSF energy inside the automatic guard band


def guard_band(guard: int | str, psf_stack: Tensor | np.ndarray, max_px: int | None = None) -> int:
    """A guard band in voxels: ``guard`` itself (a non-negative integer), or for ``"auto"``
    :func:`psf_support_radius` of ``psf_stack`` at ``GUARD_ENERGY``, at most ``max_px`` (e.g.
    half the view: light from farther out is a small fraction of the field's)."""
    if guard == "auto":
        radius = psf_support_radius(psf_stack, fraction=GUARD_ENERGY)
        return radius if max_px is None else min(radius, int(max_px))
    if isinstance(guard, bool) or not isinstance(guard, (int, np.integer)) or guard < 0:
        raise ValueError(f"guard_px must be a non-negative integer or 'auto', got {guard!r}")
    return int(guard)


class MeasuredOperator:
    """The measured views of a padded volume: ``(..., Z, Y+2g, X+2g) -> (..., V, Y, X)``.

    ``forward(V)[v] = g_v [A V]_v[g : g + Y, g : g + X]`` with ``A`` the
    :class:`~fgat.optics.operator.FLFMOperator` (Eqs. S3, S52) of the padded grid, and
    :meth:`adjoint` its exact adjoint (gains, zero-padding by ``g``, ``A^T`` of Eq. S53). With
    ``guard_px=0`` and ``gains=None`` both are exactly the FLFMOperator's.

    Parameters
    ----------
    psf_stack : Tensor
        ``(V, Z, h, w)`` real PSFs, float32 or float64 (sets the precision; gradients flow to it
        through the OTFs).
    view_shape : (int, int)
        ``(Y, X)`` of each measured view, pixels.
    guard_px : int
        Lateral guard band ``g`` in voxels on each side of the reconstruction grid.
    gains : Tensor or array-like, optional
        ``(V,)`` positive per-view gains (dimensionless); default all 1. A tensor that requires
        grad stays differentiable through :meth:`forward`.

    Attributes
    ----------
    operator : FLFMOperator
        ``A`` on the padded grid.
    volume_shape : (int, int, int)
        The padded grid ``(Z, Y + 2g, X + 2g)`` it acts on.
    view_shape, guard_px, n_views, psf_shape, gains
        As given (``gains`` a tensor of the operator's dtype and device, or ``None``).
    """

    def __init__(
        self,
        psf_stack: Tensor,
        view_shape: tuple[int, int],
        guard_px: int = 0,
        gains: Tensor | np.ndarray | None = None,
    ) -> None:
        if len(view_shape) != 2 or not all(int(n) > 0 for n in view_shape):
            raise ValueError(f"view_shape must be (Y, X) positive sizes, got {view_shape!r}")
        if isinstance(guard_px, bool) or int(guard_px) != guard_px or guard_px < 0:
            raise ValueError(f"guard_px must be a non-negative integer, got {guard_px!r}")
        if not isinstance(psf_stack, Tensor):
            psf_stack = torch.as_tensor(psf_stack)
        self.view_shape = (int(view_shape[0]), int(view_shape[1]))
        self.guard_px = int(guard_px)
        self.operator = FLFMOperator(
            psf_stack, padded_shape((psf_stack.shape[1], *self.view_shape), self.guard_px)
        )
        self.gains = None if gains is None else self._check_gains(gains)

    def _check_gains(self, gains) -> Tensor:
        gains = torch.as_tensor(gains).to(dtype=self.dtype, device=self.device)
        if gains.shape != (self.n_views,):
            raise ValueError(f"gains must have shape ({self.n_views},), got {tuple(gains.shape)}")
        if not (torch.isfinite(gains).all() and (gains > 0).all()):
            raise ValueError("gains must be finite and positive")
        return gains

    @property
    def volume_shape(self) -> tuple[int, int, int]:
        return self.operator.volume_shape

    @property
    def n_views(self) -> int:
        return self.operator.n_views

    @property
    def psf_shape(self) -> tuple[int, int]:
        return self.operator.psf_shape

    @property
    def dtype(self) -> torch.dtype:
        return self.operator.dtype

    @property
    def device(self) -> torch.device:
        return self.operator.device

    def forward(self, volume: Tensor) -> Tensor:
        """Measured views ``(..., V, Y, X)`` of a padded volume ``(..., Z, Y+2g, X+2g)``."""
        g, (y, x) = self.guard_px, self.view_shape
        views = self.operator.forward(volume)[..., g : g + y, g : g + x]
        return views if self.gains is None else views * self.gains[:, None, None]

    __call__ = forward

    def adjoint(self, views: Tensor) -> Tensor:
        """Exact adjoint: a padded volume ``(..., Z, Y+2g, X+2g)`` from views ``(..., V, Y, X)``."""
        if views.shape[-3:] != (self.n_views, *self.view_shape):
            raise ValueError(
                f"views must end in shape {(self.n_views, *self.view_shape)}, "
                f"got {tuple(views.shape)}"
            )
        views = views.to(self.dtype)
        if self.gains is not None:
            views = views * self.gains[:, None, None]
        g = self.guard_px
        if g:
            views = torch.nn.functional.pad(views, (g, g, g, g))
        return self.operator.adjoint(views)

    def crop(self, volume: Tensor | np.ndarray) -> Tensor | np.ndarray:
        """The central ``(..., Z, Y, X)`` of a padded volume ``(..., Z, Y+2g, X+2g)`` (a view)."""
        if tuple(volume.shape[-2:]) != self.volume_shape[1:]:
            raise ValueError(
                f"volume must end in shape {self.volume_shape[1:]}, got {tuple(volume.shape)}"
            )
        return crop_guard(volume, self.guard_px)

    def with_gains(self, gains: Tensor | np.ndarray | None) -> MeasuredOperator:
        """This operator with other ``gains`` ``(V,)`` (``None``: all 1), sharing its OTFs (no
        FFT is recomputed; for gains that change every step, e.g. estimated ones)."""
        other = copy.copy(self)
        other.gains = None if gains is None else self._check_gains(gains)
        return other

    def pad(self, volume: Tensor) -> Tensor:
        """Zero-pad a volume ``(..., Z, Y, X)`` to the padded grid ``(..., Z, Y+2g, X+2g)``."""
        g = self.guard_px
        return torch.nn.functional.pad(volume, (g, g, g, g)) if g else volume
