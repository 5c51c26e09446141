import math

import numpy as np
import pytest
import torch
from skimage.metrics import peak_signal_noise_ratio, structural_similarity
from skimage.registration import phase_cross_correlation

from fgat.recon.metrics import (
    axial_lateral_aspect,
    compare_volumes,
    gaussian_blur,
    max_normalize,
    mip,
    psnr,
    ssim,
)


@pytest.mark.parametrize("shape", [(40, 50), (24, 30, 27)])
def test_ssim_matches_scikit_image(shape, dtype):
    rng = np.random.default_rng(len(shape))
    a = rng.random(shape)
    b = np.clip(a + 0.15 * rng.standard_normal(shape), 0, None)
    reference = structural_similarity(
        a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.5
    )
    assert ssim(a, b, 1.5) == pytest.approx(reference, abs=1e-10)
    ours = ssim(torch.tensor(a, dtype=dtype), torch.tensor(b, dtype=dtype), 1.5)
    assert isinstance(ours, torch.Tensor) and ours.dtype == dtype
    assert float(ours) == pytest.approx(reference, abs=1e-4)


def test_ssim_is_differentiable_and_one_for_identical():
    a = torch.rand(2, 20, 20, dtype=torch.float64, requires_grad=True)
    b = torch.rand(2, 20, 20, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda x: ssim(x, b, 1.0, spatial_dims=2), (a,))
    assert float(ssim(b, b, 1.0, spatial_dims=2)) == pytest.approx(1.0)


def test_batched_ssim_is_mean_of_items():
    a, b = torch.rand(3, 16, 18, dtype=torch.float64), torch.rand(3, 16, 18, dtype=torch.float64)
    batched = ssim(a, b, 1.0, spatial_dims=2)
    assert float(batched) == pytest.approx(
        np.mean([float(ssim(a[i], b[i], 1.0)) for i in range(3)])
    )


def test_psnr_matches_scikit_image():
    rng = np.random.default_rng(0)
    a, b = rng.random((10, 12, 14)), rng.random((10, 12, 14))
    assert psnr(a, b, 2.0) == pytest.approx(peak_signal_noise_ratio(b, a, data_range=2.0))
    assert psnr(a, a, 1.0) == float("inf")


def test_mips_and_normalisation():
    volume = np.zeros((4, 5, 6))
    volume[2, 3, 1] = 8.0
    volume[1, 0, 0] = -3.0
    assert mip(volume, "xy").shape == (5, 6) and mip(volume, "xz").shape == (4, 6)
    assert mip(volume, "yz")[2, 3] == 8.0
    normalized = max_normalize(volume)
    assert normalized.max() == 1.0 and normalized.min() == 0.0
    assert torch.equal(max_normalize(torch.zeros(3)), torch.zeros(3))
    scores = compare_volumes(
        3.0 * np.random.default_rng(1).random((16, 16, 16)) + 0, np.ones((16, 16, 16))
    )
    assert set(scores) == {
        "psnr",
        "ssim",
        "psnr_xy",
        "ssim_xy",
        "psnr_xz",
        "ssim_xz",
        "psnr_yz",
        "ssim_yz",
    }


def test_scale_invariance_of_compare_volumes():
    truth = np.random.default_rng(2).random((16, 16, 16))
    assert compare_volumes(truth * 123.0, truth)["psnr"] > 250  # equal up to rounding


def test_errors():
    with pytest.raises(ValueError, match="same shape"):
        psnr(np.ones((3, 3)), np.ones((3, 4)), 1.0)
    with pytest.raises(ValueError, match="data_range"):
        ssim(np.ones((20, 20)), np.ones((20, 20)), 0)
    with pytest.raises(ValueError, match="spatial side"):
        ssim(np.ones((8, 8)), np.ones((8, 8)), 1.0)
    with pytest.raises(ValueError, match="view must be"):
        mip(np.ones((2, 2, 2)), "zz")


def test_compare_volumes_on_a_thin_volume():
    rng = np.random.default_rng(5)
    scores = compare_volumes(rng.random((9, 32, 32)), rng.random((9, 32, 32)))
    assert np.isnan(scores["ssim"]) and np.isnan(scores["ssim_xz"])
    assert np.isfinite(scores["ssim_xy"]) and np.isfinite(scores["psnr"])


