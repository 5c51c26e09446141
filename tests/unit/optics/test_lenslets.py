import math

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from fgat.optics.lenslets import detect_lenslet_centers, hexagonal_offsets, sort_lenslet_centers
from fgat.optics.systems import load_system


def brightfield(centers, radius, shape, *, blur=3.0, seed=0, supersample=4):
    """Anti-aliased bright disks on a dark background, blurred, with Poisson and read noise."""
    rows, cols = np.mgrid[0 : shape[0] * supersample, 0 : shape[1] * supersample] / supersample
    rows, cols = rows + 0.5 / supersample - 0.5, cols + 0.5 / supersample - 0.5
    image = np.zeros(rows.shape)
    for r, c in centers:
        image += (rows - r) ** 2 + (cols - c) ** 2 <= radius**2
    image = image.reshape(shape[0], supersample, shape[1], supersample).mean(axis=(1, 3))
    rng = np.random.default_rng(seed)
    image = gaussian_filter(image, blur) * 200 + 20
    return rng.poisson(image) + rng.normal(0, 3, image.shape)


def test_seven_lens_geometry():
    offsets = hexagonal_offsets(7, 4.0)
    distances = np.hypot(*offsets.T)
    np.testing.assert_allclose(distances, [0] + [4.0] * 6, atol=1e-12)
    angles = np.degrees(np.arctan2(-offsets[1:, 0], offsets[1:, 1])) % 360
    np.testing.assert_allclose(angles, [0, 60, 120, 180, 240, 300], atol=1e-9)
    pairwise = np.hypot(*(offsets[:, None] - offsets[None]).transpose(2, 0, 1))
    assert np.sort(pairwise[0])[1] == pytest.approx(4.0)


@pytest.mark.parametrize("n", [1, 3, 7, 12, 19, 37])
def test_any_count_is_a_hexagonal_packing(n):
    offsets = hexagonal_offsets(n)
    assert offsets.shape == (n, 2)
    if n > 1:
        pairwise = np.hypot(*(offsets[:, None] - offsets[None]).transpose(2, 0, 1))
        assert pairwise[~np.eye(n, dtype=bool)].min() == pytest.approx(1.0)
    distances = np.hypot(*offsets.T)
    assert np.all(np.diff(np.round(distances, 9)) >= 0)  # centre first, then ring by ring


def test_sort_recovers_view_order_from_shuffled_noisy_centers():
    truth = hexagonal_offsets(19, 100.0) + [500.0, 500.0]
    rng = np.random.default_rng(1)
    noisy = truth + rng.normal(0, 2.0, truth.shape)
    shuffled = noisy[rng.permutation(19)]
    np.testing.assert_allclose(sort_lenslet_centers(shuffled), noisy)


@pytest.mark.parametrize("seed,radius", [(0, 118.7), (1, 95.3), (2, 60.2)])
def test_hough_detection_subpixel(seed, radius):
    rng = np.random.default_rng(seed)
    pitch = 2 * radius + rng.uniform(6, 30)
    origin = np.array([400.0, 400.0]) + rng.uniform(-5, 5, 2)
    truth = hexagonal_offsets(7, pitch) + origin
    image = brightfield(truth, radius, (800, 800), seed=seed)
    detected = detect_lenslet_centers(image, 7)
    assert detected.shape == (7, 2)
    assert np.abs(detected - truth).max() < 1.0
    given = detect_lenslet_centers(image, 7, radius_px=radius * 0.97)
    assert np.abs(given - truth).max() < 1.0


def test_detects_the_small_system_layout():
    system = load_system("small")
    truth = system.lenslet_centers_px()
    radius = system.lenslet_aperture_mm * 500 / system.pixel_um * 0.9
    detected = detect_lenslet_centers(brightfield(truth, radius, system.sensor_shape, blur=1.5), 7)
    assert np.abs(detected - truth).max() < 1.0


@pytest.mark.parametrize(
    "image,match",
    [
        (np.ones((50, 50)), "constant"),
        (np.ones((2, 50, 50)), "2D"),
        (np.full((50, 50), np.nan), "NaN"),
    ],
)
def test_bad_images(image, match):
    with pytest.raises(ValueError, match=match):
        detect_lenslet_centers(image, 7)


def test_too_few_disks_is_reported():
    image = brightfield([(100.0, 100.0), (100.0, 300.0)], 60, (200, 400))
    with pytest.raises(ValueError, match="expected 7"):
        detect_lenslet_centers(image, 7)
    with pytest.raises(ValueError, match="expected 7"):
        detect_lenslet_centers(image, 7, radius_px=60)
    assert math.isfinite(detect_lenslet_centers(image, 2).sum())
