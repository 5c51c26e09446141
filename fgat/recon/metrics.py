"""Image-quality metrics: PSNR, SSIM (2D and 3D) and maximum-intensity projections.

Every function takes NumPy arrays or PyTorch tensors. With tensors the result is a 0-d tensor
(differentiable, so ``1 - ssim`` is the SSIM loss of Eq. S25); with arrays it is a float.

Volume comparisons in fgat (:func:`compare_volumes`, recipes, benchmarks) use one
normalisation: negatives are clipped to zero and each volume is divided by its own maximum
(:func:`max_normalize`), then PSNR and SSIM are computed with ``data_range = 1``. A
reconstruction in the measurement's intensity units and a ground truth in arbitrary units are
thus compared on the same scale, as in the paper's figures.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

MIP_AXES = {"xy": -3, "xz": -2, "yz": -1}
"""Axis removed by each maximum-intensity projection of a ``(..., Z, Y, X)`` volume."""


def _as_tensor(value) -> tuple[Tensor, bool]:
    if isinstance(value, Tensor):
        return value, True
    array = np.asarray(value)
    dtype = torch.float64 if array.dtype == np.float64 else torch.float32
    return torch.as_tensor(
        array.astype(np.float64 if dtype == torch.float64 else np.float32)
    ), False


def _check_pair(x: Tensor, y: Tensor, data_range: float) -> None:
    if x.shape != y.shape:
        raise ValueError(
            f"images must have the same shape, got {tuple(x.shape)} and {tuple(y.shape)}"
        )
    if not (isinstance(data_range, (int, float)) and math.isfinite(data_range) and data_range > 0):
        raise ValueError(f"data_range must be a positive number, got {data_range!r}")


def _result(value: Tensor, tensor_input: bool):
    return value if tensor_input else float(value)


def mip(volume, view: str = "xy"):
    """Maximum-intensity projection of a ``(..., Z, Y, X)`` volume.

    ``"xy"`` -> ``(..., Y, X)``, ``"xz"`` -> ``(..., Z, X)``, ``"yz"`` -> ``(..., Z, Y)``.
    """
    if view not in MIP_AXES:
        raise ValueError(f"view must be one of {sorted(MIP_AXES)}, got {view!r}")
    if isinstance(volume, Tensor):
        return volume.amax(dim=MIP_AXES[view])
    return np.asarray(volume).max(axis=MIP_AXES[view])


def max_normalize(volume):
    """Clip negatives to zero and divide by the maximum (guarded: an all-zero volume stays zero)."""
    if isinstance(volume, Tensor):
        clipped = volume.clamp(min=0)
        return clipped / clipped.max().clamp(min=torch.finfo(clipped.dtype).tiny)
    clipped = np.clip(np.asarray(volume, dtype=np.float64), 0, None)
    peak = clipped.max()
    return clipped / peak if peak > 0 else clipped


def psnr(estimate, truth, data_range: float):
    """Peak signal-to-noise ratio ``10 log10(data_range^2 / MSE)`` in dB, any dimensionality.

    An exact match gives ``inf``.
    """
    x, tensor_input = _as_tensor(estimate)
    y, _ = _as_tensor(truth)
    _check_pair(x, y, data_range)
    mse = (x.to(y.dtype) - y).square().mean()
    value = 10.0 * torch.log10(data_range**2 / mse) if float(mse) > 0 else torch.tensor(math.inf)
    return _result(value, tensor_input)


def gaussian_window(sigma: float = 1.5, truncate: float = 3.5, *, dtype=torch.float64) -> Tensor:
    """Normalised 1D Gaussian of radius ``int(truncate sigma + 0.5)`` (scipy's
    ``gaussian_filter``)."""
    radius = int(truncate * sigma + 0.5)
    x = torch.arange(-radius, radius + 1, dtype=dtype)
    weights = torch.exp(-0.5 * (x / sigma) ** 2)
    return weights / weights.sum()


def gaussian_blur(images: Tensor, sigma: float, truncate: float = 3.5) -> Tensor:
    """Gaussian blur of the last two axes of ``(..., H, W)`` with standard deviation ``sigma``
    (pixels), zero outside the image: ``scipy.ndimage.gaussian_filter(mode="constant",
    truncate=truncate)`` per image. Differentiable; ``sigma`` 0 returns ``images``."""
    if sigma == 0:
        return images
    window = gaussian_window(sigma, truncate, dtype=images.dtype).to(images.device)
    radius = (len(window) - 1) // 2
    padded = torch.nn.functional.pad(images, (radius, radius, radius, radius))
    return _filter_valid(padded, window, 2)


def _filter_valid(image: Tensor, window: Tensor, dims: int) -> Tensor:
    """Separable 'valid' filtering of the last ``dims`` axes of ``(B, *spatial)``: on a CPU as
    sums of shifted slices (:func:`_filter_valid_shifted`), elsewhere one ``conv1d`` per axis
    (:func:`_filter_valid_conv`, few kernels for a GPU to launch); the same values to
    rounding."""
    if image.device.type == "cpu":
        return _filter_valid_shifted(image, window, dims)
    return _filter_valid_conv(image, window, dims)


def _filter_valid_conv(image: Tensor, window: Tensor, dims: int) -> Tensor:
    for axis in range(dims):
        image = image.movedim(-dims + axis, -1)
        shape = image.shape
        flat = image.reshape(-1, 1, shape[-1])
        flat = torch.nn.functional.conv1d(flat, window.view(1, 1, -1))
        image = flat.reshape(*shape[:-1], flat.shape[-1]).movedim(-1, -dims + axis)
    return image


def _filter_valid_shifted(image: Tensor, window: Tensor, dims: int) -> Tensor:
    """``sum_k w_k image[..., k : k + L]`` along each axis, added in place: on a CPU 3-11x
    faster than ``conv1d``'s single-channel path, forward and backward alike."""
    weights = window.tolist()
    for axis in range(image.ndim - dims, image.ndim):
        length = image.shape[axis] - len(weights) + 1
        filtered = image.narrow(axis, 0, length) * weights[0]
        for k, weight in enumerate(weights[1:], start=1):
            filtered.add_(image.narrow(axis, k, length), alpha=weight)
        image = filtered
    return image


