import numpy as np
import pytest

from fgat.app.cli import main
from fgat.instrument.centres import write_centers
from fgat.io.images import read_tiff
from fgat.optics.lenslets import hexagonal_offsets
from fgat.optics.sampling import (
    advised_plane_spacing_um,
    crop_overlap_note,
    depth_spacing_warning,
    largest_separate_radius,
    parallax_px_per_um,
    psf_centroids,
)
from fgat.optics.spec import OpticsSpec
from fgat.optics.systems import load_system


def moving_spots(rates_px_per_um, depths_um, size=41, sigma=1.5):
    """(V, Z, size, size) Gaussian spots whose centre moves along the columns at a known rate."""
    grid = np.arange(size) - size // 2
    stack = []
    for rate in rates_px_per_um:
        planes = []
        for z in depths_um:
            shift = rate * z
            planes.append(
                np.exp(-(grid[:, None] ** 2 + (grid[None, :] - shift) ** 2) / (2 * sigma**2))
            )
        stack.append(planes)
    return np.asarray(stack)


def test_centroids_and_parallax_of_spots_moving_at_known_rates():
    depths = np.linspace(-4.0, 4.0, 9)
    rates = [0.0, 0.5, -1.25]
    stack = moving_spots(rates, depths)
    centroids = psf_centroids(stack)
    np.testing.assert_allclose(centroids[2, :, 1], -1.25 * depths, atol=1e-6)
    np.testing.assert_allclose(centroids[..., 0], 0.0, atol=1e-9)
    np.testing.assert_allclose(parallax_px_per_um(stack, depths), np.abs(rates), atol=1e-6)


def test_parallax_of_the_small_system_is_the_documented_028_px_per_um():
    depths = [-20.0, -10.0, 0.0, 10.0, 20.0]
    psf = OpticsSpec(load_system("small"), tuple(depths)).psf()
    parallax = parallax_px_per_um(psf, depths)
    assert parallax[0] < 0.01  # the on-axis view does not move
    assert parallax[1:] == pytest.approx(0.284, abs=0.01)  # "0.28 px per um" (small.yaml)


def test_depth_spacing_warning_follows_the_parallax():
    coarse = np.linspace(-4.0, 4.0, 9)  # 1 um apart
    stack = moving_spots([0.0, 2.0], coarse)
    message = depth_spacing_warning(stack, coarse)
    assert "view 1 moves 2.00 px per um" in message and "at most 0.5 um apart" in message
    fine = np.linspace(-2.0, 2.0, 11)  # 0.4 um apart: 0.8 px per plane
    assert depth_spacing_warning(moving_spots([0.0, 2.0], fine), fine) is None


def test_crop_overlap_note_when_crops_are_wider_than_the_pitch():
    centers = hexagonal_offsets(7, 10.0) + 50.0
    assert "11 px crops (radius 5) are wider than the 10.0 px lenslet pitch" in crop_overlap_note(
        centers, 5
    )
    assert crop_overlap_note(centers, 4) is None


def test_psf_command_takes_measured_centres_and_warns_about_coarse_planes(tmp_path, capsys):
    system = load_system("small")
    nominal = system.lenslet_centers_px()
    angle = np.radians(0.8)
    rotation = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    measured = (nominal - nominal[0]) @ rotation.T + nominal[0] + [0.6, -0.3]
    write_centers(tmp_path / "centers.csv", measured)
    out = tmp_path / "psf.ome.tif"
    command = ["psf", "--system", "small", "--depths-um=-20,-10,0,10,20", "--out", str(out)]
    assert main([*command, "--centers", str(tmp_path / "centers.csv")]) == 0
    expected = OpticsSpec(system, (-20.0, -10.0, 0.0, 10.0, 20.0), measured).psf()
    np.testing.assert_allclose(read_tiff(out), expected, rtol=0, atol=1e-6 * expected.max())
    assert "too coarse for the parallax" in capsys.readouterr().err
    write_centers(tmp_path / "six.csv", measured[:6])
    assert main([*command, "--centers", str(tmp_path / "six.csv"), "--overwrite"]) == 2
    assert "6 lenslet centres, but system 'small' has 7" in capsys.readouterr().err


def curved_spots(linear, cubic, depths_um, size=61, sigma=1.5):
    """(2, Z, size, size): a fixed spot and one whose column moves as ``linear z + cubic z^3``
    (the local parallax grows towards the ends of the range, as at high NA)."""
    grid = np.arange(size) - size // 2
    shifts = linear * np.asarray(depths_um) + cubic * np.asarray(depths_um) ** 3
    planes = [
        np.exp(-(grid[:, None] ** 2 + (grid[None, :] - shift) ** 2) / (2 * sigma**2))
        for shift in shifts
    ]
    still = np.exp(-(grid[:, None] ** 2 + grid[None, :] ** 2) / (2 * sigma**2))
    return np.stack([np.broadcast_to(still, (len(planes), size, size)), np.stack(planes)])


@pytest.mark.parametrize("cubic,planes", [(0.0, 9), (0.02, 9), (0.05, 5), (0.05, 17)])
def test_advised_plane_spacing_passes_its_own_check_over_the_whole_range(cubic, planes):
    depths = np.linspace(-4.0, 4.0, planes)
    message = depth_spacing_warning(curved_spots(1.5, cubic, depths), depths)
    advised = advised_plane_spacing_um(curved_spots(1.5, cubic, depths), depths)
    assert f"at most {advised:g} um apart" in message
    # The true largest parallax is the derivative at the ends, 1.5 + 3 cubic 4^2 px/um.
    assert advised <= 1.0 / (1.5 + 3 * cubic * 16)
    followed = np.linspace(-4.0, 4.0, int(np.ceil(8.0 / advised)) + 1)
    assert np.diff(followed).max() <= advised
    assert depth_spacing_warning(curved_spots(1.5, cubic, followed), followed) is None


def test_advised_plane_spacing_rounds_down():
    depths = np.linspace(-4.0, 4.0, 9)
    # 1 / 4.8 = 0.2083 um: rounding to 0.21 would leave 1.008 px steps.
    assert advised_plane_spacing_um(moving_spots([0.0, 4.8], depths, size=61), depths) == 0.2
    followed = np.linspace(-4.0, 4.0, 41)
    assert depth_spacing_warning(moving_spots([0.0, 4.8], followed, size=61), followed) is None


@pytest.mark.parametrize("pitch", [10.0, 10.5, 11.0, 126.5, 127.0, 128.0])
def test_advised_crop_radius_passes_the_overlap_check(pitch):
    centers = np.array([[50.0, 50.0], [50.0, 50.0 + pitch]])
    radius = largest_separate_radius(pitch)
    assert crop_overlap_note(centers, radius) is None
    assert 2 * radius + 1 <= pitch < 2 * (radius + 1) + 1
    note = crop_overlap_note(centers, radius + 1)
    assert f"a crop radius <= {radius} px keeps the views apart" in note


def test_crop_radius_63_at_pitch_126_5_is_refused_and_62_advised():
    centers = np.array([[0.0, 0.0], [0.0, 126.5]])
    note = crop_overlap_note(centers, 63)
    assert "127 px crops (radius 63) are wider than the 126.5 px lenslet pitch" in note
    assert "radius <= 62 px" in note
    assert crop_overlap_note(centers, 62) is None
