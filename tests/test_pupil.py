import math

import pytest
import torch

from fgat.optics.pupil import pupil_coordinates


def test_pupil_coordinates(dtype):
    rows, cols = torch.meshgrid(
        torch.arange(5, dtype=dtype), torch.arange(5, dtype=dtype), indexing="ij"
    )
    rho, theta = pupil_coordinates(rows, cols, (2.0, 2.0), 2.0)
    assert rho[2, 4].item() == pytest.approx(1.0)
    assert rho[0, 0].item() == pytest.approx(math.sqrt(8) / 2)
    assert theta[4, 2].item() == pytest.approx(math.pi / 2)  # +y is the row direction
    assert theta[2, 0].item() == pytest.approx(math.pi)