def ssim(
    estimate, truth, data_range: float, *, spatial_dims: int | None = None, sigma: float = 1.5
):
    """Structural similarity with a Gaussian window, averaged over the image (Eq. S25 uses
    ``1 - SSIM``).

    Equal to ``skimage.metrics.structural_similarity(..., gaussian_weights=True, sigma=1.5,
    use_sample_covariance=False, data_range=data_range)`` for 2D images and 3D volumes: the
    window (radius ``int(3.5 sigma + 0.5)``), ``K1 = 0.01``, ``K2 = 0.03``, and the mean over the
    SSIM map without its border of one window radius. Leading axes beyond ``spatial_dims`` are a
    batch, averaged.

    Parameters
    ----------
    estimate, truth : array or Tensor
        ``(..., H, W)`` or ``(..., Z, Y, X)``; each spatial side larger than ``2 radius``.
    data_range : float
        Dynamic range of the data (1 for max-normalised volumes).
    spatial_dims : int, optional
        2 or 3; default ``min(ndim, 3)``.
    """
    x, tensor_input = _as_tensor(estimate)
    y, _ = _as_tensor(truth)
    _check_pair(x, y, data_range)
    dims = spatial_dims or min(x.ndim, 3)
    if dims not in (2, 3) or x.ndim < dims:
        raise ValueError(
            f"ssim works on 2D or 3D images; got spatial_dims={dims} for shape {tuple(x.shape)}"
        )
    window = gaussian_window(sigma, dtype=y.dtype).to(y.device)
    radius = (window.numel() - 1) // 2
    if min(x.shape[-dims:]) <= 2 * radius:
        raise ValueError(
            f"ssim needs every spatial side > {2 * radius} pixels, got shape {tuple(x.shape)}"
        )
    x = x.to(y.dtype).reshape(-1, *x.shape[-dims:])
    y = y.reshape(-1, *y.shape[-dims:])
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    stacked = _filter_valid(torch.stack([x, y, x * x, y * y, x * y], dim=1), window, dims)
    mu_x, mu_y, xx, yy, xy = stacked.unbind(1)
    var_x, var_y, cov = xx - mu_x**2, yy - mu_y**2, xy - mu_x * mu_y
    numerator = (2 * mu_x * mu_y + c1) * (2 * cov + c2)
    denominator = (mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2)
    return _result((numerator / denominator).mean(), tensor_input)


