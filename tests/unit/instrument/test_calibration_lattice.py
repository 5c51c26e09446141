"""The calibration against the system it claims: the pitch and rotation check of ``python -m
fgat calibrate``, per-view gains from the measured lattice when the system's nominal one is off,
and the lattice layouts of the PSF and calibration figures."""

import functools
import math

import numpy as np
import pytest
from scipy import ndimage

import fgat.viz.optics
from fgat.app.cli import main
from fgat.instrument.calibration import gains_from_image, read_calibration
from fgat.instrument.lattice import (
    PITCH_TOLERANCE,
    ROTATION_TOLERANCE_DEG,
    HexLattice,
    LatticeFit,
    lattice_mismatch,
    view_psf_energy,
)
from fgat.io.images import write_tiff
from fgat.optics.systems import load_system
from fgat.sim.simulation import SimulationConfig, simulate
from fgat.viz.optics import plot_calibration_overlay, plot_psf_stack

ROOT3 = math.sqrt(3.0)
PITCH_PX = 60.0  # the synthetic MLA images' pitch: 0.39 mm on 6.5-um pixels


def fit_of(pitch: float, rotation_deg: float, brightfield: bool = True) -> LatticeFit:
    """A perfect 7-lens lattice fit."""
    centers = HexLattice((128.0, 128.0), pitch, rotation_deg).centers(7)
    return LatticeFit(
        HexLattice((128.0, 128.0), pitch, rotation_deg),
        centers,
        np.zeros(7),
        np.zeros(7, dtype=bool),
        brightfield,
    )


def system_with(**fields):
    """The small system on a 256 x 256 sensor with a 60-px MLA, some fields changed."""
    base = {"mla_pitch_mm": PITCH_PX * 6.5 / 1000.0, "sensor_shape": (256, 256)}
    return load_system("small").replace(**{**base, **fields})


@pytest.mark.parametrize(
    ("scale", "convention", "measured_over_system"),
    [(2.0 / ROOT3, "corner", "0.866 = sqrt(3)/2"), (ROOT3 / 2.0, "row", "1.155 = 2/sqrt(3)")],
)
def test_a_pitch_off_by_a_convention_factor_is_refused_naming_it(
    scale, convention, measured_over_system
):
    """A datasheet pitch read in another convention: the system's nominal pitch is the true
    one times 2/sqrt(3) (a corner-to-corner width) or sqrt(3)/2 (a row distance)."""
    system = system_with(mla_pitch_mm=PITCH_PX * scale * 6.5 / 1000.0)
    message = lattice_mismatch(fit_of(PITCH_PX, 0.0), system)
    assert f"ratio {measured_over_system}" in message
    assert f"measured lenslet pitch 60.0 px, system 'small' {PITCH_PX * scale:.1f} px" in message
    assert f"set mla_pitch_convention: {convention}" in message
    assert "mla_pitch_mm: 0.39 with mla_pitch_convention: center" in message
    # the user's case: a few per cent of real magnification error on top of the factor
    assert f"set mla_pitch_convention: {convention}" in lattice_mismatch(
        fit_of(PITCH_PX * 0.978, 0.0), system
    )
    assert (
        lattice_mismatch(fit_of(PITCH_PX, 0.0), system.replace(mla_pitch_convention=convention))
        is None
    )


def test_a_pitch_within_the_tolerance_is_accepted_and_one_beyond_is_refused():
    system = system_with()
    for ratio in (1.0, 1.0 + 0.9 * PITCH_TOLERANCE, 1.0 - 0.9 * PITCH_TOLERANCE):
        assert lattice_mismatch(fit_of(PITCH_PX * ratio, 0.0), system) is None
    too_large = lattice_mismatch(fit_of(PITCH_PX * 1.08, 0.0), system)
    assert "ratio 1.080, no pitch convention (sqrt(3)/2, 2/sqrt(3)) explains it" in too_large
    assert "divide pixel_um by m" in too_large and "fluorescence" not in too_large
    seen_in_fluorescence = lattice_mismatch(fit_of(PITCH_PX * 1.08, 0.0, False), system)
    assert "also scales with its sample's mean depth" in seen_in_fluorescence


def test_the_convention_fields_make_a_mismatched_pitch_match():
    for convention, scale in (("corner", 2.0 / ROOT3), ("row", ROOT3 / 2.0)):
        system = system_with(
            mla_pitch_mm=PITCH_PX * scale * 6.5 / 1000.0, mla_pitch_convention=convention
        )
        assert system.pitch_px == pytest.approx(PITCH_PX)
        assert lattice_mismatch(fit_of(PITCH_PX * 1.01, 0.4), system) is None


