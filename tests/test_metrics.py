import numpy as np
import pytest
import torch
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from fgat.metrics import compare_volumes, gaussian_blur, max_normalize, mip, psnr, ssim


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
    from fgat.metrics import border_ratio

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
    from fgat.metrics import align_to_truth

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
