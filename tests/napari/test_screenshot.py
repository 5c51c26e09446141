"""The napari page's screenshot, taken from a short quickstart fit: the results folder opens
through fgat's reader as side-by-side volumes that the canvas shows (not a blank frame)."""

import importlib.util
import os
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("napari")
pytest.importorskip("pytestqt")
if not os.environ.get("DISPLAY"):  # pytest-xvfb sets it when Xvfb is installed (.ci/run)
    pytest.skip("no screen for Qt: install Xvfb and pytest-xvfb", allow_module_level=True)

from fgat.app.cli import main  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]


def figure_script():
    """docs/figures/napari_quickstart.py, which makes the docs' screenshot."""
    path = ROOT / "docs" / "figures" / "napari_quickstart.py"
    spec = importlib.util.spec_from_file_location("napari_quickstart", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
def test_a_quickstart_result_fills_the_canvas_side_by_side(make_napari_viewer, tmp_path):
    words = ["fit", "--config", str(ROOT / "configs/base/common.yaml")]
    words += ["--config", str(ROOT / "configs/quickstart.yaml"), "--trainer.max_steps=30"]
    words += [f"--trainer.default_root_dir={tmp_path}"]
    words += [f"--mlflow.tracking_uri=sqlite:///{tmp_path}/mlflow.db"]
    assert main(words) == 0
    (results,) = (tmp_path / "results").iterdir()
    viewer = make_napari_viewer(show=True)  # a hidden canvas is not drawn
    image = figure_script().results_screenshot(viewer, results)
    names = [layer.name.split(" (")[0] for layer in viewer.layers]
    assert names == ["reconstruction", "SHB baseline", "ground truth"], names
    assert image.ndim == 3 and image.shape[0] >= 200 and image.shape[1] >= 300
    colour = image[..., :3].astype(np.int32)
    lit = np.abs(colour - colour[0, 0]).sum(axis=-1) > 40  # against the background
    assert 0.005 < lit.mean() < 0.8, lit.mean()
    panels = np.array_split(lit, 3, axis=1)
    assert all(panel.mean() > 0.002 for panel in panels), [panel.mean() for panel in panels]
