"""A real acquisition in the forward model: per-view gains, pixel masks, a lateral guard band."""

import dataclasses

import numpy as np
import pytest
import scipy.signal
import torch

from fgat.dynamics.hexplane import HexPlaneSettings
from fgat.gaussians.cloud import GaussianCloud
from fgat.gaussians.densify import Densification
from fgat.optics.acquisition import (
    MeasuredOperator,
    crop_guard,
    guard_band,
    padded_shape,
    psf_support_radius,
)
from fgat.optics.operator import FLFMOperator, operator_memory
from fgat.optics.psf import JPGM
from fgat.optics.systems import load_system
from fgat.recon import (
    DynamicReconstruction,
    DynamicSettings,
    StaticReconstruction,
    StaticSettings,
    phantom_scene,
)
from fgat.recon.costs import deconvolution_memory
from fgat.recon.deconvolution import deconvolve
from fgat.recon.dynamic import check_scene
from fgat.recon.estimation import OpticsEstimation, run_event
from fgat.recon.losses import dynamic_loss, pixel_loss
from fgat.recon.metrics import psnr
from fgat.recon.scene import normalized_measurement
from fgat.sim.phantoms import beads
from fgat.sim.simulation import SimulationConfig

SIMULATION = dict(
    system="small",
    depths_um="-12:12:7",
    view_size=32,
    photons=None,
    phantom={"kind": "beads", "n_beads": 6, "sigma": 1.0, "min_spacing": 6, "margin": [1, 5, 5]},
)
GAINS = np.array([1.0, 0.9, 0.8, 0.7, 0.75, 0.85, 0.95])  # outer views dimmer


def random_problem(seed=0, guard=3, shape=(2, 9, 11), views=3, psf_size=(7, 5)):
    rng = np.random.default_rng(seed)
    psf = torch.from_numpy(rng.random((views, shape[0], *psf_size)))
    gains = torch.from_numpy(rng.uniform(0.7, 1.0, views))
    operator = MeasuredOperator(psf, shape[1:], guard, gains)
    volume = torch.from_numpy(rng.random(padded_shape(shape, guard)))
    return rng, psf, gains, operator, volume


def brute_force_views(volume, psf, gains, guard, view_shape):
    """Float64 scipy reference: per view, sum over depth of fftconvolve(mode="same") on the padded
    volume, central crop, times the view's gain."""
    y, x = view_shape
    return np.stack(
        [
            gains[v]
            * sum(
                scipy.signal.fftconvolve(volume[z], psf[v, z], mode="same")
                for z in range(len(volume))
            )[guard : guard + y, guard : guard + x]
            for v in range(len(psf))
        ]
    )


# ---------------------------------------------------------------------- the operator
def test_adjoint_identity_with_guard_and_gains():
    rng, _, _, operator, volume = random_problem()
    assert operator.volume_shape == (2, 15, 17) and operator.view_shape == (9, 11)
    for batch in ((), (2,)):
        x = torch.from_numpy(rng.random((*batch, *operator.volume_shape)))
        y = torch.from_numpy(rng.random((*batch, 3, 9, 11)))
        left = float((operator.forward(x) * y).sum())
        right = float((x * operator.adjoint(y)).sum())
        assert abs(left - right) <= 1e-10 * abs(left)


def test_no_guard_no_gains_is_the_flfm_operator_exactly():
    rng = np.random.default_rng(1)
    psf = torch.from_numpy(rng.random((3, 2, 7, 5)))
    measured, plain = MeasuredOperator(psf, (9, 11)), FLFMOperator(psf, (2, 9, 11))
    volume, views = (
        torch.from_numpy(rng.random((2, 9, 11))),
        torch.from_numpy(rng.random((3, 9, 11))),
    )
    assert torch.equal(measured.forward(volume), plain.forward(volume))
    assert torch.equal(measured.adjoint(views), plain.adjoint(views))
    assert measured.crop(volume) is not None and torch.equal(measured.crop(volume), volume)
    assert (measured.n_views, measured.psf_shape, measured.dtype) == (3, (7, 5), torch.float64)


