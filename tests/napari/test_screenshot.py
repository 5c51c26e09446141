"""The napari page's screenshot, made by its script from a short quickstart fit: the results
folder opens through fgat's reader as three side-by-side volumes that the picture shows (not a
blank frame)."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("napari")
if not os.environ.get("DISPLAY"):  # pytest-xvfb sets it when Xvfb is installed (.ci/run)
    pytest.skip("no screen for Qt: install Xvfb and pytest-xvfb", allow_module_level=True)

from fgat.app.cli import main  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_a_quickstart_result_fills_three_panels(tmp_path):
    words = ["fit", "--config", str(ROOT / "configs/base/common.yaml")]
    words += ["--config", str(ROOT / "configs/quickstart.yaml"), "--trainer.max_steps=30"]
    words += [f"--trainer.default_root_dir={tmp_path}"]
    words += [f"--mlflow.tracking_uri=sqlite:///{tmp_path}/mlflow.db"]
    assert main(words) == 0
    (results,) = (tmp_path / "results").iterdir()
    script = ROOT / "docs" / "figures" / "napari_quickstart.py"
    out = tmp_path / "screenshot.png"
    done = subprocess.run(
        [sys.executable, str(script), "--results", str(results), "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    layers = done.stdout.split("layers ")[1]
    for name in ("reconstruction", "SHB baseline", "ground truth"):
        assert f"'{name} ({results.name[:8]})'" in layers, done.stdout
    import matplotlib.pyplot as plt

    image = plt.imread(out)  # RGBA floats in [0, 1]
    assert image.shape[:2] == (460, 1380)
    colour = image[..., :3]
    lit = np.abs(colour - colour[0, 0]).sum(axis=-1) > 0.15  # against the background
    assert 0.005 < lit.mean() < 0.8, lit.mean()
    panels = np.array_split(lit[60:], 3, axis=1)  # below the layer names and colour bars
    assert all(panel.mean() > 0.002 for panel in panels), [panel.mean() for panel in panels]
