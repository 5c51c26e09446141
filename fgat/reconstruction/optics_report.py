"""The estimated optics as logged numbers: the JPGM parameters and, on phantoms, their errors."""

from __future__ import annotations

import math

from torch import Tensor

from fgat.optics.estimation import psf_errors, remove_scene_gauge
from fgat.optics.psf import JPGM
from fgat.reconstruction import names


def parameter_metrics(
    indices, coefficients: Tensor, intercepts: Tensor, slopes: Tensor
) -> dict[str, float]:
    """``zernike/c{j}`` (waves), ``shift/b{v}_y``, ``shift/b{v}_x``, ``shift/s{v}_y``,
    ``shift/s{v}_x`` (pixels)."""
    metrics = {
        names.zernike_name(j): float(c) for j, c in zip(indices, coefficients.detach().tolist())
    }
    for kind, values in (("b", intercepts), ("s", slopes)):
        for v, (row, col) in enumerate(values.detach().tolist()):
            metrics[names.shift_name(kind, v, "y")], metrics[names.shift_name(kind, v, "x")] = (
                row,
                col,
            )
    return metrics


def optics_metrics(jpgm: JPGM) -> dict[str, float]:
    """:func:`parameter_metrics` of a JPGM's current parameters."""
    return parameter_metrics(
        jpgm.zernike_indices, jpgm.zernike_coefficients, jpgm.intercepts, jpgm.slopes
    )


def optics_errors(
    jpgm: JPGM, truth: tuple[Tensor, Tensor, Tensor], psf: Tensor, true_psf: Tensor
) -> dict[str, float]:
    """Distance of the estimated optics to the truth ``(c (K,), b (V, 2), s (V, 2))``:
    ``zernike/residual_normalized`` ``||c - c_gt|| / ||c_gt||`` (sigma of Fig. S9a; NaN without
    aberration), the largest intercept and slope errors (pixels), also without the part a moved
    scene explains (:func:`~fgat.optics.estimation.remove_scene_gauge`), and the relative errors
    of the PSF stack ``psf`` to ``true_psf`` (:func:`~fgat.optics.estimation.psf_errors`)."""
    coefficients, intercepts, slopes = (t.to(jpgm.intercepts) for t in truth)
    norm = coefficients.norm()  # no aberration (Fig. S5): sigma undefined
    residual = (
        (jpgm.zernike_coefficients.detach() - coefficients).norm() / norm if norm > 0 else math.nan
    )
    metrics = {names.ZERNIKE_RESIDUAL: float(residual)}
    offsets = jpgm.centers - jpgm.centers[:1]
    errors = iter(names.SHIFT_ERRORS)  # (intercept, intercept gauge-free, slope, slope gauge-free)
    for estimate, true in ((jpgm.intercepts, intercepts), (jpgm.slopes, slopes)):
        difference = estimate.detach() - true
        metrics[next(errors)] = float(difference.abs().max())
        metrics[next(errors)] = float(remove_scene_gauge(difference, offsets).abs().max())
    return {**metrics, **psf_errors(psf, true_psf, names.PSF_ERROR)}
