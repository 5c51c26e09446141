"""Losses of the two stages: image-domain terms (Eqs. S23-S25), the static loss (Eqs. S27-S28)
and the dynamic loss with its plane regularisers (Eqs. S29-S32).

Images are per-view predictions and measurements ``(V, H, W)``; every term is averaged over
views as well as pixels.
"""

from __future__ import annotations

import torch
from torch import Tensor

from fgat.dynamics.hexplane import HexPlane
from fgat.dynamics.regularizers import plane_l1_to_one, plane_tv, temporal_smoothness
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
    """Annealed Fourier weight ``lambda_F(k) = lambda_F^0 (0.8 (1 - k / k_stat) + 0.2)``
    (Eq. S28)."""
    progress = min(max(step / max(total_steps, 1), 0.0), 1.0)
    return initial * (0.8 * (1.0 - progress) + 0.2)


def image_loss(
    prediction: Tensor,
    target: Tensor,
    *,
    p: int = 1,
    lambda_fourier: float = 0.0,
    lambda_ssim: float = 0.0,
    data_range: float = 1.0,
) -> dict[str, Tensor]:
    """``L_pix + lambda_F L_fft + lambda_S L_ssim`` and its terms (terms with a zero weight are
    not computed): a dict with ``total``, ``pix`` and, where active, ``fft`` and ``ssim``."""
    terms = {"pix": pixel_loss(prediction, target, p)}
    total = terms["pix"]
    if lambda_fourier > 0:
        terms["fft"] = fourier_loss(prediction, target)
        total = total + lambda_fourier * terms["fft"]
    if lambda_ssim > 0:
        terms["ssim"] = ssim_loss(prediction, target, data_range)
        total = total + lambda_ssim * terms["ssim"]
    return {"total": total, **terms}


def static_loss(
    prediction: Tensor,
    target: Tensor,
    *,
    step: int,
    total_steps: int,
    p: int = 1,
    lambda_fourier: float = 0.0,
    lambda_ssim: float = 0.0,
    data_range: float = 1.0,
) -> dict[str, Tensor]:
    """``L_stat = L_pix + lambda_F(k) L_fft + lambda_S L_ssim`` (Eq. S27, lambda_F(k) of Eq. S28)
    and its terms (see :func:`image_loss`)."""
    return image_loss(
        prediction,
        target,
        p=p,
        lambda_fourier=fourier_weight(step, total_steps, lambda_fourier),
        lambda_ssim=lambda_ssim,
        data_range=data_range,
    )


def dynamic_loss(
    prediction: Tensor,
    target: Tensor,
    hexplane: HexPlane,
    *,
    p: int = 1,
    lambda_fourier: float = 0.0,
    lambda_ssim: float = 0.0,
    lambda_tv: float = 1e-4,
    lambda_sm: float = 1e-3,
    lambda_l1: float = 1e-4,
    data_range: float = 1.0,
) -> dict[str, Tensor]:
    """``L_dyn = L_img^(t) + L_reg`` (Eq. S29) and its terms.

    ``L_img^(t) = (L_pix + lambda_F L_fft + lambda_S L_ssim) / (1 + lambda_S)`` on one frame
    (lambda_F constant), and ``L_reg = lambda_TV L_TV + lambda_sm L_sm + lambda_l1 L_l1`` on the
    HexPlane's planes (Eqs. S30-S32; the defaults are the note's weights). Returns ``total``,
    ``img``, the image terms of :func:`image_loss` and ``tv``, ``sm``, ``l1`` where weighted.
    """
    image = image_loss(
        prediction,
        target,
        p=p,
        lambda_fourier=lambda_fourier,
        lambda_ssim=lambda_ssim,
        data_range=data_range,
    )
    terms = {name: value for name, value in image.items() if name != "total"}
    terms["img"] = image["total"] / (1 + lambda_ssim)
    total = terms["img"]
    spatiotemporal = hexplane.spatiotemporal_planes()
    for name, weight, regulariser, planes in (
        ("tv", lambda_tv, plane_tv, list(hexplane.planes)),
        ("sm", lambda_sm, temporal_smoothness, spatiotemporal),
        ("l1", lambda_l1, plane_l1_to_one, spatiotemporal),
    ):
        if weight > 0:
            terms[name] = regulariser(planes)
            total = total + weight * terms[name]
    return {"total": total, **terms}
