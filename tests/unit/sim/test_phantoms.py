import numpy as np
import pytest

from fgat.io.images import write_tiff
from fgat.sim.phantoms import (
    bead_positions,
    beads,
    lenslet_flat,
    line_sphere,
    noisy_measurement,
    reticular,
    shell_beads,
)
from tests.conftest import SHARED_DATA


def test_beads_reproducible_and_spaced():
    a = beads((20, 40, 40), 25, sigma=1.2, min_spacing=5, margin=2, seed=7)
    assert a.dtype == np.float32 and a.shape == (20, 40, 40) and a.max() == 1.0
    np.testing.assert_array_equal(
        a, beads((20, 40, 40), 25, sigma=1.2, min_spacing=5, margin=2, seed=7)
    )
    assert not np.array_equal(
        a, beads((20, 40, 40), 25, sigma=1.2, min_spacing=5, margin=2, seed=8)
    )
    positions = bead_positions(
        (20, 40, 40), 25, min_spacing=5, margin=(2, 3, 4), rng=np.random.default_rng(0)
    )
    distances = np.linalg.norm(positions[:, None] - positions[None], axis=2)
    assert distances[~np.eye(25, dtype=bool)].min() >= 5
    assert (positions >= [2, 3, 4]).all() and (positions <= [17, 36, 35]).all()


def test_point_beads_are_single_voxels():
    volume = beads((16, 32, 32), 10, sigma=0.0, min_spacing=3, intensity_range=(0.2, 1.0), seed=1)
    assert np.count_nonzero(volume) == 10
    assert volume[volume > 0].min() >= 0.2 - 1e-6


def test_impossible_packing_is_reported():
    with pytest.raises(
        ValueError, match="cannot fit in shape \\(4, 4, 4\\).*at most 11 even densely packed"
    ):
        beads(
            (4, 4, 4), 50, min_spacing=3
        )  # 0.74 * 6^3 / (pi 3^3 / 6) = 11.3 spheres of diameter 3
    with pytest.raises(ValueError, match="could not place 10 beads"):
        beads((4, 4, 4), 10, min_spacing=3)  # under the packing bound, beyond random placement


def test_line_sphere_reproducible_in_unit_range():
    a = line_sphere((24, 48, 48), seed=3)
    np.testing.assert_array_equal(a, line_sphere((24, 48, 48), seed=3))
    assert a.min() >= 0 and a.max() == pytest.approx(1.0)
    assert 0.01 < (a > 0.5).mean() < 0.5


def test_hollow_spheres_are_dark_inside():
    volume = line_sphere(
        (40, 40, 40),
        n_lines=0,
        n_spheres=1,
        radius_range=(10, 10),
        shell_width=2,
        hollow_fraction=1.0,
        seed=0,
    )
    z, y, x = np.unravel_index(np.argmax(volume), volume.shape)
    center = np.array(np.nonzero(volume > 0.5)).mean(axis=1).round().astype(int)
    assert volume[tuple(center)] < 0.1  # the shell's centre is empty
    assert volume.max() > 0.5


def test_reticular_resamples_a_tiff(tmp_path):
    source = np.zeros((20, 20, 20), np.float32)
    source[5:15, 5:15, 5:15] = 4.0
    path = write_tiff(tmp_path / "truth.tif", source)
    volume = reticular(path, (10, 40, 40))
    assert volume.shape == (10, 40, 40) and volume.max() == pytest.approx(1.0)
    assert volume[5, 20, 20] == pytest.approx(1.0) and volume[0, 0, 0] == 0.0


@pytest.mark.skipif(
    not (SHARED_DATA / "reticular1" / "data.tif").exists(), reason="external 3DGAT data not present"
)
def test_reticular_3dgat_scene():
    volume = reticular(SHARED_DATA / "reticular1" / "data.tif", (31, 64, 64))
    assert volume.shape == (31, 64, 64) and volume.max() == pytest.approx(1.0)
    assert 0.001 < (volume > 0.2).mean() < 0.5


def test_poisson_and_read_noise_statistics():
    clean = np.full((300, 300), 2.0)
    counts = noisy_measurement(clean, photons=50.0, background=10.0, seed=0)
    n = counts.size
    assert counts.mean() == pytest.approx(60.0, abs=4 * np.sqrt(60.0 / n))
    assert counts.var() == pytest.approx(60.0, abs=4 * 60.0 * np.sqrt(2.0 / n))
    assert np.array_equal(counts, np.round(counts))  # shot noise gives integer counts
    noisy = noisy_measurement(clean, photons=50.0, background=10.0, read_noise=3.0, seed=1)
    assert noisy.var() == pytest.approx(69.0, abs=4 * 69.0 * np.sqrt(2.0 / n))
    np.testing.assert_array_equal(
        noisy_measurement(clean, background=5.0), clean + 5.0
    )  # noise-free
    np.testing.assert_array_equal(
        counts, noisy_measurement(clean, photons=50.0, background=10.0, seed=0)
    )


