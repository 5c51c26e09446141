import math

import numpy as np
import pytest
import torch

from fgat.optics.lenslets import hexagonal_offsets
from fgat.optics.pupil import (
    aperture_circumradius,
    lattice_angle,
    lenslet_aperture,
    pupil_coordinates,
    zernike_disk_radius,
)


def test_pupil_coordinates(dtype):
    rows, cols = torch.meshgrid(
        torch.arange(5, dtype=dtype), torch.arange(5, dtype=dtype), indexing="ij"
    )
    rho, theta = pupil_coordinates(rows, cols, (2.0, 2.0), 2.0)
    assert rho[2, 4].item() == pytest.approx(1.0)
    assert rho[0, 0].item() == pytest.approx(math.sqrt(8) / 2)
    assert theta[4, 2].item() == pytest.approx(math.pi / 2)  # +y is the row direction
    assert theta[2, 0].item() == pytest.approx(math.pi)


def test_circular_lenslet_aperture_is_a_disk():
    dy, dx = torch.meshgrid(
        torch.arange(-20.0, 21.0, dtype=torch.float64),
        torch.arange(-20.0, 21.0, dtype=torch.float64),
        indexing="ij",
    )
    disk = lenslet_aperture(dy, dx, shape="circle", radius=12.3)
    assert torch.equal(disk, dy**2 + dx**2 <= 12.3**2)
    assert aperture_circumradius("circle", 12.3) == 12.3
    with pytest.raises(ValueError, match="lenslet shape"):
        lenslet_aperture(dy, dx, shape="square", radius=12.3)


@pytest.mark.parametrize("angle", [0.0, 0.3, -0.45])
def test_hexagonal_lenslet_aperture(angle):
    """Area (sqrt(3) / 2) w^2 within pixelisation; flats at ``angle + k 60`` degrees (a point
    just beyond the inradius along a flat normal is outside, one at the same distance towards
    a vertex inside), and a rotated hexagon is the unrotated one on rotated coordinates."""
    width = 77.0
    step = 0.25
    u = torch.arange(-50.0, 50.0 + step / 2, step, dtype=torch.float64)
    dy, dx = torch.meshgrid(u, u, indexing="ij")
    mask = lenslet_aperture(dy, dx, shape="hexagon", radius=width / 2, angle=angle)
    area = float(mask.sum()) * step**2
    perimeter = 6 * width / math.sqrt(3.0)
    assert abs(area - math.sqrt(3.0) / 2.0 * width**2) <= perimeter * step / 2  # pixelisation
    assert float((dy[mask] ** 2 + dx[mask] ** 2).max().sqrt()) <= aperture_circumradius(
        "hexagon", width / 2
    )
    for k in range(6):
        normal = angle + k * math.pi / 3
        for direction, inside in ((normal, False), (normal + math.pi / 6, True)):
            point = 1.05 * width / 2
            y = torch.tensor([point * math.sin(direction)], dtype=torch.float64)
            x = torch.tensor([point * math.cos(direction)], dtype=torch.float64)
            hit = lenslet_aperture(y, x, shape="hexagon", radius=width / 2, angle=angle)
            assert bool(hit) is inside
    c, s = math.cos(angle), math.sin(angle)
    unrotated = lenslet_aperture(
        c * dy - s * dx, c * dx + s * dy, shape="hexagon", radius=width / 2
    )
    assert (unrotated != mask).float().mean() < 1e-3


def test_lattice_angle_follows_rotated_centres():
    nominal = hexagonal_offsets(7, 76.9) + 128.0
    assert lattice_angle(torch.from_numpy(nominal)) == pytest.approx(0.0, abs=1e-12)
    for rotation in (0.25, -0.4):
        # A turn of the image by `rotation` in the theta sense (from +col towards +row).
        turn = np.array(
            [[math.cos(rotation), -math.sin(rotation)], [math.sin(rotation), math.cos(rotation)]]
        )
        offsets = (nominal - nominal[0]) @ turn
        centers = torch.from_numpy(offsets + nominal[0])
        assert lattice_angle(centers) == pytest.approx(rotation, abs=1e-12)
    assert lattice_angle(torch.tensor([[5.0, 5.0]])) == 0.0


def test_zernike_disk_radius_circumscribes_the_lit_mask():
    centers = torch.tensor(hexagonal_offsets(7, 10.0)) + torch.tensor([3.0, -2.0])
    assert zernike_disk_radius("pupil", 17.0, centers, 5.0) == 17.0
    assert zernike_disk_radius("aperture", 17.0, centers, 5.0) == pytest.approx(15.0)
    # Lenslets reaching past the pupil: the mask ends at the pupil's edge.
    assert zernike_disk_radius("aperture", 13.0, centers, 5.0) == 13.0
    hexagon = aperture_circumradius("hexagon", 5.0)
    assert zernike_disk_radius("aperture", 30.0, centers, hexagon) == pytest.approx(10 + hexagon)