def test_border_ratio_measures_a_bright_frame():
    from fgat.recon.metrics import border_ratio

    rng = np.random.default_rng(3)
    truth = rng.random((4, 20, 20)) + 0.5
    framed = truth.copy()
    ring = np.ones((20, 20), dtype=bool)
    ring[2:-2, 2:-2] = False
    framed[:, ring] *= 3.0
    assert border_ratio(framed, truth) == pytest.approx(3.0, rel=1e-12)
    assert border_ratio(7.0 * truth, truth) == pytest.approx(1.0, rel=1e-12)
    with pytest.raises(ValueError, match="width"):
        border_ratio(truth, truth, width=10)


def test_align_to_truth_undoes_a_whole_voxel_shift():
    from fgat.recon.metrics import align_to_truth

    rng = np.random.default_rng(3)
    truth = np.zeros((20, 24, 22))
    truth[4:16, 5:19, 6:17] = rng.random((12, 14, 11))
    moved = np.roll(truth, (-2, 1, 3), axis=(0, 1, 2))  # the content sits inside: no wrap
    aligned, shift = align_to_truth(moved, truth, max_shift=3)
    assert shift == (2, -1, -3)
    np.testing.assert_array_equal(aligned, truth)
    assert align_to_truth(truth, truth)[1] == (0, 0, 0)
    with pytest.raises(ValueError, match="max_shift must be between 0 and half"):
        align_to_truth(truth, truth, max_shift=10)


def test_align_to_truth_takes_the_brute_force_correlation_peak():
    """The FFT correlation's whole-voxel peak is the brute-force one: every shift of the window
    scored as ``sum_i x[i - s] y[i]`` in float64 with zeros shifted in."""
    from fgat.recon.metrics import align_to_truth

    rng = np.random.default_rng(11)
    x, y = rng.random((3, 12, 14, 13))[:2]
    y[3:8, 4:9, 2:7] += 3 * x[4:9, 2:7, 5:10]  # a strong but not dominant match
    padded = np.pad(x, 2)

    def score(shift):
        window = tuple(slice(2 - s, 2 - s + n) for s, n in zip(shift, x.shape))
        return float((padded[window] * y).sum())

    window = range(-2, 3)
    expected = max(((a, b, c) for a in window for b in window for c in window), key=score)
    aligned, shift = align_to_truth(x, y, max_shift=2)
    assert shift == expected and all(isinstance(s, int) for s in shift)
    np.testing.assert_array_equal(
        aligned, padded[tuple(slice(2 - s, 2 - s + n) for s, n in zip(shift, x.shape))]
    )


def _blobs(shape, centres, sigma=(1.5, 1.0, 1.0)):
    """Anisotropic Gaussians at ``centres`` ``(N, 3)`` (voxels), evaluated exactly on the grid."""
    grid = np.indices(shape).reshape(3, -1).T[:, None, :]
    exponent = (((grid - centres[None]) / np.asarray(sigma)) ** 2).sum(-1)
    return np.exp(-0.5 * exponent).sum(1).reshape(shape)


@pytest.mark.parametrize("width", [36, 37])
@pytest.mark.parametrize("delta", [(0.35, -0.6, 1.3), (-1.45, 0.05, -0.25)])
def test_align_to_truth_subvoxel_undoes_a_fractional_shift(delta, width):
    """Beads displaced by ``delta`` voxels (rendered analytically there, not resampled) are
    registered to within 1/20 voxel and, moved back, match the truth far better than the
    whole-voxel alignment does; on correlation grids of even and odd width (the half spectrum's
    last frequency is a Nyquist one or not)."""
    from fgat.recon.metrics import align_to_truth

    shape = (24, 40, width)
    centres = np.random.default_rng(5).uniform((5, 6, 6), (19, 34, 30), (30, 3))
    truth = _blobs(shape, centres)
    moved = _blobs(shape, centres + np.asarray(delta))
    aligned, shift = align_to_truth(moved, truth, subvoxel=True)
    np.testing.assert_allclose(shift, -np.asarray(delta), atol=0.05)
    reference = phase_cross_correlation(truth, moved, upsample_factor=20, normalization=None)[0]
    np.testing.assert_allclose(shift, reference, atol=0.051)
    whole = compare_volumes(align_to_truth(moved, truth)[0], truth)["psnr"]
    assert compare_volumes(aligned, truth)["psnr"] > max(50.0, whole + 15.0)


