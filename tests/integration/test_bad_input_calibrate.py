"""Bad input to ``fgat calibrate``: an image without a lattice, a lenslet count the image cannot
hold, a bright frame given as the dark frame; one clear line (exit code 2) before anything is
written, and the fit's quality on a good image."""

import re
import time

import numpy as np
import pytest
import yaml
from scipy import ndimage, optimize

from fgat.app.cli import main
from fgat.instrument.calibration import low_gain_warning
from fgat.instrument.camera import camera_from_image, dark_frame_warning
from fgat.instrument.lattice import (
    MIN_VIEW_CONTRAST,
    HexLattice,
    fit_hexagonal_lattice,
    lattice_quality,
)
from fgat.io.images import write_tiff
from fgat.optics.lenslets import hexagonal_offsets

PITCH, ROTATION = 60.0, 2.0
TRUTH = HexLattice((128.0, 128.0), PITCH, ROTATION)
JITTER = np.random.default_rng(0).uniform(-1.0, 1.0, (7, 2))  # an MLA a pixel off its lattice


def brightfield(shape, centers, radius=25.0, seed=1):
    """Aperture disks 1000 counts above a 100-count offset, blurred by 1 px, noise 2 counts."""
    rows, cols = np.indices(shape)
    disks = sum(((rows - r) ** 2 + (cols - c) ** 2 <= radius**2).astype(float) for r, c in centers)
    noise = np.random.default_rng(seed).standard_normal(shape)
    return 100.0 + 1000.0 * ndimage.gaussian_filter(disks, 1.0) + 2.0 * noise


def noise_image(model: str, seed: int) -> np.ndarray:
    """A 256 x 256 image of pure noise: Poisson at 2 or 1000 counts, or Gaussian on an offset."""
    rng = np.random.default_rng(seed)
    if model == "poisson-low":
        return rng.poisson(2.0, (256, 256)).astype(np.float32)
    if model == "poisson-high":
        return rng.poisson(1000.0, (256, 256)).astype(np.float32)
    return (500.0 + 20.0 * rng.standard_normal((256, 256))).astype(np.float32)


def run(argv):
    """``fgat.app.cli.main(argv)``'s exit code, also when argparse exits."""
    try:
        return main([str(word) for word in argv])
    except SystemExit as exit:
        return exit.code


def error_line(capsys) -> str:
    """The one error line on stderr (after argparse's usage, for option errors)."""
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip() and not line.startswith(" ")]
    lines = [line for line in lines if not line.startswith("usage:")]
    assert "Traceback" not in err and len(lines) == 1, err
    assert lines[0].startswith("fgat calibrate: error: ")
    return lines[0]


@pytest.mark.parametrize("model", ["poisson-low", "poisson-high", "gaussian"])
@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("count", [["--n-lenslets", "7"], ["--system", "small"]])
def test_an_image_of_noise_is_refused_naming_views_found(model, seed, count, tmp_path, capsys):
    write_tiff(tmp_path / "noise.tif", noise_image(model, seed))
    out = tmp_path / "calib" / "run"
    assert run(["calibrate", "--image", tmp_path / "noise.tif", *count, "--out", out]) == 2
    line = error_line(capsys)
    assert f"--image {tmp_path / 'noise.tif'}: " in line
    found = re.search(r"(\d+) of (?:the )?7 expected views", line)
    assert found and int(found.group(1)) < 6  # at least 6 of 7 (80 %) would pass
    assert not (tmp_path / "calib").exists()  # no folder left behind


@pytest.mark.parametrize("seed", range(5))
def test_noise_has_no_view_of_lattice_contrast(seed):
    """The contrast of the views of a lattice fitted to noise stays below the threshold in the
    median, whatever the noise's distribution."""
    for model in ("poisson-low", "poisson-high", "gaussian"):
        image = noise_image(model, seed)
        fit = fit_hexagonal_lattice(image, 7)
        quality = lattice_quality(image, fit, camera_from_image(image).hot_pixels)
        assert quality.median_contrast < MIN_VIEW_CONTRAST - 1.0
        assert quality.problem() is not None


