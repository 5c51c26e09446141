"""Lenslet centres from the data: the hexagonal-lattice fit against synthetic MLAs with known
centres, the view-order check, per-view gains, the calibration folder and ``python -m fgat
calibrate``."""

import functools
import re

import numpy as np
import pytest
import torch
from scipy import ndimage

from fgat._core.conventions import DEPTH_AXES, VIEW_ORDER, orient_volume
from fgat.app.calibration_report import write_calibration
from fgat.app.cli import main
from fgat.instrument.calibration import (
    Calibration,
    gains_from_flat,
    gains_from_image,
    read_calibration,
    save_calibration,
)
from fgat.instrument.camera import CameraModel
from fgat.instrument.centres import check_view_order, read_centers, write_centers
from fgat.instrument.lattice import HexLattice, fit_hexagonal_lattice
from fgat.io.images import write_tiff
from fgat.optics.lenslets import sort_lenslet_centers
from fgat.optics.operator import FLFMOperator
from fgat.sim.phantoms import noisy_measurement
from fgat.sim.simulation import SimulationConfig, simulate
from tests.conftest import SHARED_DATA


def brightfield(shape, centers, radius, seed):
    """Bright aperture disks on a dark background, blurred by 1 px, with noise."""
    rows, cols = np.indices(shape)
    image = sum(((rows - r) ** 2 + (cols - c) ** 2 <= radius**2).astype(float) for r, c in centers)
    noise = np.random.default_rng(seed).standard_normal(shape)
    return ndimage.gaussian_filter(image, 1.0) + 0.02 * noise


def fluorescence(shape, centers, radius, seed):
    """The same bead field behind every lenslet (each view of a thin sample), inside a dim
    field-of-view disk."""
    rng = np.random.default_rng(seed)
    beads = rng.uniform(-0.8 * radius, 0.8 * radius, (15, 2))
    rows, cols = np.indices(shape)
    image = np.zeros(shape)
    for r, c in centers:
        for b_r, b_c in beads:
            image += np.exp(-((rows - r - b_r) ** 2 + (cols - c - b_c) ** 2) / (2 * 1.5**2))
        image += 0.05 * ((rows - r) ** 2 + (cols - c) ** 2 <= radius**2)
    return image + 0.01 * rng.standard_normal(shape)


@pytest.mark.parametrize("kind", ["brightfield", "fluorescence"])
@pytest.mark.parametrize(
    ("n_lenslets", "pitch", "rotation"), [(7, 40.0, 0.4), (19, 30.0, -3.0), (37, 24.0, 12.0)]
)
def test_lattice_fit_recovers_centres_off_a_rotated_lattice(kind, n_lenslets, pitch, rotation):
    truth = HexLattice((150.3, 161.7), pitch, rotation)
    jitter = np.random.default_rng(n_lenslets).uniform(-1.5, 1.5, (n_lenslets, 2))
    centers = truth.centers(n_lenslets) + jitter  # a real MLA is off its lattice by pixels
    make = brightfield if kind == "brightfield" else fluorescence
    fit = fit_hexagonal_lattice(make((320, 330), centers, 0.42 * pitch, n_lenslets), n_lenslets)
    error = fit.centers - centers
    if kind == "fluorescence":  # a common offset of all views is a lateral shift of the scene
        error -= error.mean(axis=0)
    assert np.linalg.norm(error, axis=1).max() < 0.3  # px
    assert fit.lattice.pitch == pytest.approx(pitch, rel=0.01)
    assert fit.lattice.rotation_deg == pytest.approx(rotation, abs=1.0)
    check_view_order(fit.centers, "fit")  # in fgat's view order
    np.testing.assert_array_equal(
        sort_lenslet_centers(truth.centers(n_lenslets)), truth.centers(n_lenslets)
    )
    assert not fit.missing.any()


def test_a_missing_lenslet_is_flagged_and_keeps_its_lattice_point():
    truth = HexLattice((150.3, 161.7), 30.0, 5.0)
    centers = truth.centers(19) + np.random.default_rng(3).uniform(-1.0, 1.0, (19, 2))
    fit = fit_hexagonal_lattice(brightfield((320, 330), np.delete(centers, 4, axis=0), 12.6, 3), 19)
    assert np.flatnonzero(fit.missing).tolist() == [4]
    np.testing.assert_allclose(fit.centers[4], fit.lattice.centers(19)[4])
    assert np.linalg.norm(np.delete(fit.centers - centers, 4, axis=0), axis=1).max() < 0.3