def test_align_to_truth_subvoxel_stays_in_the_window():
    """Between unrelated volumes the circular correlation peaks anywhere; the registration keeps
    to the shifts it searched (``max_shift``, plus the voxel of refinement)."""
    from fgat.recon.metrics import align_to_truth

    rng = np.random.default_rng(4)
    for _ in range(3):
        x, y = rng.random((2, 16, 18, 20)) ** 8  # sparse bright spots
        _, shift = align_to_truth(x, y, max_shift=2, subvoxel=True)
        assert max(abs(s) for s in shift) <= 3.0


def test_registered_psnr_scores_the_registered_volume_at_its_own_scale():
    """The displaced beads of the test above: the registered PSNR is the PSNR of the estimate,
    max-normalised before it is moved back by the registered shift (float64 reference:
    scipy's spline shift by the true displacement, the same scale); an estimate in place scores
    as :func:`compare_volumes` does; a volume displaced beyond the searched window scores NaN."""
    from scipy import ndimage

    from fgat.recon.metrics import registered_psnr

    shape, delta = (24, 40, 36), np.array((0.35, -0.6, 1.3))
    centres = np.random.default_rng(5).uniform((5, 6, 6), (19, 34, 30), (30, 3))
    truth = _blobs(shape, centres)
    moved = 7.0 * _blobs(shape, centres + delta)
    score, shift = registered_psnr(moved, truth)
    np.testing.assert_allclose(shift, -delta, atol=0.05)
    back = ndimage.shift(moved / moved.max(), -delta, order=5, mode="grid-constant")
    reference = psnr(np.clip(back, 0, 1), truth / truth.max(), 1.0)
    assert score == pytest.approx(reference, abs=1.5) and score > 45.0
    in_place = 0.5 * truth + 0.01 * np.random.default_rng(1).random(shape)
    score, shift = registered_psnr(in_place, truth)
    assert shift == pytest.approx((0.0, 0.0, 0.0), abs=1e-12)
    assert score == pytest.approx(compare_volumes(in_place, truth)["psnr"], abs=1e-9)
    bead = _blobs(shape, np.array([(12.0, 15.0, 18.0)]))
    far = _blobs(shape, np.array([(12.0, 24.0, 18.0)]))  # its correlation rises to the edge
    assert math.isnan(registered_psnr(far, bead, max_shift=3)[0])


def test_registered_psnr_in_the_window_the_grid_allows():
    """``max_shift=None``: the window of :func:`registration_window` (a 9-voxel-thin grid
    searches 4 voxels; 2 voxels along z found, which a 2-voxel window would call its edge), and
    NaN without a shift where the grid is too thin to register at all."""
    from fgat.recon.metrics import registered_psnr, registration_window

    shape = (9, 30, 30)
    centres = np.array([(3.0, 12.0, 15.0), (3.0, 20.0, 9.0)])
    truth, moved = _blobs(shape, centres), _blobs(shape, centres + (2.0, 0.0, 0.0))
    assert registration_window(shape) == 4
    score, shift = registered_psnr(moved, truth, max_shift=None)
    assert shift == pytest.approx((-2.0, 0.0, 0.0), abs=0.1) and score > 30
    assert (score, shift) == registered_psnr(moved, truth, max_shift=4)
    assert math.isnan(registered_psnr(moved, truth, max_shift=2)[0])
    thin = truth[:2]
    assert registration_window(thin.shape) == 0
    score, shift = registered_psnr(thin, thin, max_shift=None)
    assert math.isnan(score) and shift is None
    with pytest.raises(ValueError, match="max_shift"):
        registered_psnr(thin, thin)  # the default window does not fit