def _ssim_or_nan(x, y, spatial_dims: int) -> float:
    """SSIM, or NaN where a side is not longer than the Gaussian window (e.g. a thin volume)."""
    radius = (gaussian_window().numel() - 1) // 2
    if min(np.shape(x)[-spatial_dims:]) <= 2 * radius:
        return math.nan
    return float(ssim(x, y, 1.0, spatial_dims=spatial_dims))


def scoring_pair(volume: Tensor, truth) -> tuple[Tensor, Tensor]:
    """``volume`` ``(Z, Y, X)`` and ``truth`` (array or tensor) as float64 tensors on
    ``volume``'s device, where :func:`compare_volumes` scores them (a paper-size volume's SSIM
    takes seconds on a CPU, milliseconds on a GPU); on the host for MPS, which has no float64."""
    volume = volume.detach()
    if volume.device.type == "mps":
        volume = volume.cpu()
    volume = volume.to(torch.float64)
    return volume, torch.as_tensor(truth, device=volume.device).to(volume)


def compare_volumes(estimate, truth) -> dict[str, float]:
    """PSNR and SSIM of a volume and of its three MIPs, after :func:`max_normalize` of both.

    SSIM is NaN for an image with a side of 11 voxels or fewer (the Gaussian window's size).
    """
    x = max_normalize(estimate)
    y = max_normalize(truth)
    scores = {"psnr": float(psnr(x, y, 1.0)), "ssim": _ssim_or_nan(x, y, 3)}
    for view in MIP_AXES:
        scores[f"psnr_{view}"] = float(psnr(mip(x, view), mip(y, view), 1.0))
        scores[f"ssim_{view}"] = _ssim_or_nan(mip(x, view), mip(y, view), 2)
    return scores


def border_ratio(estimate, truth, width: int = 2) -> float:
    """The frame artefact of a volume ``(Z, Y, X)``: its ratio of the mean over the lateral
    border ring of ``width`` voxels to the mean inside it, divided by the truth's ratio. Light
    from beyond the field of view forced into the border voxels makes it larger than 1; 1 when
    the border holds the truth's share of the light (scale-free: no normalisation needed)."""
    x = np.asarray(estimate, dtype=np.float64)
    y = np.asarray(truth, dtype=np.float64)
    if width < 1 or 2 * width >= min(x.shape[-2:]):
        raise ValueError(f"width must be between 1 and half the lateral size, got {width}")
    ring = np.ones(x.shape[-2:], dtype=bool)
    ring[width:-width, width:-width] = False

    def share(volume: np.ndarray) -> float:
        return volume[..., ring].mean() / max(volume[..., ~ring].mean(), 1e-30)

    return float(share(x) / max(share(y), 1e-30))