def test_forward_with_guard_equals_fftconvolve_on_the_padded_volume():
    _, psf, gains, operator, volume = random_problem(2, guard=4)
    expected = brute_force_views(volume.numpy(), psf.numpy(), gains.numpy(), 4, (9, 11))
    np.testing.assert_allclose(operator.forward(volume).numpy(), expected, rtol=1e-10, atol=1e-12)


def test_crop_pad_and_gains_gradient():
    _, psf, gains, operator, volume = random_problem(3)
    inner = operator.crop(volume)
    assert inner.shape == (2, 9, 11) and torch.equal(inner, volume[:, 3:12, 3:14])
    padded = operator.pad(inner)
    assert padded.shape == operator.volume_shape and torch.equal(operator.crop(padded), inner)
    assert float(padded.sum()) == pytest.approx(float(inner.sum()))
    np.testing.assert_array_equal(crop_guard(volume.numpy(), 3), inner.numpy())
    # d/dg_v sum(forward) = sum of the ungained view v
    trainable = gains.clone().requires_grad_(True)
    operator.with_gains(trainable).forward(volume).sum().backward()
    ungained = operator.with_gains(None).forward(volume).sum(dim=(1, 2))
    torch.testing.assert_close(trainable.grad, ungained)
    with pytest.raises(ValueError, match="gains must have shape"):
        MeasuredOperator(psf, (9, 11), 3, torch.ones(2))
    with pytest.raises(ValueError, match="finite and positive"):
        MeasuredOperator(psf, (9, 11), 3, torch.tensor([1.0, 0.0, 1.0]))
    with pytest.raises(ValueError, match="guard_px"):
        MeasuredOperator(psf, (9, 11), -1)
    with pytest.raises(ValueError, match="views must end in shape"):
        operator.adjoint(torch.ones(3, 15, 17, dtype=torch.float64))


def test_psf_support_radius_is_the_smallest_chebyshev_square_holding_the_fraction():
    psf = np.zeros((2, 3, 21, 21))
    psf[0, 0, 10, 10] = 1.0
    psf[1, 2, 10 + 3, 10 - 7] = 1.0  # a shifted (parallax) PSF: Chebyshev distance 7
    assert psf_support_radius(psf) == 7
    psf[0, 1, 10 + 2, 10 + 2] = 9.0  # 90% at distance 2, 10% at distance 9
    psf[0, 1, 10 - 9, 10] = 1.0
    assert psf_support_radius(psf[:1], 0.9) == 2
    assert psf_support_radius(psf[:1], 0.95) == 9
    # brute force on a random stack: the first r whose square holds the fraction, max over crops
    rng = np.random.default_rng(4)
    stack = rng.random((3, 2, 15, 13)) ** 8
    for fraction in (0.5, 0.9, 0.999):
        expected = 0
        for crop in stack.reshape(-1, 15, 13):
            radius = 0
            while (
                crop[max(7 - radius, 0) : 8 + radius, max(6 - radius, 0) : 7 + radius].sum()
                < fraction * crop.sum()
            ):
                radius += 1
            expected = max(expected, radius)
        assert psf_support_radius(torch.from_numpy(stack), fraction) == expected
    assert psf_support_radius(np.zeros((1, 1, 5, 5))) == 0
    auto = psf_support_radius(psf[:1], fraction=0.99)
    assert guard_band("auto", psf[:1]) == auto and guard_band(5, psf) == 5
    assert guard_band("auto", psf[:1], max_px=auto - 1) == auto - 1
    with pytest.raises(ValueError, match="fraction"):
        psf_support_radius(psf, 0.0)
    with pytest.raises(ValueError, match="guard_px"):
        guard_band("wide", psf)


def test_memory_estimates_count_the_padded_grid():
    psf_shape, shape = (7, 5, 65, 65), (5, 40, 40)
    assert operator_memory(psf_shape, shape, guard_px=0) == operator_memory(psf_shape, shape)
    assert operator_memory(psf_shape, shape, guard_px=12) == operator_memory(psf_shape, (5, 64, 64))
    assert (
        deconvolution_memory(psf_shape, shape, guard_px=12)
        > deconvolution_memory(psf_shape, (5, 64, 64)) - 1
    )


# ---------------------------------------------------------------------- the guard band
@pytest.fixture(scope="module")
def small_psf():
    with torch.no_grad():
        return JPGM(load_system("small"), np.linspace(-12, 12, 7))().double()


