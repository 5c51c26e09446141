import numpy as np
import pytest
import torch

from fgat.losses import fourier_loss, fourier_weight, pixel_loss, ssim_loss, static_loss
from fgat.metrics import ssim


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
