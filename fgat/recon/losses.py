"""Losses of the two stages: image-domain terms (Eqs. S23-S25), the static loss (Eqs. S27-S28)
and the dynamic loss with its plane regularisers (Eqs. S29-S32).

Images are per-view predictions and measurements ``(V, H, W)``; every term is averaged over
views as well as pixels. Every image term takes an optional pixel ``mask`` broadcastable to
``(V, H, W)`` (1: use, 0: ignore, e.g. hot pixels): the pixel loss is then the mean over the
unmasked pixels (a ``mask``-weighted mean), and the Fourier and SSIM terms compare
``mask * prediction`` with ``mask * target``. ``mask=None`` is the unmasked loss.
"""

from __future__ import annotations

import torch
from torch import Tensor

from fgat.dynamics.hexplane import HexPlane
from fgat.dynamics.regularizers import plane_regularisers
from fgat.recon.metrics import gaussian_blur, ssim


def apply_mask(prediction: Tensor, target: Tensor, mask: Tensor | None) -> tuple[Tensor, Tensor]:
    """``(mask * prediction, mask * target)``; the inputs themselves when ``mask`` is ``None``."""
    if mask is None:
        return prediction, target
    return prediction * mask, target * mask


def pixel_loss(
    prediction: Tensor, target: Tensor, p: int = 1, mask: Tensor | None = None
) -> Tensor:
    """``L_pix^(p) = mean |A - B|^p`` (Eq. S23): MAE for ``p = 1``, MSE for ``p = 2``; with a
    ``mask`` the mean runs over the unmasked pixels only, ``sum m |A - B|^p / sum m``."""
    if p not in (1, 2):
        raise ValueError(f"p must be 1 or 2, got {p!r}")
    difference = prediction - target
    if mask is None:
        return difference.abs().mean() if p == 1 else difference.square().mean()
    mask = mask.to(difference).expand_as(difference)
    # Masked pixels count exactly zero, however far off they are (a hot pixel's square may
    # overflow, and inf * 0 is NaN).
    difference = torch.where(mask > 0, difference, 0.0)
    error = difference.abs() if p == 1 else difference.square()
    return (error * mask).sum() / mask.sum().clamp(min=1e-12)


def blurred_pixel_loss(
    prediction: Tensor,
    target: Tensor,
    p: int = 1,
    mask: Tensor | None = None,
    blur_px: float = 0.0,
) -> Tensor:
    """:func:`pixel_loss` of views ``mask * A`` and ``mask * B`` ``(..., H, W)``, each blurred
    over its last two axes by a Gaussian of standard deviation ``blur_px`` pixels
    (:func:`~fgat.recon.metrics.gaussian_blur`): the coarse-to-fine data loss of JPGM events;
    :func:`pixel_loss` itself for ``blur_px`` 0."""
    if blur_px == 0:
        return pixel_loss(prediction, target, p, mask)
    prediction, target = apply_mask(prediction, target, mask)
    return pixel_loss(gaussian_blur(prediction, blur_px), gaussian_blur(target, blur_px), p)


def fourier_loss(prediction: Tensor, target: Tensor, mask: Tensor | None = None) -> Tensor:
    """``L_fft = 1/(HW) sum |F(A) - F(B)|`` (Eq. S24), unnormalised 2D DFT, averaged over views
    (of ``mask * A`` and ``mask * B`` with a mask)."""
    prediction, target = apply_mask(prediction, target, mask)
    return (torch.fft.fft2(prediction) - torch.fft.fft2(target)).abs().mean()


def ssim_loss(
    prediction: Tensor, target: Tensor, data_range: float, mask: Tensor | None = None
) -> Tensor:
    """``L_ssim = 1 - SSIM(A, B)`` (Eq. S25), 2D SSIM per view (Gaussian window, sigma 1.5) (of
    ``mask * A`` and ``mask * B`` with a mask)."""
    prediction, target = apply_mask(prediction, target, mask)
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
    mask: Tensor | None = None,
) -> dict[str, Tensor]:
    """``L_pix + lambda_F L_fft + lambda_S L_ssim`` and its terms (terms with a zero weight are
    not computed): a dict with ``total``, ``pix`` and, where active, ``fft`` and ``ssim``;
    ``mask`` (broadcastable to ``(V, H, W)``, 1 = use) as in the module docstring."""
    terms = {"pix": pixel_loss(prediction, target, p, mask)}
    total = terms["pix"]
    if lambda_fourier > 0:
        terms["fft"] = fourier_loss(prediction, target, mask)
        total = total + lambda_fourier * terms["fft"]
    if lambda_ssim > 0:
        terms["ssim"] = ssim_loss(prediction, target, data_range, mask)
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
    mask: Tensor | None = None,
) -> dict[str, Tensor]:
    """``L_stat = L_pix + lambda_F(k) L_fft + lambda_S L_ssim`` (Eq. S27, lambda_F(k) of Eq. S28)
    and its terms (see :func:`image_loss`, also for ``mask``)."""
    return image_loss(
        prediction,
        target,
        p=p,
        lambda_fourier=fourier_weight(step, total_steps, lambda_fourier),
        lambda_ssim=lambda_ssim,
        data_range=data_range,
        mask=mask,
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
    mask: Tensor | None = None,
    backend: str = "auto",
) -> dict[str, Tensor]:
    """``L_dyn = L_img^(t) + L_reg`` (Eq. S29) and its terms.

    ``L_img^(t) = (L_pix + lambda_F L_fft + lambda_S L_ssim) / (1 + lambda_S)`` on one frame
    (lambda_F constant), and ``L_reg = lambda_TV L_TV + lambda_sm L_sm + lambda_l1 L_l1`` on the
    HexPlane's planes (Eqs. S30-S32; the defaults are the note's weights). Returns ``total``,
    ``img``, the image terms of :func:`image_loss` and ``tv``, ``sm``, ``l1`` where weighted;
    ``mask`` as in :func:`image_loss`; ``backend`` the regularisers' (:func:`plane_regularisers`).
    """
    image = image_loss(
        prediction,
        target,
        p=p,
        lambda_fourier=lambda_fourier,
        lambda_ssim=lambda_ssim,
        data_range=data_range,
        mask=mask,
    )
    terms = {name: value for name, value in image.items() if name != "total"}
    terms["img"] = image["total"] / (1 + lambda_ssim)
    total = terms["img"]
    weights = {"tv": lambda_tv, "sm": lambda_sm, "l1": lambda_l1}
    weighted = [name for name, weight in weights.items() if weight > 0]
    if weighted:
        regularisers = plane_regularisers(
            list(hexplane.planes), hexplane.spatiotemporal_planes(), weighted, backend=backend
        )
        for name, value in regularisers.items():
            terms[name] = value
            total = total + weights[name] * value
    return {"total": total, **terms}