def test_offset_is_a_bias_and_background_a_map():
    clean = np.full((300, 300), 2.0)
    dark = np.zeros_like(clean)
    dark[10, 20] = 500.0  # a hot pixel: dark signal with shot noise
    counts = noisy_measurement(clean, photons=50.0, background=dark, offset=100.0, seed=0)
    n = counts.size
    assert counts.mean() == pytest.approx(150.0 + 500.0 / n, abs=4 * np.sqrt(50.0 / n))
    assert np.delete(counts, 10 * 300 + 20).var() == pytest.approx(50.0, rel=0.05)  # no shot
    # noise from the offset
    assert counts[10, 20] > 100 + 50 + 500 - 5 * np.sqrt(550)
    np.testing.assert_array_equal(  # noise-free: clean + dark map + offset
        noisy_measurement(clean, background=dark, offset=100.0), clean + dark + 100.0
    )
    np.testing.assert_array_equal(  # offset 0 is the plain model, bit for bit
        noisy_measurement(clean, photons=50.0, background=10.0, read_noise=2.0, seed=3),
        noisy_measurement(clean, photons=50.0, background=10.0, read_noise=2.0, seed=3, offset=0),
    )


def test_lenslet_flat_disks():
    centers = np.array([[50.3, 60.7], [50.3, 120.2], [-40.0, 10.0]])  # the last misses the sensor
    flat = lenslet_flat((100, 160), centers, 20.0, [1.0, 0.6, 1.0])
    assert flat.shape == (100, 160) and flat.max() == pytest.approx(1.0, abs=1e-6)
    rows, cols = np.mgrid[:100, :160]
    for (row, col), gain in zip(centers[:2], (1.0, 0.6)):
        distance = np.hypot(rows - row, cols - col)
        assert np.allclose(flat[distance < 15], gain, rtol=1e-3)  # uniform inside
        assert flat[(distance > 23) & (distance < 30)].max() < 1e-2 * gain  # smooth, narrow edge
        area = flat[distance < 35].sum() / gain
        assert area == pytest.approx(np.pi * 20.0**2, rel=0.01)
    assert flat[:, 150:].max() < 1e-6
    with pytest.raises(ValueError, match="gains must be"):
        lenslet_flat((100, 160), centers, 20.0, [1.0, 0.6])


def test_measurement_errors():
    with pytest.raises(ValueError, match="non-negative"):
        noisy_measurement(-np.ones(3))
    with pytest.raises(ValueError, match="photons"):
        noisy_measurement(np.ones(3), photons=0)


def test_moving_beads_translate_and_rotate_rigidly():
    from fgat.sim.phantoms import moving_beads

    shape = (12, 41, 41)
    still = moving_beads(shape, [0.0], 8, sigma=1.0, min_spacing=5, margin=(3, 12, 12), seed=4)
    np.testing.assert_array_equal(
        still[0], beads(shape, 8, sigma=1.0, min_spacing=5, margin=(3, 12, 12), seed=4)
    )
    shifted = moving_beads(
        shape, [0.0, 1.0], 8, velocity=(0, 3, 0), rotation_deg=0, margin=(3, 12, 12), seed=4
    )
    np.testing.assert_allclose(shifted[1], np.roll(shifted[0], 3, axis=1), atol=1e-6)
    turned = moving_beads(
        shape, [0.0, 1.0], 8, velocity=(0, 0, 0), rotation_deg=90, margin=(3, 12, 12), seed=4
    )
    # equal up to where each bead's 4-sigma footprint is cut (exp(-8) = 3.4e-4 of its peak)
    np.testing.assert_allclose(turned[1], np.rot90(turned[0], 1, axes=(1, 2)), atol=4e-4)
    assert np.abs(turned[1] - turned[0]).max() > 0.5  # while the beads did move


def test_beating_shell_contracts_and_relaxes():
    from fgat.sim.phantoms import beating_shell

    shape = (25, 49, 49)
    frames = beating_shell(shape, [0.0, 0.5, 1.0], contraction=0.25)
    np.testing.assert_allclose(frames[2], frames[0], atol=1e-6)  # one full beat
    radius = 0.35 * 49
    for frame, expected in ((frames[0], radius), (frames[1], 0.75 * radius)):
        profile = frame[12, 24, 24:]
        assert abs(int(np.argmax(profile)) - expected) <= 1.0
        assert frame[12, 24, 24] < 1e-3  # hollow
    with pytest.raises(ValueError, match="contraction must be in"):
        beating_shell(shape, [0.0], contraction=1.0)


