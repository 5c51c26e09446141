"""Per-view parallax at NA 1.3 with a water sample under silicone oil against an independent
float64 high-NA model, and the depth-scale calibration from a bead z-stack."""

import math

import numpy as np
import pytest
import torch

from fgat.app.cli import main
from fgat.instrument.calibration import Calibration, read_calibration, save_calibration
from fgat.instrument.measurement import measurement_model
from fgat.io.images import read_tiff, write_tiff
from fgat.optics.depth_scale import (
    MAX_RESIDUAL,
    MIN_BEAD_SNR,
    calibrate_depth_scale,
    fit_depth_scale,
    render_bead_stack,
)
from fgat.optics.psf import JPGM
from fgat.optics.systems import load_system

WATER, COVERSLIP = 1.33, 1.518


def fresnel_transmittance(n1, n2, invariant):
    """Power transmittances (s, p) from index n1 into n2 at ``n sin(theta) = invariant``."""
    c1 = np.sqrt(1.0 - (invariant / n1) ** 2)
    c2 = np.sqrt(1.0 - (invariant / n2) ** 2)
    t_s = 2 * n1 * c1 / (n1 * c1 + n2 * c2)
    t_p = 2 * n1 * c1 / (n2 * c1 + n1 * c2)
    ratio = n2 * c2 / (n1 * c1)
    return ratio * t_s**2, ratio * t_p**2


def reference_centroids(system, depths_um, *, centers=None, medium="sample", samples_per_px=2):
    """(V, Z, 2) centroids (row, col) of each lenslet's image in its crop window, relative to the
    lenslet axis, independent of fgat's code: the Richards-Wolf pupil field of an isotropic
    emitter in water under a 1.518 coverslip and the immersion oil (amplitude
    sqrt((T_s1 T_s2 + T_p1 T_p2) / (2 cos theta_s)) from the sine condition and the Fresnel
    transmittances, which gives the centroid of the polarisation-averaged vectorial image),
    with the Gibson-Lanni phase of a depth step in the sample (2 pi z n_s cos theta_s / lambda)
    or of a step of the immersion layer (n_i cos theta_i), sampled at ``samples_per_px`` per
    camera pixel over each lenslet's aperture and pupil, and Fresnel-propagated through the
    lenslet to the camera by a float64 discrete Fourier integral at the crop's pixels.
    ``centers`` ``(V, 2)``: the lenslets (view 0 on the axis), default the system's."""
    lam, na, n_i = system.wavelength_um, system.na, system.immersion_index
    n_s = system.sample_medium_index
    radius_px = system.pupil_radius_px
    aperture = system.lenslet_aperture_mm * 500.0 / system.pixel_um
    kappa = system.pixel_um**2 / (lam * system.f_mla_mm * 1000.0)
    r = system.crop_radius_px
    centers = system.lenslet_centers_px() if centers is None else centers
    half = int(math.ceil(aperture * samples_per_px))
    t = np.arange(-half, half + 1) / samples_per_px
    j = np.arange(-r, r + 1, dtype=np.float64)
    kernel = np.exp(-2j * np.pi * kappa * np.outer(j, t))  # (window, aperture samples)
    out = np.zeros((len(centers), len(depths_um), 2))
    for v, c in enumerate(centers):
        uy, ux = np.meshgrid(c[0] + t, c[1] + t, indexing="ij")
        rho = np.hypot(uy - centers[0, 0], ux - centers[0, 1]) / radius_px
        invariant = na * rho
        lit = ((uy - c[0]) ** 2 + (ux - c[1]) ** 2 <= aperture**2) & (rho <= 1.0)
        lit &= invariant < n_s
        invariant = np.where(lit, invariant, 0.0)
        cos_s = np.sqrt(1.0 - (invariant / n_s) ** 2)
        first, second = (
            fresnel_transmittance(n_s, COVERSLIP, invariant),
            fresnel_transmittance(COVERSLIP, n_i, invariant),
        )
        intensity = (first[0] * second[0] + first[1] * second[1]) / (2.0 * cos_s)
        amplitude = np.where(lit, np.sqrt(intensity), 0.0)
        index = n_s if medium == "sample" else n_i
        optical_path = index * np.sqrt(1.0 - (invariant / index) ** 2)  # n cos(theta), per um
        for k, z in enumerate(depths_um):
            field = amplitude * np.exp(2j * np.pi * z * optical_path / lam)
            image = np.abs(kernel @ field @ kernel.T) ** 2
            total = image.sum()
            out[v, k] = [(image.sum(1) * j).sum() / total, (image.sum(0) * j).sum() / total]
    return out


