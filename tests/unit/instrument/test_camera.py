"""The camera model: offset, read noise and hot pixels from dark frames and from an FLFM image
alone, flat-fielding, and the shape checks."""

import functools

import numpy as np
import pytest

from fgat.instrument.camera import (
    MIN_FLAT,
    CameraModel,
    camera_from_dark,
    camera_from_image,
    flat_field,
    read_camera,
    write_camera,
)
from fgat.sim.simulation import SimulationConfig, simulate

SHAPE = (256, 256)


def dark_frames(frames, seed=0, offset=100.0, read_noise=2.5, n_hot=20):
    """Dark frames ``(T, H, W)`` with a known offset and read noise, and ``n_hot`` hot pixels
    40 to 400 counts above the offset (at least 16 read-noise sigmas); returns the frames and
    the hot pixels' flat indices."""
    rng = np.random.default_rng(seed)
    dark = offset + read_noise * rng.standard_normal((frames, *SHAPE))
    hot = rng.choice(SHAPE[0] * SHAPE[1], n_hot, replace=False)
    dark.reshape(frames, -1)[:, hot] += rng.uniform(40.0, 400.0, n_hot)
    return dark, hot


@pytest.mark.parametrize("frames", [1, 10])
def test_dark_frames_give_offset_read_noise_and_every_hot_pixel(frames):
    dark, hot = dark_frames(frames)
    camera = camera_from_dark(dark)
    assert camera.offset == pytest.approx(100.0, rel=0.002)  # measured: within 0.003 counts
    assert camera.read_noise == pytest.approx(2.5, rel=0.03)  # measured: within 0.2 %
    assert sorted(np.flatnonzero(camera.hot_pixels)) == sorted(hot)  # all, no false positive
    assert camera.flat is None


def test_noisy_pixels_of_a_dark_sequence_are_defective_too():
    dark, hot = dark_frames(10, seed=1)
    noisy = np.array([1000, 2000])  # normal mean, temporal std 10x the read noise
    rng = np.random.default_rng(2)
    dark.reshape(10, -1)[:, noisy] = 100.0 + 25.0 * rng.choice([-1.0, 1.0], (10, 2))
    camera = camera_from_dark(dark)
    assert sorted(np.flatnonzero(camera.hot_pixels)) == sorted([*hot, *noisy])


def test_a_clean_dark_frame_has_no_hot_pixels():
    camera = camera_from_dark(dark_frames(1, n_hot=0)[0])
    assert camera.hot_pixels is None


@functools.cache
def simulated_sensor(seed):
    """A simulated FLFM image (small system: 7 views of 64 px on 256 x 256, beads, 1000
    photons at the peak, background 100 counts with shot noise, read noise 2.5 counts)."""
    config = SimulationConfig(
        system="small",
        depths_um="-10:10:5",
        view_size=64,
        photons=1000.0,
        background=100.0,
        read_noise=2.5,
        seed=seed,
        phantom={"kind": "beads", "n_beads": 30, "sigma": 1.0},
    )
    return simulate(config).sensor.astype(np.float64)


def flfm_image(seed, n_hot=20):
    """:func:`simulated_sensor` with ``n_hot`` hot pixels, 200 to 1000 counts, on pixels
    without sample light; returns the image and the hot pixels' flat indices."""
    image = simulated_sensor(seed).copy()
    rng = np.random.default_rng(seed + 100)
    dark_pixels = np.flatnonzero(image < 100.0 + 3 * 10.3)
    hot = rng.choice(dark_pixels, n_hot, replace=False)
    image.reshape(-1)[hot] += rng.uniform(200.0, 1000.0, n_hot)
    return image, hot


@pytest.mark.parametrize("seed", [0, 1])
def test_an_flfm_image_alone_gives_offset_noise_and_hot_pixels(seed):
    image, hot = flfm_image(seed)
    camera = camera_from_image(image)
    assert abs(camera.offset - 100.0) < 1.0  # measured: 0.03-0.1 counts
    # a dark pixel's noise: the shot noise of the simulated background and the read noise
    assert camera.read_noise == pytest.approx(np.sqrt(100.0 + 2.5**2), rel=0.15)  # meas. < 2 %
    assert sorted(np.flatnonzero(camera.hot_pixels)) == sorted(hot)  # beads are not spikes


