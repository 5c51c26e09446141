"""An optics spec: everything the JPGM needs to make a PSF stack, as one frozen value.

A reconstruction carries its optics as an :class:`OpticsSpec` (the system, the PSF planes, the
lenslet centres and the JPGM parameters ``c_j``, ``b_v``, ``s_v`` of Eqs. S5-S10); the
self-estimation starts from it, a phantom's true optics are one, and :meth:`OpticsSpec.jpgm`
is the one place that turns a spec into a :class:`~fgat.optics.psf.JPGM`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
import torch

from fgat.optics.psf import JPGM
from fgat.optics.systems import FLFMSystem


@dataclass(frozen=True, eq=False)
class OpticsSpec:
    """The optics a PSF stack ``(V, Z, h, w)`` is made from.

    Attributes
    ----------
    system : FLFMSystem
        Objective, Fourier lens, MLA and camera.
    depths_um : tuple of float
        ``(Z,)`` PSF planes relative to the native focal plane, um.
    centers_px : numpy.ndarray or None
        ``(V, 2)`` lenslet centres (row, col) pixels; ``None``: the system's nominal MLA.
    zernike : dict
        Noll index -> pupil coefficient ``c_j`` in waves (Eq. S5); absent terms are zero.
    intercepts, slopes : dict
        View -> ``(row, col)`` PSF shift ``b_v`` (pixels) and ``s_v`` (pixels per unit ``xi``),
        Eq. S10; absent views are unshifted.
    """

    system: FLFMSystem
    depths_um: tuple[float, ...]
    centers_px: np.ndarray | None = None
    zernike: dict = field(default_factory=dict)
    intercepts: dict = field(default_factory=dict)
    slopes: dict = field(default_factory=dict)

    def jpgm(self, **options) -> JPGM:
        """The JPGM with these parameters set; ``options`` as :class:`~fgat.optics.psf.JPGM`'s
        constructor (``zernike_indices``, ``dtype``, ``device``, ``method``, ...)."""
        return JPGM.with_parameters(
            self.system,
            list(self.depths_um),
            centers_px=self.centers_px,
            zernike=self.zernike,
            intercepts=self.intercepts,
            slopes=self.slopes,
            **options,
        )

    def psf(self, **options) -> np.ndarray:
        """The PSF stack ``(V, Z, h, w)`` of :meth:`jpgm` as a float32 array."""
        with torch.no_grad():
            return self.jpgm(**options)().float().cpu().numpy()

    def ideal(self) -> OpticsSpec:
        """The same system, planes and centres without aberrations or shifts (3DGAT's
        assumption)."""
        return dataclasses.replace(self, zernike={}, intercepts={}, slopes={})

    def parameters(
        self, zernike_indices, n_views: int
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(c (K,), b (V, 2), s (V, 2))`` float32 tensors on ``zernike_indices`` and ``n_views``
        views (zero where the spec has no entry)."""
        coefficients = torch.tensor([float(self.zernike.get(j, 0.0)) for j in zernike_indices])
        intercepts, slopes = (
            torch.tensor(
                [list(table.get(v, (0.0, 0.0))) for v in range(n_views)], dtype=torch.float32
            )
            for table in (self.intercepts, self.slopes)
        )
        return coefficients, intercepts, slopes