def crop_centroids(stack):
    """(V, Z, 2) centroids (row, col) of a PSF stack's crops relative to the crop centre."""
    stack = stack.numpy()
    j = np.arange(stack.shape[-1]) - stack.shape[-1] // 2
    total = stack.sum(axis=(2, 3))
    return np.stack([(stack.sum(3) * j).sum(2) / total, (stack.sum(2) * j).sum(2) / total], axis=-1)


@pytest.fixture(scope="module")
def water_system():
    return load_system("small37").replace(sample_index=WATER)


def parallax_errors(system, depths, views):
    """Relative error (V, Z) of fgat's per-lenslet centroid shifts from focus against the
    reference's, the reference's shifts (V, Z, 2), for ``views`` (view 0 first)."""
    centers = system.lenslet_centers_px()[views]
    with torch.no_grad():
        model = JPGM(
            system,
            depths,
            centers_px=centers,
            method="mft",
            oversampling=2,  # what the automatic choice takes here
            zernike_indices=(),
            dtype=torch.float64,
        )
        shifts = crop_centroids(model())
    reference = reference_centroids(system, depths, centers=centers)
    focus = list(depths).index(0.0)
    ours = shifts - shifts[:, focus : focus + 1]
    theirs = reference - reference[:, focus : focus + 1]
    size = np.linalg.norm(theirs, axis=-1)
    error = np.linalg.norm(ours - theirs, axis=-1) / np.maximum(size, 1e-12)
    assert np.abs(ours[0]).max() < 1e-6 and np.abs(theirs[0]).max() < 1e-6
    return np.delete(error, focus, axis=1)[1:], theirs


def test_jpgm_parallax_matches_the_high_na_reference_at_every_ring_and_depth(water_system):
    """60x/1.3 silicone objective on water, one view of each ring (views 1, 7, 13, 19, 31 at
    1, sqrt(3), 2, sqrt(7) and 3 pitches) over -6..6 um (the outer view moves 18 px in its
    24-px crop): fgat's per-lenslet centroid shifts stay within 2% of the reference (1.5%
    measured at the outer ring, the Fresnel loss fgat leaves out; 8% there and 4% at sqrt(7)
    pitches without the aplanatic apodization). The outer ring moves 3.79 px per um over the
    3 um around focus."""
    depths = [-6.0, -3.0, 0.0, 3.0, 6.0]
    error, reference = parallax_errors(water_system, depths, [0, 1, 7, 13, 19, 31])
    assert error.max() <= 0.02, error.max()
    assert error[:3].max() < 2e-3  # inner rings: the Fresnel loss is negligible there
    outer = np.linalg.norm(reference[-1, 3]) / 3.0
    assert outer == pytest.approx(3.79, abs=0.02)


@pytest.mark.slow
def test_jpgm_parallax_matches_the_high_na_reference_for_every_view(water_system):
    """The same for all 37 views at 13 depths from -6 to 6 um."""
    depths = list(np.linspace(-6.0, 6.0, 13))
    error, _ = parallax_errors(water_system, depths, list(range(37)))
    assert error.max() <= 0.02, error.max()