def test_centres_in_another_order_are_refused_naming_the_view(tmp_path):
    centers = HexLattice((100.0, 100.0), 30.0, 0.0).centers(7)
    check_view_order(centers, "ok")  # fgat's order passes
    write_centers(tmp_path / "swapped.csv", centers[[0, 2, 1, 3, 4, 5, 6]])
    with pytest.raises(
        ValueError,
        match=r"swapped.csv: lenslet centres are not in fgat's view order: line 2 .* is view 2",
    ):
        read_centers(tmp_path / "swapped.csv")


def test_calibrate_command_writes_centres_lattice_and_overlay(tmp_path, capsys):
    truth = HexLattice((128.0, 128.0), 60.0, 2.0)
    centers = truth.centers(7) + np.random.default_rng(0).uniform(-1.0, 1.0, (7, 2))
    frames = np.stack([brightfield((256, 256), centers, 25.0, seed) for seed in range(3)])
    write_tiff(tmp_path / "frames.tif", frames.astype(np.float32), axes="TYX")
    out = tmp_path / "calib"
    command = ["calibrate", "--image", str(tmp_path / "frames.tif"), "--n-lenslets", "7"]
    assert main([*command, "--out", str(out)]) == 0
    printed = re.search(r"7 lenslets: pitch ([0-9.]+) px", capsys.readouterr().out)
    assert float(printed.group(1)) == pytest.approx(60.0, rel=0.01)
    found = read_centers(out / "centers.csv")  # in view order, or read_centers refuses it
    assert np.linalg.norm(found - centers, axis=1).max() < 0.3
    assert {"lattice.yaml", "overlay.png"} <= {path.name for path in out.iterdir()}
    assert main([*command, "--out", str(out)]) == 2  # nothing is overwritten without --overwrite
    assert "centers.csv: the file exists" in capsys.readouterr().err


@pytest.mark.skipif(not (SHARED_DATA / "reticular1").is_dir(), reason="needs ../shared/data")
def test_centres_of_a_foreign_fluorescence_image_match_its_own_centre_file():
    """The 3DGAT reticular image (another group's simulation): the centres found on the image
    itself agree with its MLcenter_idxes.mat (integers, 1-based, another view order) up to the
    scene gauge (a common shift and a parallax-like scaling, see remove_scene_gauge)."""
    import torch

    from fgat.io.images import read_mat, read_tiff
    from fgat.recon.estimation import remove_scene_gauge

    reference = sort_lenslet_centers(
        read_mat(SHARED_DATA / "reticular1" / "MLcenter_idxes.mat") - 1.0
    )
    image = read_tiff(SHARED_DATA / "reticular1" / "LFimage.tif", ndim=2)
    fit = fit_hexagonal_lattice(image, 7)
    difference = torch.from_numpy(fit.centers - reference)
    residual = remove_scene_gauge(difference, torch.from_numpy(reference - reference[:1]))
    assert float(residual.abs().max()) < 1.0  # px (the file holds whole pixels)


GAINS = np.array([1.0, 0.93, 0.81, 0.88, 0.7, 0.97, 0.76])


def test_gains_from_a_white_light_mla_image():
    truth = HexLattice((128.0, 128.0), 60.0, 2.0)
    centers = truth.centers(7) + np.random.default_rng(0).uniform(-1.0, 1.0, (7, 2))
    rows, cols = np.indices((256, 256))
    light = sum(
        gain * ((rows - r) ** 2 + (cols - c) ** 2 <= 27.0**2)
        for gain, (r, c) in zip(GAINS, centers)
    )
    rng = np.random.default_rng(1)
    flat = 100.0 + 2000.0 * ndimage.gaussian_filter(light, 1.5)
    flat = rng.poisson(flat) + 2.5 * rng.standard_normal(flat.shape)
    gains = gains_from_flat(flat, centers, 0.4 * 60.0)  # offset from the flat's dark corners
    assert np.abs(gains / GAINS - 1).max() < 0.01  # measured: 0.1 %
    camera = CameraModel(100.0, 10.0)
    assert np.abs(gains_from_flat(flat, centers, 24.0, camera) / GAINS - 1).max() < 0.01
    with pytest.raises(ValueError, match=r"view 0: no valid pixel within 5 px"):
        gains_from_flat(flat, [[-20.0, -20.0]], 5.0, camera)