SHELL_VOXEL_UM = (0.5, 0.54, 0.54)  # anisotropic, as FLFM grids are


def tanh_wall(distance_um, wall_um, edge_um):
    return 0.5 * (1 - np.tanh((np.abs(distance_um) - wall_um / 2) / edge_um))


def test_shell_beads_shell_is_round_in_um_with_the_analytic_profile_and_volume():
    diameter, wall = 12.0, 1.0
    shape = (31, 29, 29)  # odd: the centre is a voxel
    volume = shell_beads(shape, voxel_size_um=SHELL_VOXEL_UM, diameter_um=diameter, n_beads=0)
    assert volume.dtype == np.float32 and volume.shape == shape
    middle, edge = (diameter - wall) / 2, 0.5 * max(SHELL_VOXEL_UM)
    peak = tanh_wall(0.0, wall, edge)  # the wall's peak, scaled to 1
    # radial profiles along z and x (different voxel sizes) are the same function of r in um
    centre = tuple(n // 2 for n in shape)
    for axis in (0, 2):
        index = np.arange(shape[axis] // 2 + 1)
        line = volume[tuple(slice(c, None) if k == axis else c for k, c in enumerate(centre))]
        expected = tanh_wall(index * SHELL_VOXEL_UM[axis] - middle, wall, edge) / peak
        np.testing.assert_allclose(line, expected, atol=2e-3)
    # integrated light: 4 pi (R^2 w + w^3 / 12 + w pi^2 e^2 / 12) um^3 for a tanh-edged wall
    # (a box of width w smoothed by a logistic of variance pi^2 e^2 / 12) of mid-radius R
    analytic = 4 * np.pi * wall * (middle**2 + wall**2 / 12 + np.pi**2 * edge**2 / 12)
    measured = volume.sum(dtype=np.float64) * peak * np.prod(SHELL_VOXEL_UM)
    assert measured == pytest.approx(analytic, rel=0.01)
    assert volume[centre] < 1e-6  # hollow


def test_shell_beads_beads_lie_outside_the_shell():
    from scipy.ndimage import maximum_filter

    shape, n_beads, clearance = (31, 40, 40), 12, 2.0
    volume = shell_beads(
        shape,
        voxel_size_um=SHELL_VOXEL_UM,
        diameter_um=10.0,
        n_beads=n_beads,
        clearance_um=clearance,
        seed=3,
    )
    np.testing.assert_array_equal(
        volume,
        shell_beads(
            shape,
            voxel_size_um=SHELL_VOXEL_UM,
            diameter_um=10.0,
            n_beads=n_beads,
            clearance_um=clearance,
            seed=3,
        ),
    )
    centre = (np.asarray(shape) - 1) / 2
    radius_um = np.linalg.norm(
        (np.stack(np.meshgrid(*map(np.arange, shape), indexing="ij"), -1) - centre)
        * SHELL_VOXEL_UM,
        axis=-1,
    )
    peaks = (volume == maximum_filter(volume, size=3)) & (volume > 0.3) & (radius_um > 5.5)
    # every bead is a separate peak, its centre within half a voxel of >= 5 + 2 um
    assert peaks.sum() == n_beads
    assert radius_um[peaks].min() >= 5.0 + clearance - 0.5 * np.linalg.norm(SHELL_VOXEL_UM)
    assert volume[radius_um < 2.5].max() < 1e-4  # nothing in the hollow


def test_bead_positions_keep_rejects_positions():
    rng = np.random.default_rng(0)
    positions = bead_positions((10, 20, 20), 30, rng=rng, keep=lambda p: p[2] > 10)
    assert positions.shape == (30, 3) and (positions[:, 2] > 10).all()
    with pytest.raises(ValueError, match="could not place"):
        bead_positions((10, 20, 20), 3, rng=rng, keep=lambda p: False)


@pytest.mark.parametrize(
    "options, message",
    [
        ({"wall_um": 6.0}, "wall_um = 6 must be under half of diameter_um = 12"),
        ({"voxel_size_um": (0.5, 0.0, 0.5)}, "voxel_size_um must be three positive sizes"),
        ({"voxel_size_um": (0.5, 0.5)}, "voxel_size_um must be 3 numbers"),
    ],
)
def test_shell_beads_refuses_bad_options(options, message):
    options = {"voxel_size_um": SHELL_VOXEL_UM, "diameter_um": 12.0, **options}
    with pytest.raises(ValueError, match=message):
        shell_beads((9, 9, 9), **options)
