"""reproduce/fig5_tracking.py end to end on a tiny phantom: one field of 12 cells (2 driven),
15 frames, 20 SHB iterations per frame (a few seconds on one core)."""

import dataclasses
import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd

RECIPE = Path(__file__).resolve().parents[1] / "reproduce" / "fig5_tracking.py"


def load_recipe():
    spec = importlib.util.spec_from_file_location("fig5_tracking", RECIPE)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def test_tiny_phantom_is_tracked_and_classified(tmp_path):
    recipe = load_recipe()
    config = dataclasses.replace(
        recipe.QUICK, n_fields=1, n_frames=15, iterations=20, min_track_frames=10, seed=0
    )
    summary = recipe.run(config, tmp_path, log=lambda message: None)
    for name in (
        "trajectories.csv",
        "truth_trajectories.csv",
        "cells.csv",
        "summary.json",
        "speed_histogram.png",
        "msd_curves.png",
        "trajectories.png",
    ):
        assert (tmp_path / name).stat().st_size > 0, name
    assert json.loads((tmp_path / "summary.json").read_text())["fraction_right"] == 1.0
    cells = pd.read_csv(tmp_path / "cells.csv")
    assert len(cells) == 12 and (cells["class_true"] == "driven").sum() == 2
    # drift 15 um/s against free cells of about 2 um/s: every class found is the true one
    assert (cells["class_found"] == cells["class_true"]).all()
    assert (cells["match_um"] < 1.0).all()
    assert summary["threshold_relative_error"] < 0.15
    free = cells[cells["class_true"] == "free"]
    np.testing.assert_allclose(free["mean_speed_um_s"], free["mean_speed_true_um_s"], rtol=0.15)
    assert "alpha free" in recipe.report(summary)