def align_to_truth(
    estimate, truth, max_shift: int = 3, subvoxel: bool = False
) -> tuple[np.ndarray, tuple[float, ...]]:
    """The estimate translated by the shift that best matches the truth.

    A reconstruction sits where its calibration put the scene: the lenslet shifts that a joint
    estimate (or lenslet centres found on a fluorescence image) settles on are fixed only up to
    the sample's mean position (a common shift and a parallax-like scale, see
    :func:`fgat.recon.estimation.remove_scene_gauge`), which moves the whole volume, by a
    fraction of a voxel as often as not. Scores against such a truth are reported both as they
    are and after this alignment: the whole-voxel shift of at most ``max_shift`` voxels per axis
    of largest correlation (voxels shifted in from outside are 0), then with ``subvoxel`` the
    shift of largest correlation within one voxel of it, to 1/20 voxel (the correlation's
    spectrum evaluated between the samples, as upsampled cross-correlation does), the estimate
    shifted by a phase ramp of its spectrum (band-limited interpolation; zero-padded so that
    nothing wraps around).

    Parameters
    ----------
    estimate, truth : array-like
        Volumes of the same shape ``(Z, Y, X)``.
    max_shift : int
        Largest whole-voxel shift tried along each axis, voxels.
    subvoxel : bool
        Refine the shift to fractions of a voxel.

    Returns
    -------
    aligned : numpy.ndarray
        ``(Z, Y, X)`` float64, ``aligned[i] = estimate[i - shift]``.
    shift : tuple
        The shift ``(dz, dy, dx)``, voxels (``int`` without ``subvoxel``).
    """
    x, y = _volume_pair(estimate, truth)
    if max_shift < 0 or 2 * max_shift >= min(x.shape):
        raise ValueError(
            f"max_shift must be between 0 and half the smallest side of {x.shape}, got {max_shift}"
        )
    spectrum, size = _cross_spectrum(x, y, max_shift)
    whole = _correlation_peak(spectrum, size, max_shift)
    if not subvoxel:
        return _whole_shift(x, whole), whole
    shift = _refined_peak(spectrum, size, whole)
    return _fourier_shift(x, shift), shift


REGISTRATION_WINDOW = 6
"""Largest whole-voxel shift (per axis) :func:`registered_psnr` searches by default."""


def registered_psnr(
    estimate, truth, max_shift: int | None = REGISTRATION_WINDOW
) -> tuple[float, tuple[float, ...] | None]:
    """PSNR of a volume against the truth without the translation of the scene that neither
    the data nor a reconstruction can fix (the lenslet shifts' gauge).

    The estimate is scaled as :func:`compare_volumes` scales it (:func:`max_normalize`), then
    moved by :func:`align_to_truth`'s sub-voxel registration and scored with that scale kept
    (re-normalising after a sub-voxel shift would rescale the whole volume by how much the
    brightest voxel lost). A registration whose correlation peak sits on the edge of the
    searched window (``max_shift`` voxels along some axis) has not found the scene, as with
    reconstructions too smeared to resemble the truth: the score is then NaN.

    Parameters
    ----------
    estimate, truth : array-like
        Volumes of the same shape ``(Z, Y, X)``.
    max_shift : int or None
        Largest whole-voxel shift searched along each axis, voxels. None: the window the grid
        allows (:func:`registration_window`), and NaN for a grid too thin to register.

    Returns
    -------
    psnr : float
        dB (``data_range`` 1), or NaN.
    shift : tuple of float or None
        ``(dz, dy, dx)`` voxels, or None.
    """
    if max_shift is None:
        max_shift = registration_window(np.shape(truth))
        if max_shift < 1:
            return math.nan, None
    x = max_normalize(estimate)
    aligned, shift = align_to_truth(x, truth, max_shift, subvoxel=True)
    if max(abs(s) for s in shift) >= max_shift:
        return math.nan, None
    return _aligned_psnr(aligned, truth), shift


