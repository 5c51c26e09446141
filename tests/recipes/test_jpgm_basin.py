"""``benchmarks/jpgm_basin.py --figure``: JPGM against the true volume on a recipe's scene."""

from pathlib import Path

import numpy as np
import pytest
import torch

from fgat.app.recipes import jpgm_basin, time_vs_error

ROOT = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.slow


def test_recipe_basin_starts_from_the_ideal_optics_and_lowers_the_loss(monkeypatch):
    """Fig. S7's CPU recipe: the first row is the ideal optics (Zernike terms at zero, so sigma
    is exactly 1; PSF error a float64 ``||h_ideal - h_gt|| / ||h_gt||`` of the scene's PSFs),
    then one row per blur level of the recipe (plain events: one), whose updates lower the
    data loss."""
    monkeypatch.chdir(ROOT)
    rows = jpgm_basin.recipe_run("figS7", paper=False, seed=0, steps=6)
    start, *stages = rows
    assert start["blur_px"] is None and start["sigma"] == pytest.approx(1.0, abs=1e-6)
    scene, config = time_vs_error.case_scene("beads", "joint", seed=0)
    method = config["model"]["init_args"]["optics"].get("psf_method", "auto")
    with torch.no_grad():
        ideal = scene.optics.jpgm(method=method)
        true = scene.truth_optics.jpgm(zernike_indices=ideal.zernike_indices)()
        ideal, true = ideal().double().numpy(), true.double().numpy()
    expected = np.linalg.norm(ideal - true) / np.linalg.norm(true)
    assert start["psf_error"] == pytest.approx(expected, rel=1e-4)
    assert [row["blur_px"] for row in stages] == [0.0] and stages[0]["steps"] == 6
    assert stages[0]["loss_after"] < stages[0]["loss_before"]
    assert stages[0]["psf_error"] < start["psf_error"]
    assert torch.isfinite(torch.tensor([row["elapsed_s"] for row in rows])).all()


def test_recipe_basin_can_hold_the_static_stage_s_starting_volume(monkeypatch):
    """``--volume seed`` holds the rendered Gaussians that the static stage starts from (seeded
    by SHB under the ideal optics), not the truth: the same start row, another data loss before
    the first update, and updates that still lower it."""
    monkeypatch.chdir(ROOT)
    truth_rows = jpgm_basin.recipe_run("figS7", paper=False, seed=0, steps=2)
    seed_rows = jpgm_basin.recipe_run("figS7", paper=False, seed=0, steps=2, held="seed")
    assert [row["volume"] for row in seed_rows] == ["seed", "seed"]
    assert seed_rows[0]["psf_error"] == pytest.approx(truth_rows[0]["psf_error"], rel=1e-6)
    truth_stage, seed_stage = truth_rows[1], seed_rows[1]
    assert abs(seed_stage["loss_before"] - truth_stage["loss_before"]) > 1e-3
    assert seed_stage["loss_after"] < seed_stage["loss_before"]