def test_guard_band_removes_the_frame_artefact(small_psf):
    """Beads just outside the field of view (and some inside) on a padded truth: SHB on a grid the
    size of the views paints their light into a bright border frame; SHB on a grid padded by the
    PSF's support radius puts it in the guard band."""
    y, outside = 32, 12
    inner = beads((7, y - 8, y - 8), 8, sigma=1.0, min_spacing=5, margin=1, seed=1)
    truth = beads((7, y + 2 * outside, y + 2 * outside), 40, sigma=1.0, min_spacing=5, seed=11)
    truth[:, outside - 1 : outside + y + 1, outside - 1 : outside + y + 1] = 0  # none in the field
    truth[:, outside + 4 : outside + y - 4, outside + 4 : outside + y - 4] += inner
    simulation = MeasuredOperator(small_psf, (y, y), outside)
    truth = torch.from_numpy(truth).double()
    views = simulation.forward(truth)
    central = simulation.crop(truth).numpy()

    def frame(volume):  # mean of the outer 2-voxel ring over the interior's mean
        ring = np.ones(volume.shape[1:], bool)
        ring[2:-2, 2:-2] = False
        return volume[:, ring].mean() / volume[:, 2:-2, 2:-2].mean()

    guard = psf_support_radius(small_psf)
    assert guard == 32 and frame(central) == 0.0
    scores = {}
    for g in (0, guard):
        operator = MeasuredOperator(small_psf, (y, y), g)
        volume = operator.crop(deconvolve(views, operator, 30)).numpy()
        scores[g] = frame(volume), psnr(volume, central, data_range=float(central.max()))
    # measured: frame 0.189 -> 0.018, PSNR 38.5 -> 48.1 dB
    assert scores[guard][0] < 0.2 * scores[0][0] and scores[0][0] > 0.15
    assert scores[guard][1] > scores[0][1] + 6.0


# ---------------------------------------------------------------------- the engines
@pytest.fixture(scope="module")
def scene():
    return phantom_scene(SimulationConfig(**SIMULATION))


def test_scene_fields_grid_and_checks(scene):
    guarded = dataclasses.replace(scene, guard_px=5, gains=GAINS)
    assert guarded.volume_shape == (7, 32, 32) and guarded.grid_shape == (7, 42, 42)
    plain = GaussianCloud(scene.volume_shape, scene.voxel_size_um)
    padded = GaussianCloud(guarded.grid_shape, scene.voxel_size_um, origin=guarded.grid_origin)
    index = torch.tensor([[0, 0, 0], [3, 17, 31], [6, 31, 0]])
    torch.testing.assert_close(
        padded.voxel_centers(index + torch.tensor([0, 5, 5])), plain.voxel_centers(index)
    )
    assert scene.grid_origin == tuple(plain.origin.tolist())  # no guard: the cloud's default
    hot = np.ones((7, 4, 4))
    hot[1, 2, 2] = 100.0
    mask = np.ones_like(hot)
    mask[1, 2, 2] = 0
    views, scale = normalized_measurement(hot + 5.0, 5.0, mask=mask)
    assert scale == 1.0 and views[1, 2, 2] == 100.0  # the hot pixel does not set the scale
    with pytest.raises(ValueError, match="gains must be 7 finite positive"):
        dataclasses.replace(scene, gains=np.ones(3))
    with pytest.raises(ValueError, match="mask must be 0/1"):
        dataclasses.replace(scene, mask=np.full(scene.measurement.shape, 0.5))
    with pytest.raises(ValueError, match="guard_px"):
        dataclasses.replace(scene, guard_px=-2)


def test_normalized_measurement_is_scale_invariant_and_exact():
    """Counts and any multiple of them (offset too, scaled in float64) normalise to the same
    float32 views; for counts float32 holds exactly they equal float32 arithmetic (division is
    correctly rounded either way); a sequence is normalised by its reference frame's maximum."""
    counts = np.random.default_rng(0).poisson(40.0, (2, 3, 5, 6)).astype(np.float32) + 100.0
    reference, offset = 1, 100.0
    float32 = np.clip(counts - np.float32(offset), 0, None)
    expected = float32 / float32[reference].max()
    views, scale = normalized_measurement(counts, offset, reference)
    assert views.dtype == np.float32 and scale == float(float32[reference].max())
    np.testing.assert_array_equal(views, expected)
    for factor in (1e-6, 3.7, 1e6):
        scaled, scaled_scale = normalized_measurement(
            counts.astype(np.float64) * factor, offset * factor, reference
        )
        np.testing.assert_array_equal(scaled, views)
        assert scaled_scale == pytest.approx(scale * factor, rel=1e-15)