@functools.cache
def small_simulation():
    """A bead phantom inside every view's field and its PSF stack (small system, no noise)."""
    config = SimulationConfig(
        system="small",
        depths_um="-10:10:5",
        view_size=64,
        photons=None,
        phantom={"kind": "beads", "n_beads": 20, "sigma": 1.0, "margin": [0, 16, 16]},
    )
    return simulate(config)


def gained_image(seed: int):
    """The small simulation's sensor image with views scaled by ``GAINS``, camera noise and a
    100-count background: ``(simulation, image)``."""
    sim = small_simulation()
    psf = torch.from_numpy(sim.psf).double()
    views = FLFMOperator(psf, sim.truth.shape).forward(torch.from_numpy(sim.truth).double())
    views = views.clamp(min=0) * torch.from_numpy(GAINS)[:, None, None]
    clean = FLFMOperator.sensor(views, sim.centers, sim.system.sensor_shape).numpy()
    return sim, noisy_measurement(
        clean, photons=1000.0, background=100.0, read_noise=2.5, seed=seed
    )


def test_gains_from_the_fluorescence_image_itself():
    sim, image = gained_image(seed=1)
    energy = sim.psf.sum(axis=(2, 3)).mean(axis=1)  # (V,) share of the light per view
    gains = gains_from_image(image, sim.centers, 64, energy)
    assert np.abs(gains / GAINS - 1).max() < 0.03  # measured: 0.8 %
    with pytest.raises(ValueError, match=r"psf_energy must be 7 positive values"):
        gains_from_image(image, sim.centers, 64, energy[:6])
    with pytest.raises(ValueError, match=r"view 1: a 120 x 120 window .* does not fit"):
        gains_from_image(image, sim.centers, 120)


def fitted_calibration(tmp_path, **options):
    """A fit of a 7-lens brightfield image written as a calibration folder."""
    truth = HexLattice((128.0, 128.0), 60.0, 2.0)
    image = brightfield((256, 256), truth.centers(7), 25.0, 0)
    fit = fit_hexagonal_lattice(image, 7)
    paths = write_calibration(fit, tmp_path, image, "bf.tif", **options)
    return fit, paths