def test_a_37_lens_system_on_a_7_lens_image_is_refused(tmp_path, capsys):
    centers = HexLattice((128.0, 128.0), 50.0, 0.0).centers(7)  # small37's pitch
    write_tiff(tmp_path / "seven.tif", brightfield((256, 256), centers, 21.0).astype(np.float32))
    command = ["calibrate", "--image", tmp_path / "seven.tif", "--out", tmp_path / "out"]
    assert run([*command, "--system", "small37"]) == 2
    assert "no lattice of 37 lenslets: 7 of 37 expected views found (share 0.19" in error_line(
        capsys
    )
    # 37 lenslets 77 px apart (the small system's 7-lens image) cannot lie on a 256 x 256 image
    centers = HexLattice((128.0, 128.0), 77.0, 0.0).centers(7)
    write_tiff(tmp_path / "wide.tif", brightfield((256, 256), centers, 32.0).astype(np.float32))
    command[2] = tmp_path / "wide.tif"
    assert run([*command, "--n-lenslets", "37"]) == 2
    found = re.search(r"at most (\d+) of the 37 expected views can lie on it", error_line(capsys))
    assert found and int(found.group(1)) < 0.8 * 37
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    "count,message",
    [
        ("1e6", "--n-lenslets 1000000: 1000000 lenslets of at least 5 px pitch need 2.17e+07 px"),
        ("3000", "3000 lenslets 60.0 px apart (the image's lattice pitch) do not fit on the"),
        ("nan", "argument --n-lenslets: must be an integer >= 1, got 'nan'"),
        ("-3", "argument --n-lenslets: must be an integer >= 1, got '-3'"),
        ("2.5", "argument --n-lenslets: must be an integer >= 1, got '2.5'"),
        ("many", "argument --n-lenslets: must be an integer >= 1, got 'many'"),
    ],
)
def test_lenslet_counts_the_image_cannot_hold_are_refused_fast(count, message, tmp_path, capsys):
    write_tiff(tmp_path / "image.tif", brightfield((256, 256), TRUTH.centers(7)))
    start = time.perf_counter()
    argv = ["calibrate", "--image", tmp_path / "image.tif", "--n-lenslets", count]
    assert run([*argv, "--out", tmp_path / "out"]) == 2
    assert time.perf_counter() - start < 2.0
    assert message in error_line(capsys)
    assert not (tmp_path / "out").exists()