def test_static_step_uses_gains_mask_and_guard(scene):
    """One static step's loss is the masked L1 of the gained, guarded forward model of the padded
    Gaussians; a hot pixel under the mask changes nothing; outputs are cropped."""
    mask = np.ones(scene.measurement.shape, np.float32)
    mask[2, 10, 12] = 0
    hot = scene.measurement.copy()
    hot[2, 10, 12] = 1e6
    acquired = dataclasses.replace(scene, measurement=hot, mask=mask, gains=GAINS, guard_px=4)
    settings = StaticSettings(n_gaussians=40, init_iterations=5, baseline_iterations=5)
    engines = [
        StaticReconstruction(s, settings, Densification(enabled=False), total_steps=5)
        for s in (acquired, dataclasses.replace(acquired, measurement=scene.measurement))
    ]
    engine = engines[0]
    assert engine.cloud.shape == (7, 40, 40) and engine.volume().shape == (7, 32, 32)
    assert engine.baseline.shape == (7, 32, 32)
    torch.testing.assert_close(engine.baseline, engines[1].baseline)  # the hot pixel is ignored
    operator = MeasuredOperator(engine.psf.double(), (32, 32), 4, GAINS)
    with torch.no_grad():
        expected = pixel_loss(
            operator.forward(engine.cloud().double()),
            torch.from_numpy(hot).double(),
            1,
            torch.from_numpy(mask).double(),
        )
    results = [e.step() for e in engines]
    assert results[0].losses["pix"] == pytest.approx(float(expected), rel=1e-5)
    assert results[0].losses["pix"] == pytest.approx(results[1].losses["pix"], rel=1e-6)
    assert results[0].metrics == {}  # gains fixed: nothing to log
    assert set(engine.evaluate()) >= {"val/psnr_volume", "val/psnr_volume_shb"}


def test_joint_gain_estimation_recovers_relative_gains():
    """Views scaled by known gains (0.7-1.0, Poisson noise at 300 photons); a static fit that
    starts from gains 1 recovers g_v / g_0 (measured: max error 1.4% after 150 steps)."""
    noisy = phantom_scene(SimulationConfig(**{**SIMULATION, "photons": 300.0}))
    views = noisy.measurement * GAINS[:, None, None]
    noisy = dataclasses.replace(noisy, measurement=(views / views.max()).astype(np.float32))
    settings = StaticSettings(
        n_gaussians=200,
        init_iterations=10,
        baseline_iterations=0,
        lr_means=0.05,
        lr_intensities=0.05,
        estimate_gains=True,
    )
    engine = StaticReconstruction(noisy, settings, Densification(enabled=False), total_steps=150)
    for _ in range(150):
        result = engine.step()
    estimated = np.array([result.metrics[f"gain/view{v}"] for v in range(7)])
    np.testing.assert_allclose(estimated / estimated[0], GAINS / GAINS[0], atol=0.03)
    assert float(np.exp(np.log(estimated).mean())) == pytest.approx(1.0, rel=1e-5)  # the gauge