def test_calibration_folder_round_trip(tmp_path):
    hot = np.zeros((256, 256), dtype=bool)
    hot[[5, 200], [7, 31]] = True
    flat = np.random.default_rng(0).uniform(0.9, 1.1, (256, 256)).astype(np.float32)
    camera = CameraModel(99.5, 2.5, hot, flat)
    fit, paths = fitted_calibration(
        tmp_path,
        gains=GAINS,
        gains_source="flat.tif",
        camera=camera,
        camera_source="dark.tif",
        depth_axis="down",
    )
    assert set(paths) == {
        "centers.csv",
        "lattice.yaml",
        "overlay.png",
        "calibration.yaml",
        "hot_pixels.ome.tif",
        "flat.ome.tif",
    }
    assert all(path.is_file() for path in paths.values())
    calibration = read_calibration(tmp_path)
    np.testing.assert_allclose(calibration.centers, fit.centers, atol=1e-6)  # CSV: 6 decimals
    assert calibration.lattice == fit.lattice
    np.testing.assert_array_equal(calibration.residuals, fit.residuals)
    np.testing.assert_array_equal(calibration.gains, GAINS)
    assert (calibration.camera.offset, calibration.camera.read_noise) == (99.5, 2.5)
    np.testing.assert_array_equal(calibration.camera.hot_pixels, hot)
    np.testing.assert_array_equal(calibration.camera.flat, flat)
    assert calibration.depth_axis == "down"
    assert calibration.view_order == VIEW_ORDER
    assert (calibration.source, calibration.gains_source, calibration.camera_source) == (
        "bf.tif",
        "flat.tif",
        "dark.tif",
    )
    # a calibration without a fit, gains or camera (centres from elsewhere)
    bare = Calibration(centers=fit.lattice.centers(7), source="centers.csv")
    (tmp_path / "bare").mkdir()
    save_calibration(bare, tmp_path / "bare")
    again = read_calibration(tmp_path / "bare")
    assert again.lattice is None and again.residuals is None and again.gains is None
    assert again.camera is None and again.depth_axis == "up" and again.source == "centers.csv"


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda r: r.pop("version"), r"calibration.yaml: missing field\(s\) \['version'\]"),
        (lambda r: r.update(version=2), r"calibration.yaml: version: expected 1, got 2"),
        (lambda r: r.update(colour="red"), r"calibration.yaml: unknown field\(s\) \['colour'\]"),
        (
            lambda r: r.update(gains=[1.0] * 6),
            r"calibration.yaml: gains: 6 values, but centers.csv has 7 lenslet centres",
        ),
        (
            lambda r: r.update(gains=[1.0, "a"] + [1.0] * 5),
            r"calibration.yaml: gains: expected a list of 7 numbers",
        ),
        (
            lambda r: r.update(residuals_px=[0.1] * 8),
            r"calibration.yaml: residuals_px: 8 values, but centers.csv has 7",
        ),
        (
            lambda r: r.update(depth_axis="sideways"),
            r"calibration.yaml: depth_axis: expected one of \['up', 'down'\], got 'sideways'",
        ),
        (lambda r: r.update(n_views=19), r"calibration.yaml: n_views is 19, but centers.csv has 7"),
        (
            lambda r: r.update(centers="nowhere.csv"),
            r"calibration.yaml: centers: .*nowhere.csv does not exist",
        ),
        (
            lambda r: r["lattice"].update(pitch_px=-3),
            r"calibration.yaml: lattice.pitch_px must be a finite number > 0, got -3",
        ),
        (
            lambda r: r["camera"].update(read_noise=-1),
            r"calibration.yaml: camera.read_noise must be a finite number >= 0, got -1",
        ),
        (
            lambda r: r["camera"].update(hot_pixels="gone.ome.tif"),
            r"calibration.yaml: camera.hot_pixels: .*gone.ome.tif does not exist",
        ),
    ],
)
def test_bad_calibration_files_are_refused_naming_file_and_field(tmp_path, edit, message):
    import yaml

    hot = np.zeros((256, 256), dtype=bool)
    hot[5, 7] = True
    lattice = HexLattice((128.0, 128.0), 60.0, 2.0)
    calibration = Calibration(
        lattice.centers(7), lattice, np.zeros(7), GAINS, CameraModel(100.0, 2.5, hot)
    )
    save_calibration(calibration, tmp_path)
    path = tmp_path / "calibration.yaml"
    record = yaml.safe_load(path.read_text())
    edit(record)
    path.write_text(yaml.safe_dump(record))
    with pytest.raises((ValueError, FileNotFoundError), match=message):
        read_calibration(tmp_path)


def test_missing_calibration_files_are_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="calibration folder .*nothing does not exist"):
        read_calibration(tmp_path / "nothing")
    with pytest.raises(FileNotFoundError, match=r"calibration.yaml does not exist"):
        read_calibration(tmp_path)
    (tmp_path / "calibration.yaml").write_text("version: [1,\n")
    with pytest.raises(ValueError, match=r"calibration.yaml: invalid YAML at line 2"):
        read_calibration(tmp_path)


def test_orient_volume_flips_depth_only_for_down():
    volume = np.arange(24.0).reshape(2, 3, 2, 2)  # (T, Z, Y, X)
    assert orient_volume(volume, "up") is volume
    np.testing.assert_array_equal(orient_volume(volume, "down"), volume[:, ::-1])
    tensor = torch.from_numpy(volume)
    np.testing.assert_array_equal(orient_volume(tensor, "down").numpy(), volume[:, ::-1])
    with pytest.raises(ValueError, match="depth_axis must be one of"):
        orient_volume(volume, "Down")
    with pytest.raises(ValueError, match=r"expected a volume \(\.\.\., Z, Y, X\)"):
        orient_volume(np.zeros((3, 3)), "down")
    assert "nearest the objective" in DEPTH_AXES["up"]


@pytest.mark.parametrize(("header", "swap"), [("x,y", True), ("Y, X", False), ("col,row", True)])
def test_centres_with_x_y_headers(tmp_path, header, swap):
    centers = HexLattice((100.0, 120.0), 30.0, 3.0).centers(7)
    written = centers[:, ::-1] if swap else centers
    lines = [header] + [f"{a},{b}" for a, b in written]
    (tmp_path / "c.csv").write_text("\n".join(lines) + "\n")
    np.testing.assert_allclose(read_centers(tmp_path / "c.csv"), centers)


