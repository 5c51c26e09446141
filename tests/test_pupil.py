import math

import pytest
import torch

from fgat.optics.pupil import aperture_geometry, circular_mask, complex_pupil, pixel_grid, pupil_coordinates


def test_aperture_geometry_recovers_disk():
    rows, cols = pixel_grid((400, 300), dtype=torch.float64)
    mask = circular_mask(rows, cols, (190.3, 140.7), 95.2)
    (cy, cx), radius = aperture_geometry(mask)
    assert cy == pytest.approx(190.3, abs=0.05)
    assert cx == pytest.approx(140.7, abs=0.05)
    assert radius == pytest.approx(95.2, abs=0.05)


def test_pupil_coordinates_and_complex_pupil(dtype):
    rows, cols = pixel_grid((5, 5), dtype=dtype)
    rho, theta = pupil_coordinates(rows, cols, (2.0, 2.0), 2.0)
    assert rho[2, 4].item() == pytest.approx(1.0)
    assert theta[4, 2].item() == pytest.approx(math.pi / 2)  # +y is the row direction
    mask = rho <= 1
    phase = torch.full((5, 5), 0.7, dtype=dtype)
    pupil = complex_pupil(mask, phase)
    assert torch.equal(pupil.abs() > 0.5, mask)
    assert torch.allclose(torch.angle(pupil[mask]), torch.full_like(pupil[mask].real, 0.7))


def test_empty_and_bad_masks():
    with pytest.raises(ValueError, match="empty"):
        aperture_geometry(torch.zeros(4, 4, dtype=torch.bool))
    with pytest.raises(ValueError, match="2D"):
        aperture_geometry(torch.ones(2, 4, 4, dtype=torch.bool))