def test_a_rotation_beyond_the_tolerance_is_refused_with_the_fields_that_match_it():
    system = system_with()
    assert lattice_mismatch(fit_of(PITCH_PX, 0.9 * ROTATION_TOLERANCE_DEG), system) is None
    assert (
        lattice_mismatch(fit_of(PITCH_PX, -29.5), system.replace(mla_orientation="flat-top"))
        is None
    )
    message = lattice_mismatch(fit_of(PITCH_PX, 5.0), system)
    assert "measured lattice rotation 5.0 deg, system 'small' 0.0 deg" in message
    assert "+5.0 deg apart; set mla_orientation: pointy-top and mla_rotation_deg: 5.0" in message
    assert lattice_mismatch(fit_of(PITCH_PX, 5.0), system.replace(mla_rotation_deg=5.0)) is None
    # a flat-top array (neighbours along the rows) taken for a pointy-top one
    message = lattice_mismatch(fit_of(PITCH_PX, -29.0), system)
    assert "-29.0 deg apart (near 30: the array is the other way up" in message
    assert "set mla_orientation: flat-top and mla_rotation_deg: 1.0" in message
    assert (
        lattice_mismatch(fit_of(PITCH_PX, -29.0), system.replace(mla_orientation="flat-top"))
        is None
    )
    flat_top = system.replace(mla_orientation="flat-top", mla_rotation_deg=1.0)
    assert lattice_mismatch(fit_of(PITCH_PX, -29.0), flat_top) is None
    assert lattice_mismatch(fit_of(PITCH_PX, 29.5), flat_top) is None  # 60 degrees repeat


def brightfield(shape, centers, radius, seed):
    """Bright aperture disks on a dark background, blurred by 1 px, with noise."""
    rows, cols = np.indices(shape)
    image = sum(((rows - r) ** 2 + (cols - c) ** 2 <= radius**2).astype(float) for r, c in centers)
    noise = np.random.default_rng(seed).standard_normal(shape)
    return 100.0 + 1000.0 * ndimage.gaussian_filter(image, 1.0) + 2.0 * noise