def test_shifted_psnr_scores_a_known_shift_as_the_registration_does():
    """Given the shift a registration found, the registered score again; given the true
    displacement instead, a score against scipy's spline shift (float64 reference, as above);
    and another volume moved by the same shift (one scene, two frames) scores what its own
    registration gives."""
    from scipy import ndimage

    from fgat.recon.metrics import registered_psnr, registration_window, shifted_psnr

    shape, delta = (24, 40, 36), np.array((0.35, -0.6, 1.3))
    centres = np.random.default_rng(5).uniform((5, 6, 6), (19, 34, 30), (30, 3))
    truth = _blobs(shape, centres)
    moved = 7.0 * _blobs(shape, centres + delta)
    score, shift = registered_psnr(moved, truth)
    assert shifted_psnr(moved, truth, shift) == score
    back = ndimage.shift(moved / moved.max(), -delta, order=5, mode="grid-constant")
    reference = psnr(np.clip(back, 0, 1), truth / truth.max(), 1.0)
    assert shifted_psnr(moved, truth, -delta) == pytest.approx(reference, abs=1.5)
    later = centres + np.random.default_rng(6).normal(0, 0.3, centres.shape)  # a later frame
    frame, frame_truth = 3.0 * _blobs(shape, later + delta), _blobs(shape, later)
    assert shifted_psnr(frame, frame_truth, shift) == pytest.approx(
        registered_psnr(frame, frame_truth)[0], abs=0.5
    )
    assert [registration_window(s) for s in ((24, 40, 36), (9, 20, 20), (2, 8, 8))] == [6, 4, 0]
    with pytest.raises(ValueError, match=r"one shape expected, got \(24, 40, 36\), \(40, 36\)"):
        shifted_psnr(moved, truth[0], shift)
    with pytest.raises(ValueError, match=r"a shift \(dz, dy, dx\) in voxels expected, got \(0.5,"):
        shifted_psnr(moved, truth, (0.5, 0.0))


def test_fourier_shift_by_whole_voxels_is_a_zero_filled_translation():
    """A whole-voxel shift is the exact translation with zeros shifted in (content at the
    border leaves the volume instead of wrapping around), as the phase ramp just off whole
    voxels gives it; a shift past the volume leaves zeros."""
    from fgat.recon.metrics import _fourier_shift

    x = np.random.default_rng(2).random((9, 10, 11))
    expected = np.zeros_like(x)
    expected[2:, :, :-3] = x[:-2, :, 3:]
    np.testing.assert_array_equal(_fourier_shift(x, (2.0, 0.0, -3.0)), expected)
    # the phase ramp itself, just off whole voxels, agrees with the translation
    np.testing.assert_allclose(_fourier_shift(x, (2.0, 0.0, -3.0 + 1e-9)), expected, atol=1e-7)
    np.testing.assert_array_equal(_fourier_shift(x, (0.0, 12.0, 0.0)), np.zeros_like(x))


@pytest.mark.parametrize("sigma", [0.6, 2.0, 4.5])
def test_gaussian_blur_is_scipys(sigma):
    """Per image, scipy.ndimage.gaussian_filter with zeros outside (mode "constant", the same
    truncation) on a batch of odd-sized views; differentiable; sigma 0 is the identity."""
    from scipy import ndimage

    images = torch.rand(
        2, 3, 41, 38, dtype=torch.float64, generator=torch.Generator().manual_seed(1)
    )
    expected = np.stack(
        [
            [ndimage.gaussian_filter(image, sigma, mode="constant", truncate=3.5) for image in view]
            for view in images.numpy()
        ]
    )
    np.testing.assert_allclose(gaussian_blur(images, sigma).numpy(), expected, atol=1e-14)
    assert gaussian_blur(images, 0.0) is images
    probe = torch.rand(1, 9, 8, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: gaussian_blur(x, sigma), (probe,))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("dims, shape", [(2, (3, 5, 20, 17)), (3, (2, 5, 14, 16, 13))])
