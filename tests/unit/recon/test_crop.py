"""Skipping empty space: the signal's box, the PSFs' reach, the cropped scene and fit."""

import numpy as np
import pytest
import torch

from fgat.gaussians.densify import Densification
from fgat.recon import StaticReconstruction, StaticSettings, phantom_scene
from fgat.recon.crop import crop_scene, psf_reach, signal_box
from fgat.sim.simulation import SimulationConfig

SLAB = dict(
    system="small",
    depths_um="-15:15:21",
    view_size=48,
    photons=None,
    background=0,
    phantom={
        "kind": "beads",
        "n_beads": 12,
        "sigma": 1.0,
        "min_spacing": 4.0,
        "margin": [8, 14, 14],
    },
)


def reach_by_brute_force(psf, energy):
    """The smallest centred square's half-width holding ``energy`` of every PSF, summing every
    box directly."""
    _, _, h, w = psf.shape
    for radius in range(max(h, w)):
        inside = psf[
            ...,
            max(h // 2 - radius, 0) : h // 2 + radius + 1,
            max(w // 2 - radius, 0) : w // 2 + radius + 1,
        ].sum(axis=(-2, -1))
        if np.all(inside >= energy * psf.sum(axis=(-2, -1))):
            return radius
    return h // 2


def test_psf_reach_is_the_smallest_box_holding_the_energy():
    rng = np.random.default_rng(0)
    y, x = np.mgrid[:31, :31]
    psf = np.zeros((3, 4, 31, 31))
    for v in range(3):
        for z in range(4):
            cy, cx = 15 + rng.uniform(-6, 6, 2)
            psf[v, z] = np.exp(-((y - cy) ** 2 + (x - cx) ** 2) / (2 * rng.uniform(0.8, 2.5) ** 2))
    for energy in (0.9, 0.99, 0.999):
        assert psf_reach(psf, energy) == (reach_by_brute_force(psf, energy),) * 2
    assert psf_reach(psf) == psf_reach(psf, 0.99)
    assert psf_reach(np.ones((1, 1, 9, 9)), 0.999) == (4, 4)  # spread to the crop's edges


def test_signal_box_against_the_lit_voxels():
    volume = np.zeros((10, 20, 30))
    volume[3, 5, 7] = 1.0
    volume[6, 12, 25] = 0.5
    volume[8, 2, 2] = 0.04  # below 5% of the maximum
    assert signal_box(volume, 0.05, (1, 2, 10)) == (slice(2, 8), slice(3, 15), slice(0, 30))
    assert signal_box(volume, 0.01, (0, 0, 0)) == (slice(3, 9), slice(2, 13), slice(2, 26))
    assert signal_box(np.zeros((2, 3, 4)), 0.1, (1, 1, 1)) == (
        slice(0, 2),
        slice(0, 3),
        slice(0, 4),
    )


def test_cropped_scene_predicts_the_cropped_measurement_at_the_same_places():
    """All the light in a crop's views comes from its box when the signal lies in the box: the
    crop's forward model (views and PSF planes cut alike) predicts the whole scene's prediction
    within the box to float rounding, however tight the box; grown by the PSFs' reach it holds
    99% of the light. Every voxel keeps its world position."""
    scene = phantom_scene(SimulationConfig(**SLAB))
    lit = signal_box(scene.truth, 1e-6, (0, 0, 0))
    box = (lit[0], *signal_box(scene.truth, 1e-6, (0, 2, 3))[1:])
    crop = crop_scene(scene, box)
    assert crop.volume_shape == tuple(s.stop - s.start for s in box)
    assert 0 < box[1].start and box[1].stop < scene.volume_shape[1]  # cut laterally too
    whole = scene.operator(torch.tensor(scene.psf)).forward(torch.tensor(scene.truth)).numpy()
    expected = whole[:, box[1], box[2]]
    predicted = crop.operator(torch.tensor(crop.psf)).forward(torch.tensor(crop.truth)).numpy()
    np.testing.assert_allclose(predicted, expected, rtol=1e-4, atol=1e-6 * expected.max())
    reach = psf_reach(scene.psf[:, lit[0]])
    window = signal_box(scene.truth, 1e-6, (0, *reach))
    assert whole[:, window[1], window[2]].sum() >= 0.99 * whole.sum()
    voxel = np.asarray(scene.voxel_size_um)
    start = np.array([s.start for s in box])
    np.testing.assert_allclose(
        np.asarray(crop.grid_origin), np.asarray(scene.grid_origin) + start * voxel, atol=1e-5
    )


@pytest.fixture(scope="module")
def slab_scene():
    return phantom_scene(SimulationConfig(**{**SLAB, "photons": 10000, "background": 10}))


def fit(scene, crop, steps=120):
    engine = StaticReconstruction(
        scene,
        StaticSettings(n_gaussians=150, baseline_iterations=0, crop=crop),
        Densification(enabled=False),
        total_steps=steps,
    )
    for _ in range(steps):
        engine.step()
    return engine


@pytest.mark.slow
def test_a_cropped_fit_pads_back_and_matches_the_whole_grid(slab_scene):
    whole, cropped = fit(slab_scene, 0.0), fit(slab_scene, 0.1)
    box = cropped.box
    saved = cropped.crop_metrics()["crop/voxels_saved"]
    assert 0.2 < saved < 1 and box[0] != slice(0, slab_scene.volume_shape[0])
    volume = cropped.volume()
    assert volume.shape == slab_scene.volume_shape
    outside = volume.clone()
    outside[box] = 0
    assert outside.abs().max() == 0
    assert cropped.cloud.shape == cropped.fit_scene.grid_shape
    psnr_whole = whole.evaluate()["val/psnr_volume"]
    psnr_cropped = cropped.evaluate()["val/psnr_volume"]
    assert psnr_cropped > psnr_whole - 0.5, (psnr_cropped, psnr_whole)
    state = cropped.state_dict()
    resumed = StaticReconstruction(
        slab_scene, cropped.settings, Densification(enabled=False), total_steps=120
    )
    resumed.load_state_dict(state)
    torch.testing.assert_close(resumed.volume(), volume)
    other = {**state, "crop_box": None}
    with pytest.raises(ValueError, match="the checkpoint was fitted on the crop None"):
        resumed.load_state_dict(other)


def test_the_dynamic_stage_refuses_a_cropped_static_run(tmp_path, slab_scene):
    from fgat.recon import load_static

    path = tmp_path / "static.ckpt"
    torch.save({"reconstruction": fit(slab_scene, 0.1, steps=1).state_dict()}, path)
    with pytest.raises(ValueError, match=r"was fitted on a crop of the grid \(model.crop"):
        load_static(path)
