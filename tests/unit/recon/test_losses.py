import numpy as np
import pytest
import torch

from fgat.recon.losses import fourier_loss, fourier_weight, pixel_loss, ssim_loss, static_loss
from fgat.recon.metrics import ssim


def test_terms_against_numpy():
    rng = np.random.default_rng(0)
    a, b = rng.random((3, 16, 20)), rng.random((3, 16, 20))
    ta, tb = torch.from_numpy(a), torch.from_numpy(b)
    assert float(pixel_loss(ta, tb, 1)) == pytest.approx(np.abs(a - b).mean())
    assert float(pixel_loss(ta, tb, 2)) == pytest.approx(((a - b) ** 2).mean())
    expected = np.abs(np.fft.fft2(a) - np.fft.fft2(b)).sum(axis=(1, 2)).mean() / (16 * 20)
    assert float(fourier_loss(ta, tb)) == pytest.approx(expected)
    assert float(ssim_loss(ta, tb, 1.0)) == pytest.approx(
        1 - float(ssim(ta, tb, 1.0, spatial_dims=2))
    )


def test_annealed_weight_and_total():
    assert fourier_weight(0, 100, 2.0) == pytest.approx(2.0)
    assert fourier_weight(100, 100, 2.0) == pytest.approx(0.4)
    assert fourier_weight(50, 100, 2.0) == pytest.approx(1.2)
    a, b = torch.rand(2, 16, 16), torch.rand(2, 16, 16)
    terms = static_loss(a, b, step=50, total_steps=100, lambda_fourier=2.0, lambda_ssim=0.5)
    expected = terms["pix"] + 1.2 * terms["fft"] + 0.5 * terms["ssim"]
    torch.testing.assert_close(terms["total"], expected)
    assert set(static_loss(a, b, step=0, total_steps=10)) == {"total", "pix"}
    with pytest.raises(ValueError, match="p must be"):
        pixel_loss(a, b, 3)


def test_masked_terms_against_numpy():
    rng = np.random.default_rng(1)
    a, b = rng.random((3, 16, 20)), rng.random((3, 16, 20))
    mask = (rng.random((3, 16, 20)) > 0.2).astype(np.float64)
    b[mask == 0] = 1e200  # hot pixels: ignored, however hot (their square overflows float64)
    ta, tb, tm = torch.from_numpy(a), torch.from_numpy(b), torch.from_numpy(mask)
    use = mask > 0
    assert float(pixel_loss(ta, tb, 1, tm)) == pytest.approx(np.abs(a - b)[use].mean())
    assert float(pixel_loss(ta, tb, 2, tm)) == pytest.approx(((a - b)[use] ** 2).mean())
    b[~use] = 0.0
    tb = torch.from_numpy(b)
    am, bm = a * mask, b * mask
    expected = np.abs(np.fft.fft2(am) - np.fft.fft2(bm)).sum(axis=(1, 2)).mean() / (16 * 20)
    assert float(fourier_loss(ta, tb, tm)) == pytest.approx(expected)
    assert float(ssim_loss(ta, tb, 1.0, tm)) == pytest.approx(
        1 - float(ssim(torch.from_numpy(am), torch.from_numpy(bm), 1.0, spatial_dims=2))
    )
    # a (H, W) mask broadcasts over views; None is the unmasked loss exactly
    plane = torch.from_numpy(use[0].astype(np.float64))
    assert float(pixel_loss(ta, tb, 1, plane)) == pytest.approx(np.abs(a - b)[:, use[0]].mean())
    terms = static_loss(ta, tb, step=3, total_steps=10, lambda_fourier=1.0, lambda_ssim=0.5)
    unmasked = static_loss(
        ta, tb, step=3, total_steps=10, lambda_fourier=1.0, lambda_ssim=0.5, mask=None
    )
    for name, value in terms.items():
        assert torch.equal(value, unmasked[name])
    masked = static_loss(ta, tb, step=3, total_steps=10, lambda_fourier=1.0, mask=tm)
    assert float(masked["pix"]) == pytest.approx(float(pixel_loss(ta, tb, 1, tm)))


def test_masked_pixel_loss_gradient_ignores_masked_pixels():
    """The gradient of the masked mean square, ``2 (p - t) m / sum(m)`` (numpy, float64): zero
    and finite at a masked pixel however hot its target."""
    rng = np.random.default_rng(2)
    p, t = rng.random((2, 8, 8)), rng.random((2, 8, 8))
    t[1, 3, 3] = 1e200
    m = np.ones((2, 8, 8))
    m[1, 3, 3] = 0
    prediction = torch.from_numpy(p).requires_grad_(True)
    pixel_loss(prediction, torch.from_numpy(t), 2, torch.from_numpy(m)).backward()
    expected = 2 * (p - t) * m / m.sum()
    np.testing.assert_allclose(prediction.grad.numpy(), expected, rtol=1e-12, atol=0)
    assert prediction.grad[1, 3, 3] == 0
