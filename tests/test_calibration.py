"""Lenslet centres from the data: the hexagonal-lattice fit against synthetic MLAs with known
centres, the view-order check, and ``python -m fgat calibrate``."""

import re

import numpy as np
import pytest
from conftest import SHARED_DATA
from scipy import ndimage

from fgat.cli import main
from fgat.io import write_tiff
from fgat.optics.calibration import HexLattice, check_view_order, fit_hexagonal_lattice
from fgat.optics.lenslets import sort_lenslet_centers
from fgat.simulation import read_centers, write_centers


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

    from fgat.io import read_mat, read_tiff
    from fgat.optics.estimation import remove_scene_gauge

    reference = sort_lenslet_centers(
        read_mat(SHARED_DATA / "reticular1" / "MLcenter_idxes.mat") - 1.0
    )
    image = read_tiff(SHARED_DATA / "reticular1" / "LFimage.tif", ndim=2)
    fit = fit_hexagonal_lattice(image, 7)
    difference = torch.from_numpy(fit.centers - reference)
    residual = remove_scene_gauge(difference, torch.from_numpy(reference - reference[:1]))
    assert float(residual.abs().max()) < 1.0  # px (the file holds whole pixels)
