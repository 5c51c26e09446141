"""Image-domain losses of the static stage (Eqs. S23-S28).

Images are per-view predictions and measurements ``(V, H, W)``; every term is averaged over
views as well as pixels.
"""

from __future__ import annotations

import torch
from torch import Tensor

from fgat.metrics import ssim


def pixel_loss(prediction: Tensor, target: Tensor, p: int = 1) -> Tensor:
    """``L_pix^(p) = mean |A - B|^p`` (Eq. S23): MAE for ``p = 1``, MSE for ``p = 2``."""
    if p not in (1, 2):
        raise ValueError(f"p must be 1 or 2, got {p!r}")
    difference = prediction - target
    return difference.abs().mean() if p == 1 else difference.square().mean()


def fourier_loss(prediction: Tensor, target: Tensor) -> Tensor:
    """``L_fft = 1/(HW) sum |F(A) - F(B)|`` (Eq. S24), unnormalised 2D DFT, averaged over views."""
    return (torch.fft.fft2(prediction) - torch.fft.fft2(target)).abs().mean()


def ssim_loss(prediction: Tensor, target: Tensor, data_range: float) -> Tensor:
    """``L_ssim = 1 - SSIM(A, B)`` (Eq. S25), 2D SSIM per view (Gaussian window, sigma 1.5)."""
    return 1.0 - ssim(prediction, target, data_range, spatial_dims=2)


def fourier_weight(step: int, total_steps: int, initial: float) -> float:
    """Annealed Fourier weight ``lambda_F(k) = lambda_F^0 (0.8 (1 - k / k_stat) + 0.2)`` (Eq. S28)."""
    progress = min(max(step / max(total_steps, 1), 0.0), 1.0)
    return initial * (0.8 * (1.0 - progress) + 0.2)


def static_loss(prediction: Tensor, target: Tensor, *, step: int, total_steps: int, p: int = 1,
                lambda_fourier: float = 0.0, lambda_ssim: float = 0.0, data_range: float = 1.0) -> dict[str, Tensor]:
    """``L_stat = L_pix + lambda_F(k) L_fft + lambda_S L_ssim`` (Eq. S27) and its terms.

    Terms with a zero weight are not computed. Returns a dict with ``total``, ``pix`` and, where
    active, ``fft`` and ``ssim``.
    """
    terms = {"pix": pixel_loss(prediction, target, p)}
    total = terms["pix"]
    weight = fourier_weight(step, total_steps, lambda_fourier)
    if weight > 0:
        terms["fft"] = fourier_loss(prediction, target)
        total = total + weight * terms["fft"]
    if lambda_ssim > 0:
        terms["ssim"] = ssim_loss(prediction, target, data_range)
        total = total + lambda_ssim * terms["ssim"]
    return {"total": total, **terms}