def test_both_valid_filterings_match_a_float64_convolution(dims, shape, dtype):
    """The SSIM's separable Gaussian filtering, as shifted sums (the CPU's) and as ``conv1d``
    (other devices'), against NumPy's valid convolution along each axis in float64; and the
    shifted sums' gradient against finite differences."""
    from fgat.recon.metrics import _filter_valid_conv, _filter_valid_shifted, gaussian_window

    image = torch.rand(shape, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    window = gaussian_window(1.5, dtype=torch.float64)
    expected = image.numpy()
    for axis in range(len(shape) - dims, len(shape)):
        expected = np.apply_along_axis(np.convolve, axis, expected, window.numpy(), "valid")
    tolerance = {"rtol": 1e-5, "atol": 1e-6} if dtype == torch.float32 else {"rtol": 1e-12}
    for filtering in (_filter_valid_shifted, _filter_valid_conv):
        got = filtering(image.to(dtype), window.to(dtype), dims)
        np.testing.assert_allclose(got.double().numpy(), expected, **tolerance)
    if dtype == torch.float64:
        small = torch.rand((1,) + (12,) * dims, dtype=dtype, requires_grad=True)
        assert torch.autograd.gradcheck(lambda x: _filter_valid_shifted(x, window, dims), (small,))


def ellipsoid_grid(shape, voxel_um, centre_um):
    """Coordinates ``(3, Z, Y, X)`` of the voxel centres from ``centre_um``, um."""
    axes = [np.arange(n) * d - c for n, d, c in zip(shape, voxel_um, centre_um)]
    return np.stack(np.meshgrid(*axes, indexing="ij"))


def test_axial_lateral_aspect_of_an_ellipsoid_and_a_shell():
    voxel = (0.3, 0.25, 0.25)  # anisotropic: the aspect is in um
    z, y, x = ellipsoid_grid((60, 72, 72), voxel, (9.0, 9.0, 9.0))
    a, b = 6.0, 4.0
    solid = (((z / a) ** 2 + (y / b) ** 2 + (x / b) ** 2) <= 1).astype(np.float32)
    solid[50, 60, 60] = 3.0  # a brighter bead apart from it: not the object
    result = axial_lateral_aspect(solid, voxel)
    # a solid ellipsoid's second moments are a^2 / 5 and b^2 / 5
    assert result["aspect"] == pytest.approx(a / b, rel=0.01)
    assert result["sigma_z_um"] == pytest.approx(a / math.sqrt(5), rel=0.01)
    assert result["sigma_x_um"] == pytest.approx(b / math.sqrt(5), rel=0.01)
    assert result["voxels"] == int((solid == 1).sum())
    # a spherical shell between r1 and r2: <z^2> = (r2^5 - r1^5) / (5 (r2^3 - r1^3))
    r = np.sqrt(z**2 + y**2 + x**2)
    r1, r2 = 5.0, 6.0
    shell = ((r >= r1) & (r <= r2)).astype(np.float32)
    result = axial_lateral_aspect(shell, voxel)
    sigma = math.sqrt((r2**5 - r1**5) / (5 * (r2**3 - r1**3)))
    assert result["aspect"] == pytest.approx(1.0, abs=0.01)
    assert result["sigma_z_um"] == pytest.approx(sigma, rel=0.01)
    # squashed along z by 2 (the depth scale halved): aspect 1/2
    squashed = (np.sqrt((2 * z) ** 2 + y**2 + x**2) >= r1) & (
        np.sqrt((2 * z) ** 2 + y**2 + x**2) <= r2
    )
    assert axial_lateral_aspect(squashed, voxel)["aspect"] == pytest.approx(0.5, rel=0.02)


def test_axial_lateral_aspect_of_an_empty_volume_and_bad_input():
    result = axial_lateral_aspect(np.zeros((4, 5, 6)), (1, 1, 1))
    assert math.isnan(result["aspect"]) and result["voxels"] == 0
    assert math.isnan(axial_lateral_aspect(np.full((4, 5, 6), np.nan), (1, 1, 1))["aspect"])
    with pytest.raises(ValueError, match="voxel_size_um must be three positive sizes"):
        axial_lateral_aspect(np.ones((4, 5, 6)), (1, 0, 1))
    with pytest.raises(ValueError, match="threshold must be in"):
        axial_lateral_aspect(np.ones((4, 5, 6)), (1, 1, 1), threshold=1.0)