def test_calibrate_refuses_a_system_whose_pitch_is_the_corner_width_before_writing(
    tmp_path, capsys
):
    centers = HexLattice((128.0, 128.0), PITCH_PX, 0.5).centers(7)
    write_tiff(tmp_path / "mla.tif", brightfield((256, 256), centers, 25.0, 0).astype(np.float32))
    yaml = tmp_path / "mine.yaml"
    datasheet = (
        f"base: small\nname: mine\nsensor_shape: [256, 256]\nmla_pitch_mm: {0.39 * 2 / ROOT3}\n"
    )
    yaml.write_text(datasheet)
    out = tmp_path / "calib"
    command = ["calibrate", "--image", str(tmp_path / "mla.tif"), "--system", str(yaml)]
    assert main([*command, "--out", str(out)]) == 2
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1 and "Traceback" not in error
    assert "measured lenslet pitch 60.0 px, system 'mine' 69.3 px" in error
    assert "ratio 0.866 = sqrt(3)/2" in error and "set mla_pitch_convention: corner" in error
    assert not out.exists()
    yaml.write_text(datasheet + "mla_pitch_convention: corner\n")
    assert main([*command, "--flat", str(tmp_path / "mla.tif"), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "system mine: pitch 60.00 px (measured / system 1.00" in printed
    assert read_calibration(out).lattice.pitch == pytest.approx(PITCH_PX, rel=0.002)


@functools.cache
def vignetted_simulation():
    """A noise-free small37 bead image inside every view's field, the MLA turned 0.4 degrees,
    lenslets 1 px off the lattice, gains in [0.6, 1]; its outer ring is partly vignetted."""
    config = SimulationConfig(
        system="small37",
        depths_um="0",
        view_size=40,
        photons=None,
        phantom={"kind": "beads", "n_beads": 12, "sigma": 1.0, "margin": [0, 10, 10]},
        imperfections={
            "mla_rotation_deg": 0.4,
            "center_jitter_px": 1.0,
            "gains": [0.6, 1.0],
            "flat": True,
        },
    )
    return simulate(config)


@pytest.mark.slow
def test_gains_come_from_the_measured_lattice_when_the_nominal_one_is_off(tmp_path, capsys):
    """A system file 4.5 % off in pitch and 2 degrees off in rotation (accepted): the gains
    from the image divide each view's flux by its PSF energy at the measured centres and
    recover the true ones; the nominal lattice's energies would not (the outer lenses sit
    elsewhere in the pupil)."""
    sim = vignetted_simulation()
    truth = sim.imperfections.gains
    (tmp_path / "off.yaml").write_text(
        f"base: small37\nname: offset37\nmla_pitch_mm: {0.325 * 1.045}\nmla_rotation_deg: -2.0\n"
    )
    write_tiff(tmp_path / "sensor.tif", sim.sensor + 100.0)
    write_tiff(tmp_path / "flat.tif", sim.flat)
    command = ["calibrate", "--image", str(tmp_path / "sensor.tif")]
    command += ["--system", str(tmp_path / "off.yaml")]
    assert main([*command, "--out", str(tmp_path / "calib")]) == 0
    calibration = read_calibration(tmp_path / "calib")
    offsets = calibration.centers - sim.centers  # up to the scene's lateral position
    assert np.linalg.norm(offsets - offsets.mean(axis=0), axis=1).max() < 1.5
    assert np.abs(calibration.gains / truth - 1).max() < 0.04  # measured: 2.4 %
    # the flux per view, summed directly over a pitch-wide disc about each true centre
    rows, cols = np.indices(sim.sensor.shape)
    flux = np.array(
        [sim.sensor[np.hypot(rows - r, cols - c) <= 25.0].sum() for r, c in sim.centers]
    )
    system = load_system(str(tmp_path / "off.yaml"))
    share = calibration.gains * view_psf_energy(system, calibration.centers)
    assert np.abs(share / share.max() - flux / flux.max()).max() < 0.02
    nominal = view_psf_energy(system, system.lenslet_centers_px())
    wrong = gains_from_image(sim.sensor + 100.0, calibration.centers, 40, nominal)
    assert np.abs(wrong / truth - 1).max() > 0.08  # measured: 13 %
    # a white-light MLA image: each measured lenslet's mean over 0.4 pitch
    flat = [*command, "--flat", str(tmp_path / "flat.tif"), "--out", str(tmp_path / "flat")]
    assert main(flat) == 0
    assert np.abs(read_calibration(tmp_path / "flat").gains / truth - 1).max() < 0.01
    capsys.readouterr()


@pytest.fixture
def figures(monkeypatch):
    """The figures the plot functions save: ``[(figure size in inches, number of axes, texts
    of the first axes)]``."""
    saved = []
    original = fgat.viz.figures.save_figure

    def record(figure, path):
        texts = [(text.get_text(), text.get_position()) for text in figure.axes[0].texts]
        saved.append((tuple(figure.get_size_inches()), len(figure.axes), texts))
        return original(figure, path)

    monkeypatch.setattr(fgat.viz.optics, "save_figure", record)
    return saved


@pytest.mark.parametrize("n_views", [7, 37])
def test_psf_figure_lays_the_views_out_on_the_lattice(tmp_path, figures, n_views):
    stack = np.random.default_rng(0).random((n_views, 5, 21, 21)).astype(np.float32)
    path = plot_psf_stack(stack, tmp_path / "psf.png", depths_um=[-2, -1, 0, 1, 2], pixel_um=0.5)
    size, axes, texts = figures[0]
    assert axes == 2 * n_views + 1  # x-y and x-z of every view, and the colour bar
    assert [text for text, _ in texts] == ["0"]  # each view numbered in its own panel
    rings = {7: 3, 37: 7}[n_views]  # lenslets across the array
    assert size[0] / size[1] < 2.6 and size[0] < 2 * rings * 1.8 + 3.5
    from PIL import Image

    width, height = Image.open(path).size  # 8954 x 506 px for 37 views in a row before
    assert abs(width - size[0] * 110) <= 1 and abs(height - size[1] * 110) <= 1
    assert width < 1800 and height > 500


@pytest.mark.parametrize("n_views", [7, 37])
def test_overlay_labels_sit_on_the_rim_and_gains_in_a_table(tmp_path, figures, n_views):
    pitch = 60.0 if n_views == 7 else 30.0
    centers = HexLattice((150.0, 160.0), pitch, 1.0).centers(n_views)
    image = brightfield((300, 320), centers, 0.4 * pitch, 0)
    gains = np.linspace(1.0, 0.5, n_views)
    plot_calibration_overlay(image, centers, 0.45 * pitch, tmp_path / "a.png", gains=gains)
    plot_calibration_overlay(image, centers, 0.45 * pitch, tmp_path / "b.png")
    (size, axes, texts), (_, axes_plain, _) = figures
    assert axes == 2 and axes_plain == 1  # the image, and the gains' colour bar
    assert [text for text, _ in texts] == [str(v) for v in range(n_views)]
    for (row, col), (_, (x, y)) in zip(centers, texts):
        assert math.hypot(x - col, y - row) == pytest.approx(0.45 * pitch)  # on the rim
    assert size[0] > 7.0  # room for the gain table beside the image


@pytest.mark.parametrize("rotation", [29.6, -29.7])
def test_a_flat_top_array_is_numbered_like_its_system(rotation):
    """Near 30 degrees fgat's view order could number the array either way; calibrated against
    a flat-top system, view v is the system's nominal view v."""
    from fgat.instrument.lattice import fit_hexagonal_lattice, number_like

    system = system_with(mla_orientation="flat-top", sensor_shape=(257, 257))
    truth = HexLattice(system.optical_axis_px, PITCH_PX, rotation).centers(7)
    fit = fit_hexagonal_lattice(brightfield((257, 257), truth, 25.0, 1), 7, system.pitch_px)
    assert fit.lattice.pitch == pytest.approx(PITCH_PX, rel=0.01)  # once 0 at 29.6 degrees
    assert lattice_mismatch(fit, system) is None
    numbered = number_like(fit, system.lattice_rotation_deg)
    assert abs(numbered.lattice.rotation_deg - system.lattice_rotation_deg) < 1.0
    nominal = system.lenslet_centers_px()
    assert np.linalg.norm(numbered.centers - nominal, axis=1).max() < 2.0
    np.testing.assert_allclose(numbered.centers, numbered.lattice.centers(7), atol=0.5)
    assert number_like(numbered, system.lattice_rotation_deg) is numbered
