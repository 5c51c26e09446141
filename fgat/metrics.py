"""Image-quality metrics (PSNR, SSIM, registration to a truth, residuals): this public
path re-exports :mod:`fgat.recon.metrics`, where the code lives."""

from fgat.recon.metrics import (  # noqa: F401
    align_to_truth,
    axial_lateral_aspect,
    border_ratio,
    compare_volumes,
    gaussian_blur,
    gaussian_window,
    max_normalize,
    mip,
    psnr,
    registered_psnr,
    registration_window,
    relative_residual,
    residual_ratios,
    residual_summary,
    residual_sums,
    scoring_pair,
    shifted_psnr,
    ssim,
)

__all__ = [
    "mip",
    "max_normalize",
    "psnr",
    "gaussian_window",
    "gaussian_blur",
    "ssim",
    "scoring_pair",
    "compare_volumes",
    "border_ratio",
    "align_to_truth",
    "registered_psnr",
    "registration_window",
    "shifted_psnr",
    "residual_sums",
    "residual_ratios",
    "relative_residual",
    "residual_summary",
    "axial_lateral_aspect",
]