def test_calibrate_command_with_dark_and_flat(tmp_path, capsys):
    truth = HexLattice((128.0, 128.0), 60.0, 2.0)
    centers = truth.centers(7)
    rng = np.random.default_rng(0)
    frames = 100.0 + 1000.0 * brightfield((256, 256), centers, 25.0, 1)
    dark = 100.0 + 2.5 * rng.standard_normal((4, 256, 256))
    dark[:, [10, 200], [20, 50]] += 300.0
    rows, cols = np.indices((256, 256))
    light = sum(
        g * ((rows - r) ** 2 + (cols - c) ** 2 <= 27**2) for g, (r, c) in zip(GAINS, centers)
    )
    sensitivity = 1.0 + 0.05 * np.sin(cols / 9.0) * np.cos(rows / 13.0)  # seen by every frame
    flat = 100.0 + 2000.0 * light * sensitivity + 2.5 * rng.standard_normal((256, 256))
    pixel_flat = 100.0 + 3000.0 * sensitivity * np.ones((8, 1, 1))
    pixel_flat += 2.5 * rng.standard_normal(pixel_flat.shape)
    arrays = (("image", frames), ("dark", dark), ("flat", flat), ("pixel_flat", pixel_flat))
    for name, array in arrays:
        write_tiff(tmp_path / f"{name}.tif", array.astype(np.float32))
    out = tmp_path / "calib"
    command = ["calibrate", "--image", str(tmp_path / "image.tif"), "--n-lenslets", "7"]
    files = ["--dark", str(tmp_path / "dark.tif"), "--flat", str(tmp_path / "flat.tif")]
    files += ["--pixel-flat", str(tmp_path / "pixel_flat.tif")]
    assert main([*command, *files, "--depth-axis", "down", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "gains: min 0.700 (view 4), max 1 (view 0)" in printed
    assert re.search(r"camera: offset 100\.0\d counts, read noise 2\.[45]\d counts", printed)
    assert "hot pixels: 2 -> " in printed and "fluorescence image" not in printed
    expected = {"centers.csv", "lattice.yaml", "overlay.png", "calibration.yaml"}
    assert {path.name for path in out.iterdir()} == expected | {
        "hot_pixels.ome.tif",
        "flat.ome.tif",
    }
    calibration = read_calibration(out)
    reference = sensitivity / sensitivity.mean()  # the pixel response, 8 frames of noise 2.5/3000
    good = ~calibration.camera.hot_pixels  # (the dark frames' hot pixels are masked)
    assert np.abs(calibration.camera.flat - reference)[good].max() < 3e-3
    assert np.abs(calibration.gains / GAINS - 1).max() < 0.01
    assert np.flatnonzero(calibration.camera.hot_pixels).tolist() == [10 * 256 + 20, 200 * 256 + 50]
    assert calibration.depth_axis == "down"
    assert calibration.camera_source.startswith("dark frame(s)")
    assert main([*command, "--out", str(out)]) == 2  # nothing replaced without --overwrite
    assert main([*command, "--out", str(out), "--overwrite"]) == 0  # the image's own camera
    printed = capsys.readouterr().out
    assert "gains: none" in printed and "hot pixels: 0" in printed
    assert not (out / "hot_pixels.ome.tif").exists()  # no stale map of the earlier run
    calibration = read_calibration(out)
    assert calibration.camera.flat is None
    assert calibration.gains is None and calibration.depth_axis == "up"
    assert calibration.camera_source.startswith("estimated from the image")
    assert abs(calibration.camera.offset - 100.0) < 1.0


def test_calibrate_command_estimates_gains_from_the_image_with_a_system(tmp_path, capsys):
    sim, image = gained_image(seed=2)
    write_tiff(tmp_path / "image.tif", image)
    out = tmp_path / "calib"
    command = ["calibrate", "--image", str(tmp_path / "image.tif"), "--system", "small"]
    assert main([*command, "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "assumes the sample inside every view's field" in printed
    assert "fluorescence image: the centres are fixed up to where the sample is" in printed
    calibration = read_calibration(out)
    # The flux a fluorescence image puts in each view bounds this (0.9 %, 3.2 % and 2.5 % on
    # seeds 1-3; 1.2-2.1 % with the PSF energies at the true centres), not the lattice.
    assert np.abs(calibration.gains / GAINS - 1).max() < 0.04
    assert calibration.gains_source.startswith("estimated from the image")