def test_stage_steps_are_immersion_layer_steps(water_system):
    """A stage step changes the oil layer, not the depth in the water: the JPGM's
    ``depth_medium="immersion"`` moves every ring as the reference's oil-layer phase does, within
    2%, and 0.94 (first ring) to 0.75 (outer ring) times as far per um as a step in the water."""
    views = [0, 1, 7, 13, 19, 31]
    centers = water_system.lenslet_centers_px()[views]
    depths = [-2.0, 0.0, 2.0]
    slopes = {}
    for medium in ("sample", "immersion"):
        with torch.no_grad():
            model = JPGM(
                water_system,
                depths,
                centers_px=centers,
                method="mft",
                oversampling=2,
                zernike_indices=(),
                depth_medium=medium,
                dtype=torch.float64,
            )
            shifts = crop_centroids(model())
        ours = np.linalg.norm(shifts[:, 2] - shifts[:, 0], axis=-1)[1:] / 4.0
        reference = reference_centroids(water_system, depths, centers=centers, medium=medium)
        theirs = np.linalg.norm(reference[:, 2] - reference[:, 0], axis=-1)[1:] / 4.0
        np.testing.assert_allclose(ours, theirs, rtol=0.02)
        slopes[medium] = theirs
    ratio = slopes["immersion"] / slopes["sample"]
    assert ratio[0] == pytest.approx(0.94, abs=0.01)
    assert ratio[-1] == pytest.approx(0.75, abs=0.02)
    assert np.all(np.diff(ratio) < 0)
    with pytest.raises(ValueError, match="depth_medium must be one of"):
        JPGM(water_system, [0.0], depth_medium="stage")


TRUE_SCALE = 1.12


@pytest.fixture(scope="module")
def bead_frames():
    """A small37 stage z-stack (-3..3 um, 7 frames) of an on-axis bead seen through optics whose
    pupil phase per um is TRUE_SCALE times the nominal one's; Poisson noise, peak 400 counts
    over an offset of 100."""
    system = load_system("small37")
    positions = np.linspace(-3.0, 3.0, 7)
    clean = render_bead_stack(
        system.replace(depth_scale=TRUE_SCALE), positions, system.lenslet_centers_px()
    )
    rng = np.random.default_rng(0)
    return positions, rng.poisson(clean * 400.0 / clean.max() + 100.0).astype(np.float32)


def test_calibration_recovers_a_depth_scale_and_refuses_noise(bead_frames):
    """The fit gives TRUE_SCALE back within 2% (0.1% measured, misfit 0.9% of the parallax);
    pure noise is refused before the model is rendered."""
    positions, frames = bead_frames
    nominal = load_system("small37")
    centers = nominal.lenslet_centers_px()
    fit = calibrate_depth_scale(frames, positions, nominal, centers)
    assert fit.scale == pytest.approx(TRUE_SCALE, rel=0.02)
    assert fit.residual < MAX_RESIDUAL and fit.snr > MIN_BEAD_SNR
    assert fit.used.sum() == 36
    assert all(r == pytest.approx(TRUE_SCALE, rel=0.03) for r in fit.ring_ratios.values())
    noise = np.random.default_rng(1).poisson(100.0, size=frames.shape).astype(np.float32)
    with pytest.raises(ValueError, match="MIN_BEAD_SNR"):
        calibrate_depth_scale(noise, positions, nominal, centers)