def test_gain_gauge_and_resume(scene):
    """A uniform change of every log-gain leaves the gains (and the prediction) unchanged; the
    gains' geometric mean stays the scene's; state_dict carries them."""
    known = dataclasses.replace(scene, gains=GAINS)
    settings = StaticSettings(n_gaussians=30, init="random", baseline_iterations=0)
    settings = dataclasses.replace(settings, estimate_gains=True, lr_gains=0.05)
    engine = StaticReconstruction(known, settings, Densification(enabled=False), total_steps=5)
    torch.testing.assert_close(engine.gains(), torch.tensor(GAINS, dtype=torch.float32))
    for _ in range(3):
        engine.step()
    volume = engine.grid_volume()
    with torch.no_grad():
        before = engine.operator.forward(volume)
        engine.log_gains.add_(0.4)
        torch.testing.assert_close(engine.operator.forward(volume), before)
    gains = engine.gains().detach()
    assert not torch.allclose(gains, torch.tensor(GAINS, dtype=torch.float32))  # they moved
    assert float(gains.log().mean()) == pytest.approx(float(np.log(GAINS).mean()), abs=1e-6)
    state = engine.state_dict()
    other = StaticReconstruction(known, settings, Densification(enabled=False), total_steps=5)
    other.load_state_dict(state)
    torch.testing.assert_close(other.gains(), engine.gains())
    assert [g["name"] for g in other.optimizer.param_groups][-1] == "gains"


def test_jpgm_event_sees_the_acquisition(scene, small_psf):
    """run_event with the acquisition's operator factory and mask: at the true optics and the
    padded truth, the data loss is zero (the plain FLFMOperator would not even fit the grid)."""
    optics = scene.truth_optics
    jpgm = optics.jpgm()
    with torch.no_grad():
        psf = jpgm()
    volume = torch.from_numpy(
        beads((7, 40, 40), 10, sigma=1.0, min_spacing=5, margin=(1, 2, 2), seed=3)
    )
    gains = torch.tensor(GAINS, dtype=torch.float32)
    measurement = MeasuredOperator(psf, (32, 32), 4, gains).forward(volume)
    mask = torch.ones_like(measurement)
    mask[0, :4] = 0
    measurement[0, :4] = 50.0  # masked junk
    schedule = OpticsEstimation(estimate="shifts", steps=1)
    result = run_event(
        jpgm,
        volume,
        measurement,
        schedule,
        schedule.optimizer(jpgm),
        operator=lambda stack: MeasuredOperator(stack, (32, 32), 4, gains),
        mask=mask,
    )
    assert result["loss_before"] < 1e-6


def test_dynamic_stage_with_guard_gains_and_mask():
    simulation = {
        **SIMULATION,
        "frames": 3,
        "phantom": {
            "kind": "moving_beads",
            "n_beads": 4,
            "sigma": 1.0,
            "velocity": [0.0, 4.0, 0.0],
            "min_spacing": 5.0,
            "margin": [2, 7, 5],
        },
    }
    mask = np.ones((7, 32, 32), np.float32)
    mask[1, 5, 5] = 0
    sequence = dataclasses.replace(
        phantom_scene(SimulationConfig(**simulation)), gains=GAINS, mask=mask, guard_px=3
    )
    static = StaticReconstruction(
        sequence,
        StaticSettings(n_gaussians=30, init="random", baseline_iterations=0),
        Densification(enabled=False),
        total_steps=2,
    )
    static.step()
    engine = DynamicReconstruction.from_static(
        sequence,
        static.cloud,
        static.psf,
        static.gains(),
        HexPlaneSettings(channels=4, spatial_resolution=(2, 4, 4)),
        DynamicSettings(width=8, lambda_tv=0, lambda_sm=0, lambda_l1=0),
    )
    assert engine.volume_at(0.5).shape == (7, 32, 32)
    assert engine.volumes().shape == (3, 7, 32, 32) and engine.still_volume().shape == (7, 32, 32)
    torch.manual_seed(0)  # the step draws its frame order from the global stream
    frame = engine.next_frame()
    with torch.no_grad():
        prediction = MeasuredOperator(static.psf, (32, 32), 3, GAINS).forward(
            engine.grid_volume_at(float(engine.times[frame]))
        )
        views = torch.from_numpy(engine.frames[frame])
        expected = dynamic_loss(
            prediction,
            views,
            engine.field.hexplane,
            lambda_tv=0,
            lambda_sm=0,
            lambda_l1=0,
            mask=torch.from_numpy(mask),
        )["total"]
    torch.manual_seed(0)
    assert engine.step().losses["total"] == pytest.approx(float(expected), rel=1e-5)
    assert "val/loss_pix" in engine.evaluate()
    with pytest.raises(ValueError, match="with a 3-voxel guard band"):
        check_scene(sequence, (7, 32, 32), tuple(static.psf.shape))