def test_frames_of_an_flfm_image_give_the_noise_of_one_frame():
    image, _ = flfm_image(0, n_hot=0)
    noise = np.random.default_rng(5).standard_normal((4, *image.shape)) * 10.3
    camera = camera_from_image(image[None] + noise)  # the mean's noise would be ~sqrt(5/4) x
    assert camera.read_noise == pytest.approx(np.hypot(10.3, 10.3), rel=0.1)
    assert abs(camera.offset - 100.0) < 1.0


def test_correct_and_valid():
    hot = np.zeros((4, 5), dtype=bool)
    hot[1, 2] = True
    flat = np.full((4, 5), 2.0)
    flat[3, 4] = 0.0  # dead
    camera = CameraModel(10.0, 1.0, hot, flat)
    frames = np.full((3, 4, 5), 30.0)
    corrected = camera.correct(frames)
    assert corrected.shape == (3, 4, 5)
    assert corrected[0, 0, 0] == 10.0 and corrected[2, 3, 4] == 20.0  # dead: not divided
    valid = camera.valid(frames.shape)
    assert valid.sum() == 18 and valid[1, 2] == 0 and valid[3, 4] == 0
    with pytest.raises(ValueError, match=r"4 x 5 sensor .* the image is 4 x 6"):
        camera.correct(np.zeros((4, 6)))
    with pytest.raises(ValueError, match=r"4 x 5 sensor .* the image is 5 x 5"):
        camera.valid((5, 5))
    plain = CameraModel(10.0, 1.0)
    np.testing.assert_array_equal(plain.correct(np.full((2, 2), 12.0)), 2.0)
    np.testing.assert_array_equal(plain.valid((2, 3)), np.ones((2, 3)))
    with pytest.raises(ValueError, match="read_noise must be finite and >= 0"):
        CameraModel(0.0, -1.0)


def test_flat_field_recovers_the_pixel_sensitivity():
    rng = np.random.default_rng(3)
    sensitivity = rng.uniform(0.9, 1.1, SHAPE)
    sensitivity /= sensitivity.mean()
    frames = 100.0 + 5000.0 * sensitivity + 0.5 * rng.standard_normal((8, *SHAPE))
    flat = flat_field(frames, dark=100.0)
    assert flat.mean() == pytest.approx(1.0)
    assert np.abs(flat - sensitivity).max() < 1e-3
    camera = CameraModel(100.0, 0.5, flat=flat)
    assert np.abs(camera.correct(frames.mean(axis=0)) - 5000.0).max() < 5.0
    with pytest.raises(ValueError, match="no light above the dark level"):
        flat_field(np.full(SHAPE, 90.0), dark=np.full(SHAPE, 100.0))
    assert MIN_FLAT < 0.5


def test_camera_maps_round_trip(tmp_path):
    hot = np.zeros(SHAPE, dtype=bool)
    hot[3, 4] = hot[100, 7] = True
    flat = np.random.default_rng(0).uniform(0.8, 1.2, SHAPE).astype(np.float32)
    record = write_camera(CameraModel(100.5, 2.25, hot, flat), tmp_path)
    assert record == {
        "offset": 100.5,
        "read_noise": 2.25,
        "hot_pixels": "hot_pixels.ome.tif",
        "hot_pixel_count": 2,
        "flat": "flat.ome.tif",
    }
    camera = read_camera(record, tmp_path, "calibration.yaml")
    assert (camera.offset, camera.read_noise) == (100.5, 2.25)
    np.testing.assert_array_equal(camera.hot_pixels, hot)
    np.testing.assert_array_equal(camera.flat, flat)
    with pytest.raises(ValueError, match=r"calibration.yaml: camera.hot_pixel_count is 3"):
        read_camera({**record, "hot_pixel_count": 3}, tmp_path, "calibration.yaml")
    with pytest.raises(ValueError, match=r"calibration.yaml: camera.offset must be a finite"):
        read_camera({**record, "offset": "high"}, tmp_path, "calibration.yaml")