@pytest.mark.slow
def test_calibrate_depth_command_writes_the_scale_every_command_reads(
    bead_frames, tmp_path, capsys
):
    """``fgat calibrate-depth`` writes the fitted scale into calibration.yaml with its
    provenance; the measurement model (deconvolve, fit) and ``fgat psf --centers`` then use it;
    a second run needs --overwrite, and a noise stack fails with one line, leaving the
    calibration as it was. The stack read with the objective's sign, and positions that take
    the bead out of the crops, are refused."""
    positions, frames = bead_frames
    system = load_system("small37")
    folder = tmp_path / "calib"
    folder.mkdir()
    save_calibration(Calibration(centers=system.lenslet_centers_px()), folder)
    write_tiff(tmp_path / "beads.tif", frames, axes="ZYX")
    command = [
        "calibrate-depth",
        "--stack",
        str(tmp_path / "beads.tif"),
        "--positions-um=-3:3:7",
        "--system",
        "small37",
        "--calibration",
        str(folder),
    ]
    assert main(command) == 0
    assert "depth scale 1.1" in capsys.readouterr().out
    calibration = read_calibration(folder)
    assert calibration.depth_scale == pytest.approx(TRUE_SCALE, rel=0.02)
    assert "beads.tif, stage positions -3..3 um (7)" in calibration.depth_scale_source
    model = measurement_model(calibration=calibration, system=system, depths_um=[-2.0, 2.0])
    assert model.optics.system.depth_scale == calibration.depth_scale
    expected = JPGM(system.replace(depth_scale=calibration.depth_scale), [-2.0, 2.0])
    with torch.no_grad():
        np.testing.assert_allclose(model.psf, expected().numpy(), rtol=1e-5, atol=1e-7)
    psf = tmp_path / "psf.ome.tif"
    assert main(["psf", "--system", "small37", "--depths-um=-2,2", "--centers", str(folder),
                 "--out", str(psf)]) == 0  # fmt: skip
    np.testing.assert_allclose(read_tiff(psf, ndim=4), model.psf, rtol=1e-5, atol=1e-7)
    assert main(command) == 2
    assert "pass --overwrite" in capsys.readouterr().err
    write_tiff(tmp_path / "noise.tif", np.full_like(frames, 100.0) + frames.std(), axes="ZYX")
    noise = [*command, "--overwrite"]
    noise[2] = str(tmp_path / "noise.tif")
    assert main(noise) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and "MIN_BEAD_SNR" in error[0]
    assert error[0].startswith(f"fgat calibrate-depth: error: --stack {noise[2]}: depth scale: ")
    assert read_calibration(folder).depth_scale == calibration.depth_scale
    centers = system.lenslet_centers_px()
    with pytest.raises(ValueError, match="other way"):
        calibrate_depth_scale(frames, positions, system, centers, motion="objective")
    with pytest.raises(ValueError, match="past the 24-px crops"):
        calibrate_depth_scale(frames, positions * 3.0, system, centers)


def test_fit_refuses_a_ring_dependent_parallax():
    """Parallax that grows faster with the ring than one factor allows (a wrong pupil radius)
    is refused with the threshold named; a uniform one is fitted exactly."""
    system = load_system("small37")
    centers = system.lenslet_centers_px()
    distance = np.linalg.norm(centers - centers[0], axis=1)
    direction = (centers - centers[0]) / np.maximum(distance, 1e-12)[:, None]
    model = -direction * (0.5 * distance / 50.0)[:, None]
    fit = fit_depth_scale(0.9 * model, model, centers)
    assert fit.scale == pytest.approx(0.9, rel=1e-12) and fit.residual < 1e-12
    assert set(fit.ring_ratios) == {1.0, 1.73, 2.0, 2.65, 3.0}
    warped = model * (1.0 + 0.4 * (distance / distance.max()) ** 2)[:, None]
    with pytest.raises(ValueError, match="MAX_RESIDUAL = 0.05"):
        fit_depth_scale(warped, model, centers)


def test_calibration_file_checks_the_depth_scale(tmp_path):
    """calibration.yaml round-trips the depth scale and its source; a non-positive one is
    refused with the file and the field named."""
    system = load_system("small37")
    save_calibration(
        Calibration(centers=system.lenslet_centers_px(), depth_scale=0.93, depth_scale_source="z"),
        tmp_path,
    )
    calibration = read_calibration(tmp_path)
    assert (calibration.depth_scale, calibration.depth_scale_source) == (0.93, "z")
    path = tmp_path / "calibration.yaml"
    path.write_text(path.read_text().replace("depth_scale: 0.93", "depth_scale: -1"))
    with pytest.raises(ValueError, match="calibration.yaml: depth_scale"):
        read_calibration(tmp_path)
    with pytest.raises(ValueError, match="depth_scale must be a positive number"):
        Calibration(centers=system.lenslet_centers_px(), depth_scale=0.0)
