"""Held-out pixels: the split, the stopping rule, and SHB and the static stage stopped by them."""

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from fgat.app.callbacks import HoldoutStopping
from fgat.gaussians.densify import Densification
from fgat.optics.operator import FLFMOperator
from fgat.recon import HoldoutStop, StaticReconstruction, StaticSettings, phantom_scene
from fgat.recon.deconvolution import deconvolve, iterate_deconvolution
from fgat.recon.holdout import holdout_split
from fgat.recon.metrics import psnr
from fgat.recon.names import HOLDOUT_LOSS
from fgat.sim.simulation import SimulationConfig

BEADS = {"kind": "beads", "n_beads": 40, "sigma": 1.0, "min_spacing": 6.0, "margin": 3.0}


def test_split_is_disjoint_seeded_and_keeps_the_mask():
    mask = torch.ones(3, 40, 50)
    mask[1, ::4] = 0
    fit, held = holdout_split(mask, (3, 40, 50), 0.2, seed=5)
    assert torch.equal(fit + held, mask) and float((fit * held).sum()) == 0
    share = float(held.sum() / mask.sum())
    assert abs(share - 0.2) < 4 * math.sqrt(0.2 * 0.8 / float(mask.sum()))
    again, _ = holdout_split(mask, (3, 40, 50), 0.2, seed=5)
    other, _ = holdout_split(mask, (3, 40, 50), 0.2, seed=6)
    assert torch.equal(again, fit) and not torch.equal(other, fit)
    fit, held = holdout_split(None, (2, 5, 5), 0.5, seed=0)
    assert torch.equal(fit + held, torch.ones(2, 5, 5))


def test_stop_rule_stops_patience_steps_after_the_best():
    rule = HoldoutStop(tolerance=1e-3, patience=5, min_steps=0)
    losses = [10, 8, 6, 5, 4.999, 5.1, 5.2, 5.3, 5.4, 5.5, 5.6]  # 4.999: not 1e-3 better than 5
    reasons = [rule.update(value, step) for step, value in enumerate(losses, start=1)]
    assert reasons.index(next(r for r in reasons if r)) + 1 == 4 + 5
    assert rule.best == 5 and rule.best_step == 4
    restored = HoldoutStop(tolerance=1e-3, patience=5, min_steps=0)
    restored.load_state_dict(rule.state_dict())
    assert restored.update(6.0, 10) is not None
    late = HoldoutStop(tolerance=1e-3, patience=1, min_steps=50)
    assert all(late.update(1.0, step) is None for step in range(1, 50))
    with pytest.raises(FloatingPointError, match="step 3: the held-out loss is nan"):
        late.update(math.nan, 3)
    with pytest.raises(ValueError, match="tolerance > 0 and patience >= 1"):
        HoldoutStop(tolerance=0.0)


def _scene(seed):
    scene = phantom_scene(SimulationConfig(phantom=BEADS, photons=10000, background=100, seed=seed))
    operator = FLFMOperator(torch.as_tensor(scene.psf), scene.truth.shape)
    return scene, torch.as_tensor(scene.measurement), operator


@pytest.mark.slow
def test_shb_with_held_out_pixels_returns_the_estimate_of_their_least_cost():
    scene, measurement, operator = _scene(0)
    stopped = deconvolve(measurement, operator, 300, holdout=0.1, patience=15, seed=3)
    # Independently: the same split, every iterate's held-out Poisson cost in float64.
    fit, held = holdout_split(None, tuple(measurement.shape), 0.1, seed=3)
    costs, estimates = [], []
    observed = measurement.double()
    for step in iterate_deconvolution(measurement, operator, 300, weights=fit):
        prediction = step.prediction.double() * step.image_scale
        costs.append(float((held * (prediction - observed * torch.log(prediction))).sum()))
        estimates.append(step.estimate)
    best = int(np.argmin(costs))
    assert len(costs) > best + 15  # the minimum is inside the run, not at its end
    (returned,) = [k for k, estimate in enumerate(estimates) if torch.equal(estimate, stopped)]
    # float32 costs pick the minimum among iterates whose costs agree to about 1e-7
    assert costs[returned] <= costs[best] * (1 + 1e-6) and abs(returned - best) <= 2
    truth = torch.as_tensor(scene.truth)

    def score(volume):
        return float(psnr(volume / volume.max(), truth / truth.max(), data_range=1.0))

    assert score(stopped) > score(estimates[-1]) + 3  # 300 iterations fit the noise


def test_shb_held_out_pixels_bad_input():
    _, measurement, operator = _scene(1)
    with pytest.raises(ValueError, match=r"holdout must be a share of the pixels in \(0, 0.5\]"):
        deconvolve(measurement, operator, 5, holdout=0.7)
    with pytest.raises(ValueError, match="patience must be a positive integer"):
        deconvolve(measurement, operator, 5, holdout=0.1, patience=0)


@pytest.mark.slow
def test_static_step_reports_the_held_out_pixels_loss_and_does_not_fit_them():
    scene, measurement, _ = _scene(2)
    engine = StaticReconstruction(
        scene,
        StaticSettings(n_gaussians=200, holdout=0.25, baseline_iterations=0),
        Densification(enabled=False),
        total_steps=10,
    )
    assert float((engine.mask * engine.holdout_mask).sum()) == 0
    assert torch.equal(engine.mask + engine.holdout_mask, torch.ones_like(measurement))
    with torch.no_grad():
        prediction = engine.operator.forward(engine.cloud()).double()
    held = engine.holdout_mask.double()
    expected = float((held * (prediction - measurement.double()).abs()).sum() / held.sum())
    assert engine.step().metrics[HOLDOUT_LOSS] == pytest.approx(expected, rel=1e-5)
    with pytest.raises(ValueError, match=r"holdout must be a share of the pixels in \[0, 0.5\]"):
        StaticSettings(holdout=0.9)


def test_holdout_stopping_needs_held_out_pixels():
    module = SimpleNamespace(settings=StaticSettings())
    with pytest.raises(ValueError, match="set model.init_args.holdout"):
        HoldoutStopping().on_fit_start(None, module)