def test_the_count_a_sensor_holds_is_its_area_over_a_hexagonal_cell(tmp_path, capsys):
    # cells of sqrt(3)/2 * 5^2 = 21.65 px: 65536 px hold 3026 lenslets, 3027 are refused
    write_tiff(tmp_path / "image.tif", brightfield((256, 256), TRUTH.centers(7)))
    argv = ["calibrate", "--image", tmp_path / "image.tif", "--out", tmp_path / "out"]
    assert run([*argv, "--n-lenslets", "3027"]) == 2
    assert "at most 3026 lenslets fit" in error_line(capsys)
    assert int(65536 // (np.sqrt(3) / 2 * 25)) == 3026


@pytest.fixture
def bright_field_files(tmp_path):
    """A 7-lens brightfield image (offset 100, noise 2) and dark frames: a right one, one 50
    counts too high, the image itself and a uniformly lit frame."""
    image = brightfield((256, 256), TRUTH.centers(7))
    rng = np.random.default_rng(2)
    darks = {
        "dark": 100.0 + 2.0 * rng.standard_normal((4, 256, 256)),
        "high": 150.0 + 2.0 * rng.standard_normal((4, 256, 256)),
        "bright": image,
        "lit": 3000.0 + 2.0 * rng.standard_normal((256, 256)),
    }
    for name, array in {"image": image, **darks}.items():
        write_tiff(tmp_path / f"{name}.tif", array.astype(np.float32))
    return tmp_path


def calibrate_with_dark(folder, dark):
    return run(
        [
            "calibrate",
            "--image",
            folder / "image.tif",
            "--n-lenslets",
            "7",
            "--dark",
            folder / f"{dark}.tif",
            "--out",
            folder / f"out_{dark}",
        ]
    )


def test_a_dark_frame_of_the_camera_passes_without_a_warning(bright_field_files, capsys):
    assert calibrate_with_dark(bright_field_files, "dark") == 0
    assert "warning" not in capsys.readouterr().err


def test_a_bright_frame_given_as_dark_is_warned_about(bright_field_files, capsys):
    folder = bright_field_files
    assert calibrate_with_dark(folder, "bright") == 0
    captured = capsys.readouterr()
    hot = int(re.search(r"hot pixels: (\d+)", captured.out).group(1))
    disks = 7 * np.pi * 25.0**2 / 256**2  # the share of the sensor under the disks
    assert hot > 0.01 * 256**2 and abs(hot / 256**2 - disks) < 0.05
    assert f"--dark {folder / 'bright.tif'}: {hot} hot pixels, {hot / 256**2:.1%}" in captured.err


def test_a_dark_frame_above_the_image_background_is_warned_about(bright_field_files, capsys):
    assert calibrate_with_dark(bright_field_files, "high") == 0
    err = capsys.readouterr().err
    levels = re.search(
        r"its level ([\d.]+) counts lies ([\d.]+) counts above the image's own background "
        r"([\d.]+) counts",
        err,
    )
    assert levels, err
    dark, excess, background = (float(v) for v in levels.groups())
    assert (dark, excess, background) == pytest.approx((150.0, 50.0, 100.0), abs=0.5)


def test_a_dark_frame_above_the_whole_image_is_refused(bright_field_files, capsys):
    assert calibrate_with_dark(bright_field_files, "lit") == 2
    line = error_line(capsys)
    assert "--dark" in line and "its level 3000 counts lies above 100.0% of the image's" in line
    assert not (bright_field_files / "out_lit").exists()


def test_dark_frame_warning_is_none_for_a_dark_frame_of_the_camera():
    from fgat.instrument.camera import camera_from_dark

    rng = np.random.default_rng(3)
    image = brightfield((128, 128), HexLattice((64.0, 64.0), 30.0, 0.0).centers(7), 12.0)
    dark = camera_from_dark(100.0 + 2.0 * rng.standard_normal((3, 128, 128)))
    assert dark_frame_warning(dark, image) is None


def test_a_failed_write_leaves_no_folder(tmp_path, capsys, monkeypatch):
    import fgat.viz.optics

    def fail(*args, **kwargs):
        raise ValueError("disk full")

    monkeypatch.setattr(fgat.viz.optics, "plot_calibration_overlay", fail)
    write_tiff(tmp_path / "image.tif", brightfield((256, 256), TRUTH.centers(7)))
    out = tmp_path / "new" / "calib"
    argv = ["calibrate", "--image", tmp_path / "image.tif", "--n-lenslets", "7", "--out", out]
    assert run(argv) == 2
    assert "disk full" in error_line(capsys)
    assert not (tmp_path / "new").exists()


def best_lattice_rms(centers: np.ndarray) -> float:
    """RMS distance (px) of ``centers`` from the hexagonal lattice nearest them, by nonlinear
    least squares over centre, pitch and rotation (independent of fgat's linear fit)."""
    unit = hexagonal_offsets(len(centers), 1.0)

    def residuals(p):
        c, s = np.cos(np.radians(p[3])), np.sin(np.radians(p[3]))
        rows = p[0] + p[2] * (c * unit[:, 0] - s * unit[:, 1])
        cols = p[1] + p[2] * (s * unit[:, 0] + c * unit[:, 1])
        return np.concatenate([rows - centers[:, 0], cols - centers[:, 1]])

    start = [*centers[0], PITCH, ROTATION]
    solution = optimize.least_squares(residuals, start, xtol=1e-12, ftol=1e-12)
    distance = np.hypot(*solution.fun.reshape(2, -1))
    return float(np.sqrt(np.mean(distance**2)))


def test_the_quality_of_a_good_fit_is_printed_and_recorded(tmp_path, capsys):
    centers = TRUTH.centers(7) + JITTER
    write_tiff(tmp_path / "image.tif", brightfield((256, 256), centers))
    out = tmp_path / "calib"
    argv = ["calibrate", "--image", tmp_path / "image.tif", "--n-lenslets", "7", "--out", out]
    assert run(argv) == 0
    printed = capsys.readouterr().out
    match = re.search(
        r"lattice quality: 7 of 7 views found, residual RMS ([0-9.]+) px \(([0-9.]+) pitch\), "
        r"median view contrast ([0-9.]+) noise std",
        printed,
    )
    assert match
    rms, fraction, contrast = (float(v) for v in match.groups())
    expected = best_lattice_rms(centers)  # the jitter left after the best lattice: ~0.7 px
    assert abs(rms - expected) < 0.15
    assert fraction == pytest.approx(rms / PITCH, abs=1e-3)
    # disks 1000 counts over noise 2 / (2 sqrt(pi)) after the 1-px smoothing: 1770 std
    assert contrast == pytest.approx(1000.0 / (2.0 / (2.0 * np.sqrt(np.pi))), rel=0.1)
    record = yaml.safe_load((out / "lattice.yaml").read_text())["quality"]
    assert (record["views_found"], record["n_views"]) == (7, 7)
    assert record["residual_rms_px"] == pytest.approx(rms, abs=0.01)
    assert min(record["view_contrast"]) > MIN_VIEW_CONTRAST


def test_a_view_without_light_is_named_in_a_gain_warning(tmp_path, capsys):
    """A 19-lens array with one lenslet blocked in the white-light image: 19 views are found on
    the image, the gain of the blocked one is 0 and named."""
    truth = HexLattice((160.0, 165.0), 30.0, 0.0)
    image = brightfield((320, 330), truth.centers(19), 12.6)
    flat = brightfield((320, 330), np.delete(truth.centers(19), 4, axis=0), 12.6, seed=4)
    for name, array in (("image", image), ("flat", flat)):
        write_tiff(tmp_path / f"{name}.tif", array.astype(np.float32))
    argv = ["calibrate", "--image", tmp_path / "image.tif", "--n-lenslets", "19"]
    argv += ["--flat", tmp_path / "flat.tif", "--out", tmp_path / "calib"]
    assert run(argv) == 0
    err = capsys.readouterr().err
    assert "warning: gains: 1 of 19 views get less than 0.05 of the brightest" in err
    assert "(view 4: 0.000)" in err
    assert low_gain_warning(np.ones(19)) is None


def test_dark_background_is_the_level_and_noise_of_the_dark_region():
    """Offset 100 and noise 3 under disks 500 counts bright over a quarter of the image: the
    median and robust std of the dark blocks."""
    from fgat.instrument.camera import dark_background

    rng = np.random.default_rng(5)
    image = 100.0 + 3.0 * rng.standard_normal((256, 256))
    image[:128, :128] += 500.0
    level, noise = dark_background(image)
    assert level == pytest.approx(100.0, abs=0.1) and noise == pytest.approx(3.0, rel=0.05)
    assert dark_background(np.zeros((64, 64))) == (0.0, 0.0)  # noise-free: no noise


def test_a_fit_larger_than_memory_is_refused(tmp_path, capsys, monkeypatch):
    from fgat._core import resources
    from fgat.instrument.lattice import _fit_memory

    # 7 lenslets 60 px apart on 256 x 256: padded by 2 pitches + 2 px, patches of 61 x 61
    reach = int(np.abs(hexagonal_offsets(7, 60.0)).max()) + 2
    expected = 8 * ((256 + 2 * reach) ** 2 + 4 * 256**2 + 2 * 7 * 61**2)
    assert _fit_memory((256, 256), 7, 60.0) == expected
    monkeypatch.setattr(resources, "_host_available", lambda: 1_000_000)
    write_tiff(tmp_path / "image.tif", brightfield((256, 256), TRUTH.centers(7)))
    argv = ["calibrate", "--image", tmp_path / "image.tif", "--n-lenslets", "7"]
    assert run([*argv, "--out", tmp_path / "out"]) == 2
    line = error_line(capsys)
    assert "the fit of 7 lenslets 60.0 px apart need about" in line
    assert "this machine has 1.0 MB available (fewer lenslets)" in line


def test_view_contrast_of_a_point_on_white_noise_matches_the_smoothed_amplitudes():
    """A 100-count point on unit white noise, smoothed by a 1-px Gaussian: peak 100 / (2 pi)
    over the smoothed noise 1 / (2 sqrt(pi)), 56.4; marked hot, the view is dark; a view off
    the image has contrast 0."""
    from fgat.instrument.lattice import view_contrast

    image = np.random.default_rng(0).standard_normal((100, 100))
    image[50, 50] += 100.0
    points = np.array([[50.0, 50.0], [-500.0, 20.0]])
    contrast = view_contrast(image, points, 20.0)
    assert contrast[0] == pytest.approx(100.0 / (2 * np.pi) * 2 * np.sqrt(np.pi), rel=0.05)
    assert contrast[1] == 0.0
    hot = np.zeros((100, 100), dtype=bool)
    hot[50, 50] = True
    assert view_contrast(image, points, 20.0, hot)[0] < MIN_VIEW_CONTRAST
