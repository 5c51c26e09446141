"""reproduce/fig5_cytometry.py end to end on a tiny mixture: one field of 8 cells (2 per class)
under the quick aberrations, 150 steps estimating the optics, 20 SHB iterations and 30 static
4DGAT steps per channel (under a minute on one core)."""

import dataclasses
import json

import numpy as np
import pandas as pd
import pytest

from fgat.app.recipes import fig5_cytometry as recipe

TINY = dict(
    n_fields=1,
    cells_per_field=8,
    shb_iterations=20,
    static_steps=30,
    n_gaussians=600,
    optics_steps=150,
    optics_gaussians=100,
    pipeline_fields=0,
)


pytestmark = pytest.mark.slow


def test_tiny_mixture_is_classified_like_the_truth(tmp_path):
    config = dataclasses.replace(recipe.QUICK, n_flow=2000, **TINY)
    summary = recipe.run(config, tmp_path, log=lambda message: None)
    names = ["phantom_cells.csv", "counts.csv", "summary.json", "fractions.png"]
    names += [f"cells_{method}.csv" for method in recipe.METHODS]
    names += [f"montage_{m}_{v}.png" for m in recipe.METHODS for v in ("xy", "xz")]
    for name in names:
        assert (tmp_path / name).stat().st_size > 0, name
    assert json.loads((tmp_path / "summary.json").read_text())["passed"] == summary["passed"]
    results = summary["methods"]
    # the noiseless phantom: every cell found once, in its class; fractions equal the truth's
    assert results["truth"]["accuracy"] == 1.0
    assert results["truth"]["false_detections"] == 0
    assert results["truth"]["chi2_p_truth"] == pytest.approx(1.0)
    # a short reconstruction from noisy views already gets (nearly) every cell right
    assert results["shb"]["accuracy"] >= 7 / 8
    assert results["4dgat"]["accuracy"] >= 7 / 8
    assert summary["truth_counts"] == {name: 2 for name in summary["truth_counts"]}
    assert sum(summary["flow_counts"].values()) == 2000
    # the self-estimated coefficients are closer to the truth than the ideal start (all zero)
    truth = recipe.flfm_true_zernike(config, range(5, 22))
    assert 0 < summary["zernike_rms_error_waves"] < 0.5 * np.sqrt(np.mean(truth**2))

    cells = pd.read_csv(tmp_path / "phantom_cells.csv")
    assert len(cells) == 8 and (cells["class"] == cells["class_truth"]).all()
    assert (cells["class"] == cells["class_4dgat"]).sum() >= 7
    counts = pd.read_csv(tmp_path / "counts.csv")
    assert len(counts) == 3 * 4 and set(counts["method"]) == set(recipe.METHODS)
    truth_rows = counts[counts["method"] == "truth"]
    assert (truth_rows["count"] == truth_rows["truth"]).all()
    assert counts["fisher_p_flow"].between(0, 1).all()
    assert "4DGAT cells classified correctly" in recipe.report(summary)


def test_a_field_through_the_pipeline_is_cached_on_its_data(tmp_path):
    """``fgat pipeline --channels all`` on a (T, C, H, W) field, tiny stages: every channel comes
    back as a volume, and a second call with the same data skips both stages of each channel."""
    config = dataclasses.replace(
        recipe.QUICK,
        optics_steps=20,
        n_gaussians=200,
        init_iterations=5,
        pipeline_frames=2,
        pipeline_dynamic_epochs=1,
        tracking_uri=f"sqlite:///{tmp_path / 'mlflow.db'}",
    )
    optics = recipe.flfm_optics(config)
    channels, _ = recipe.cell_phantom(
        optics["shape"],
        voxel_size_um=optics["voxel"],
        n_cells=4,
        seed=0,
        **{name: getattr(config, name) for name in recipe.PHANTOM},
    )
    first = recipe.pipeline_field(channels, 0, optics, config, tmp_path)
    assert list(first) == list(channels)
    for name, volume in first.items():
        assert volume.shape == optics["shape"] and np.isfinite(volume).all() and volume.max() > 0
    runs = tmp_path / "pipeline" / "field0" / "runs"
    stages = sorted(str(path.relative_to(runs)) for path in runs.glob("ch*/*"))
    assert stages == [f"ch{c}/{stage}" for c in range(3) for stage in ("dynamic", "static")]
    again = recipe.pipeline_field(channels, 0, optics, config, tmp_path)
    assert sorted(str(path.relative_to(runs)) for path in runs.glob("ch*/*")) == stages
    for name in channels:
        np.testing.assert_array_equal(again[name], first[name])