def registration_window(shape) -> int:
    """The registration window for a grid of ``shape``: :data:`REGISTRATION_WINDOW` voxels, or
    less than half the smallest side (0: too thin to register)."""
    return min(REGISTRATION_WINDOW, (min(shape) - 1) // 2)


def shifted_psnr(estimate, truth, shift) -> float:
    """PSNR of a volume moved by a known ``shift`` ``(dz, dy, dx)`` (voxels), scaled, moved and
    scored as :func:`registered_psnr` does. For volumes that share one translation of the scene,
    e.g. every frame of a sequence reconstructed with the same optics, moved by the shift that
    one of them registered with.

    Parameters
    ----------
    estimate, truth : array-like
        Volumes of the same shape ``(Z, Y, X)``.
    shift : sequence of float
        ``aligned[i] = estimate[i - shift]``, voxels.

    Returns
    -------
    float
        dB (``data_range`` 1).
    """
    x, _ = _volume_pair(max_normalize(estimate), truth)
    if len(shift) != 3:
        raise ValueError(f"a shift (dz, dy, dx) in voxels expected, got {tuple(shift)}")
    return _aligned_psnr(_fourier_shift(x, tuple(float(s) for s in shift)), truth)


def _volume_pair(estimate, truth) -> tuple[np.ndarray, np.ndarray]:
    """Two volumes ``(Z, Y, X)`` of one shape as float64 arrays; one line naming both shapes
    otherwise."""
    x = np.asarray(estimate, dtype=np.float64)
    y = np.asarray(truth, dtype=np.float64)
    if x.shape != y.shape or x.ndim != 3:
        raise ValueError(f"two volumes (Z, Y, X) of one shape expected, got {x.shape}, {y.shape}")
    return x, y


def _aligned_psnr(aligned: np.ndarray, truth) -> float:
    """PSNR of a max-normalised volume moved onto the truth, its scale kept (clipped to [0, 1])."""
    return float(psnr(np.clip(aligned, 0.0, 1.0), max_normalize(truth), 1.0))


def _fft_workers() -> int:
    """Threads for the registration's transforms: PyTorch's (what the process, or a trial of a
    sweep, was given), the same result for any count (each 1-D transform runs whole on one)."""
    return torch.get_num_threads()


def _cross_spectrum(x: np.ndarray, y: np.ndarray, max_shift: int):
    """``conj(X) Y`` (half spectrum along the last axis: the volumes are real) on a grid
    ``max_shift + 1`` larger than the volumes per axis, so that the correlation ``r[s] = sum_i
    x[i - s] y[i]`` (``x`` zero outside) of every ``|s_k| <= max_shift + 1`` (the window and its
    refinement) is free of wrap-around; and that grid's shape."""
    from scipy import fft  # SciPy loaded when used: keeps start-up fast

    size = tuple(n + max_shift + 1 for n in x.shape)
    workers = _fft_workers()
    return np.conj(fft.rfftn(x, size, workers=workers)) * fft.rfftn(y, size, workers=workers), size


def _correlation_peak(spectrum: np.ndarray, size, max_shift: int) -> tuple[int, ...]:
    """The whole-voxel shift ``|s_k| <= max_shift`` of largest correlation."""
    from scipy import fft  # SciPy loaded when used: keeps start-up fast

    correlation = fft.irfftn(spectrum, size, workers=_fft_workers())
    window = np.arange(-max_shift, max_shift + 1)
    block = correlation[np.ix_(*[window % n for n in size])]
    return tuple(int(window[k]) for k in np.unravel_index(np.argmax(block), block.shape))


def _refined_peak(spectrum: np.ndarray, size, whole, upsample: int = 20) -> tuple[float, ...]:
    """The shift of largest correlation on a grid of ``1 / upsample`` voxel within one voxel of
    ``whole``: the correlation evaluated there from its spectrum directly (a matrix DFT per
    axis, ``r(s) = sum_k conj(X_k) Y_k exp(2 pi i k s / N)``; over the half spectrum of the last
    axis its terms pair with their conjugates, so each counts twice but the zero and Nyquist
    frequencies, and the real part is the sum)."""
    offsets = np.arange(-upsample, upsample + 1) / upsample
    grids = [s + offsets for s in whole]
    values = spectrum
    for axis in sorted(range(3), key=lambda a: -size[a]):  # the longest axis first: least work
        n = size[axis]
        if axis == 2:
            frequencies = np.arange(n // 2 + 1)
            weights = np.where((frequencies == 0) | (2 * frequencies == n), 1.0, 2.0)
        else:
            frequencies, weights = np.fft.fftfreq(n) * n, 1.0
        kernel = weights * np.exp(2j * np.pi * np.outer(grids[axis], frequencies) / n)
        values = np.moveaxis(np.tensordot(values, kernel, axes=([axis], [1])), -1, axis)
    peak = np.unravel_index(np.argmax(values.real), values.shape)
    return tuple(float(grid[k]) for grid, k in zip(grids, peak))


def _whole_shift(x: np.ndarray, shift: tuple[int, ...]) -> np.ndarray:
    """``x`` translated by whole voxels (``out[i] = x[i - shift]``), zero outside."""
    moved = np.zeros_like(x)
    if all(abs(s) < n for s, n in zip(shift, x.shape)):
        source = tuple(slice(max(-s, 0), n - max(s, 0)) for s, n in zip(shift, x.shape))
        target = tuple(slice(max(s, 0), n - max(-s, 0)) for s, n in zip(shift, x.shape))
        moved[target] = x[source]
    return moved


def _fourier_shift(x: np.ndarray, shift: tuple[float, ...]) -> np.ndarray:
    """``x`` ``(Z, Y, X)`` translated by ``shift`` voxels (``out[i] = x[i - shift]``, band-
    limited), zero outside: padded by the shift and a margin before the spectrum's phase ramp;
    a whole-voxel shift (a scene in place, most often) is the zero-filled translation itself,
    which the phase ramp gives too (to 1e-12), without the transforms."""
    from scipy import fft, ndimage  # SciPy loaded when used: keeps start-up fast

    if all(float(s).is_integer() for s in shift):
        return _whole_shift(x, tuple(int(s) for s in shift))

    margin = [math.ceil(abs(s)) + 4 for s in shift]
    padded = np.pad(x, [(m, m) for m in margin])
    workers = _fft_workers()
    spectrum = ndimage.fourier_shift(fft.rfftn(padded, workers=workers), shift, n=padded.shape[-1])
    moved = fft.irfftn(spectrum, padded.shape, workers=workers)
    return moved[tuple(slice(m, m + n) for m, n in zip(margin, x.shape))]


def residual_sums(operator, volume, measurement, weights=None) -> tuple[Tensor, Tensor]:
    """Per view, ``||w (A x - y)_v||^2`` and ``||w y_v||^2`` in float64 ``(V,)`` each: the sums
    of :func:`relative_residual` (add those of several frames for a sequence's residual).

    Parameters
    ----------
    operator
        Has ``forward`` ``(Z, Y', X') -> (V, Y, X)``: with a
        :class:`~fgat.optics.acquisition.MeasuredOperator` the acquisition model (per-view gains,
        the central views of a guard-banded grid).
    volume : Tensor
        ``(Z, Y', X')`` on the operator's grid, in the measurement's units.
    measurement : Tensor or numpy.ndarray
        ``(V, Y, X)`` the data ``y`` (background subtracted), in the same units.
    weights : Tensor or numpy.ndarray, optional
        Broadcastable to ``(V, Y, X)``, non-negative (the hot-pixel mask, held-out pixels at 0);
        default all 1.
    """
    with torch.no_grad():
        prediction = operator.forward(volume).detach().to(torch.float64)
    data = torch.as_tensor(measurement).to(prediction)
    if data.shape != prediction.shape:
        raise ValueError(
            f"measurement has shape {tuple(data.shape)}, the operator predicts "
            f"{tuple(prediction.shape)}"
        )
    w = 1.0 if weights is None else torch.as_tensor(weights).to(prediction).expand_as(data)
    misfit = ((w * (prediction - data)) ** 2).flatten(1).sum(dim=1)
    return misfit, ((w * data) ** 2).flatten(1).sum(dim=1)


def residual_ratios(misfit: Tensor, norm: Tensor) -> dict[str, object]:
    """``overall`` ``sqrt(sum misfit / sum norm)`` and ``views`` ``sqrt(misfit_v / norm_v)`` of
    :func:`residual_sums`; NaN where the norm is 0 (no data to explain)."""

    def ratio(numerator: Tensor, denominator: Tensor) -> float:
        return float((numerator / denominator).sqrt()) if denominator > 0 else math.nan

    return {
        "overall": ratio(misfit.sum(), norm.sum()),
        "views": [ratio(m, n) for m, n in zip(misfit, norm)],
    }


def relative_residual(operator, volume, measurement, weights=None) -> dict[str, object]:
    """The relative data residual ``||w (A x - y)|| / ||w y||`` of a reconstruction, overall and
    per view, in float64 (:func:`residual_sums` for the parameters).

    ``A x`` is the operator's prediction of the data (Eqs. S3, S52 with the acquisition's gains
    and guard band) and ``w`` the weights of the pixels the fit used, so the residual is the one
    of the pixels the model explains: 0 is a perfect fit, 1 what the zero volume scores.

    Returns
    -------
    dict
        ``overall`` (float) and ``views`` (list of ``V`` floats): :func:`residual_ratios`.
    """
    return residual_ratios(*residual_sums(operator, volume, measurement, weights))


def residual_summary(residual: dict[str, object]) -> str:
    """``relative data residual 0.0123 (per view 0.011-0.015)``: the line that reports
    :func:`relative_residual`."""
    views = np.asarray(residual["views"], dtype=np.float64)
    spread = (
        f" (per view {np.nanmin(views):.4g}-{np.nanmax(views):.4g})"
        if np.isfinite(views).any()
        else ""
    )
    return f"relative data residual ||Ax - y|| / ||y|| {residual['overall']:.4g}{spread}"


def axial_lateral_aspect(volume, voxel_size_um, threshold: float = 0.2) -> dict[str, float]:
    """The axial-to-lateral aspect of the main object of a volume ``(Z, Y, X)``: whether a
    reconstruction keeps the depth scale (a round object stays round, not squashed or stretched
    along z).

    The voxels at or above ``threshold`` times the volume's maximum (negatives clipped to 0) are
    split into connected components (26-connectivity); the one of largest summed intensity is
    the object. Its intensity-weighted standard deviations ``sigma_z, sigma_y, sigma_x`` (um,
    voxel centres at ``index * voxel_size_um``) give the aspect ``sigma_z / sqrt((sigma_y^2 +
    sigma_x^2) / 2)``: 1 for a sphere or a spherical shell, ``a / b`` for a solid ellipsoid (or
    a homothetic ellipsoidal shell) of axial semi-axis ``a`` and lateral ``b`` (its second
    moments are ``a^2 / 5`` and ``b^2 / 5``; a thin spherical shell's are ``R^2 / 3``).

    Parameters
    ----------
    volume : array-like
        ``(Z, Y, X)`` intensities.
    voxel_size_um : (dz, dy, dx)
        Voxel size in um.
    threshold : float
        Fraction of the maximum, in (0, 1), at which the object is cut out.

    Returns
    -------
    dict
        ``aspect``, ``sigma_z_um``, ``sigma_y_um``, ``sigma_x_um`` and ``voxels`` (the object's
        size); the sizes NaN and ``voxels`` 0 for an empty (all-zero or non-finite) volume.
    """
    from scipy import ndimage  # SciPy loaded when used: keeps start-up fast

    x = np.asarray(volume, dtype=np.float64)
    if x.ndim != 3:
        raise ValueError(f"volume must be (Z, Y, X), got shape {x.shape}")
    voxel = np.asarray(voxel_size_um, dtype=np.float64).reshape(-1)
    if voxel.shape != (3,) or not (np.isfinite(voxel).all() and (voxel > 0).all()):
        raise ValueError(f"voxel_size_um must be three positive sizes, got {voxel_size_um!r}")
    if not 0 < threshold < 1:
        raise ValueError(f"threshold must be in (0, 1), got {threshold!r}")
    empty = {
        "aspect": math.nan,
        "sigma_z_um": math.nan,
        "sigma_y_um": math.nan,
        "sigma_x_um": math.nan,
        "voxels": 0,
    }
    x = np.clip(x, 0, None)
    peak = float(x.max()) if x.size else 0.0
    if not (math.isfinite(peak) and peak > 0):
        return empty
    labels, count = ndimage.label(x >= threshold * peak, structure=np.ones((3, 3, 3)))
    sums = ndimage.sum_labels(x, labels, index=np.arange(1, count + 1))
    inside = labels == 1 + int(np.argmax(sums))
    weights = x[inside]
    coordinates = np.argwhere(inside) * voxel  # (N, 3) um
    mean = weights @ coordinates / weights.sum()
    sigma = np.sqrt(weights @ (coordinates - mean) ** 2 / weights.sum())
    lateral = math.sqrt((sigma[1] ** 2 + sigma[2] ** 2) / 2)
    return {
        "aspect": float(sigma[0] / lateral) if lateral > 0 else math.nan,
        "sigma_z_um": float(sigma[0]),
        "sigma_y_um": float(sigma[1]),
        "sigma_x_um": float(sigma[2]),
        "voxels": int(inside.sum()),
    }
