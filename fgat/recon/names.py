"""The names under which a reconstruction's numbers are logged (MLflow metrics), in one place.

Volume scores of :func:`fgat.recon.metrics.compare_volumes` are logged as ``val/<name><suffix>``:
``val/psnr_volume`` for the reconstruction, ``val/psnr_volume_shb`` for the static stage's SHB
baseline, ``val/psnr_volume_no_deformation`` for the dynamic stage's ``G_0`` left still, and
``frame/<name><suffix>`` per frame. Recipes, summaries and tests read them through these names.
Both stages add ``val/psnr_volume_registered<suffix>`` and the shift it took
(:func:`registered_scores`): the static stage registers each volume, the dynamic stage moves
every frame by the one shift that registers ``G_0`` to the reference frame's truth.
"""

from __future__ import annotations

import math

VOLUME_SCORES = {"psnr": "psnr_volume", "ssim": "ssim_volume", "ssim_xy": "ssim_mip_xy"}
"""Key of :func:`fgat.recon.metrics.compare_volumes` -> logged score name."""

SHB, STILL = "_shb", "_no_deformation"
"""Suffixes of the baselines: SHB deconvolution (static), ``G_0`` without deformation (dynamic)."""

PSNR, SSIM, SSIM_XY = (f"val/{name}" for name in VOLUME_SCORES.values())
PSNR_REGISTERED = "val/psnr_volume_registered"  # PSNR without the scene's gauge translation
REGISTRATION_SHIFT = tuple(f"val/registration_shift_{axis}_vox" for axis in "zyx")
PROGRESS_PSNR = "val/psnr"  # the progress bar's copy of PSNR
LOSS, LOSS_PIX = "loss", "val/loss_pix"
ZERNIKE_RESIDUAL = "zernike/residual_normalized"  # sigma of Fig. S9a
PSF_ERROR, PSF_ERROR_INITIAL = "psf/error", "psf/error_initial"
SHIFT_ERRORS = tuple(
    f"shift/{kind}_error{gauge}_max_px"
    for kind in ("intercept", "slope")
    for gauge in ("", "_gauge_free")
)
GAUSSIAN_COUNT = "gaussians/count"
DENSIFICATION_STOPPED = "gaussians/stopped_at_step"  # densification stopped on a settled count
OPTICS_CONVERGED = "optics/converged_at_step"  # JPGM events skipped after this step
PSF_CHANGE = "optics/psf_change"  # an event's ||h_after - h_before|| / ||h_before||
FRAMES_CONVERGED = "frames/converged_at_step"  # every frame's loss converged: the stage stops
FRAMES_SETTLED = "frames/converged"  # frames the dynamic stage currently skips as converged
CROP_VOXELS, CROP_SAVED = "crop/voxels", "crop/voxels_saved"  # the grid the static stage fits
HOLDOUT_LOSS = "loss/holdout"  # pixel loss of the pixels left out of the fit
NOISE_SIGMA = "identifiability/noise_sigma"  # residual noise level of the standard errors
FLAGGED = "identifiability/flagged"  # parameters whose standard error exceeds the tolerance
WITHIN_2SE = "identifiability/within_2se"  # phantoms: fraction of true errors within 2 s.e.


def volume_scores(
    scores: dict[str, float], suffix: str = "", prefix: str = "val/"
) -> dict[str, float]:
    """``{prefix}<name><suffix>`` for every score of :func:`fgat.recon.metrics.compare_volumes`."""
    return {f"{prefix}{name}{suffix}": float(scores[key]) for key, name in VOLUME_SCORES.items()}


def registered_scores(
    psnr: float, shift: tuple[float, ...] | None, suffix: str = ""
) -> dict[str, float]:
    """``val/psnr_volume_registered<suffix>`` and ``val/registration_shift_<z|y|x>_vox<suffix>``
    of :func:`fgat.recon.metrics.registered_psnr`'s ``(psnr, shift)``: dB and voxels, NaN for a
    volume that did not register (``shift`` None)."""
    shift = (math.nan,) * len(REGISTRATION_SHIFT) if shift is None else shift
    return {
        PSNR_REGISTERED + suffix: float(psnr),
        **{name + suffix: float(value) for name, value in zip(REGISTRATION_SHIFT, shift)},
    }


def zernike_name(j: int) -> str:
    """``zernike/c<j>``: the coefficient of Noll index ``j`` (waves)."""
    return f"zernike/c{j}"


def shift_name(kind: str, view: int, axis: str) -> str:
    """``shift/<b|s><view>_<y|x>``: an intercept (``b``) or slope (``s``) component (pixels)."""
    return f"shift/{kind}{view}_{axis}"


def stderr_name(name: str) -> str:
    """``zernike/stderr_c5`` of ``zernike/c5``, ``shift/stderr_b0_y`` of ``shift/b0_y``: the
    standard error of a logged parameter."""
    group, key = name.split("/")
    return f"{group}/stderr_{key}"
