"""The napari page's screenshot: the quickstart's results folder opened in napari through
fgat's reader (the Gaussians' volume, the SHB baseline and, on this phantom, the truth as
aligned layers in micrometres), side by side in napari's grid as x-y maximum-intensity
projections with their colour bars and a scale bar.

It runs the quickstart as a user does (``python -m fgat fit --config configs/base/common.yaml
--config configs/quickstart.yaml``, logging into a temporary folder) unless ``--results`` names
a finished one. Needs the napari extra (``pip install -e ".[napari]"``) and a screen (or
``xvfb-run``). Run from the repository root::

    python docs/figures/napari_quickstart.py [--results RUNS/quickstart/results/<run id>]
        [--out docs/images/napari_quickstart.png]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

CONFIGS = ("configs/base/common.yaml", "configs/quickstart.yaml")


def results_screenshot(viewer, results: Path, size: tuple[int, int] = (460, 1380)) -> np.ndarray:
    """Open the results folder ``results`` in ``viewer`` through fgat's reader, lay its layers
    side by side (napari's grid), each drawn in 3D as a maximum-intensity projection seen along
    z (an x-y MIP) with its name, colour bar and a scale bar in um, and return the canvas as
    RGBA ``(H, W, 4)`` uint8 of ``size`` (height, width) pixels."""
    layers = viewer.open(str(results), plugin="fgat")
    if not layers:
        raise SystemExit(f"{results}: fgat's reader opened no layer")
    grid = viewer.canvas.grid if hasattr(viewer, "canvas") else viewer.grid  # napari 0.9 moved it
    grid.enabled, grid.stride, grid.shape = True, 1, (1, len(layers))
    viewer.dims.ndisplay = 3
    viewer.camera.angles = (0, 0, 90)  # looking down the z axis
    for layer in layers:
        layer.name_overlay.visible = True
        layer.colorbar.visible = True
    viewer.scale_bar.visible = True
    viewer.reset_view()
    return viewer.screenshot(canvas_only=True, size=size, flash=False)


def quickstart(work: Path) -> Path:
    """Run the quickstart into ``work``; its results folder."""
    options = [option for path in CONFIGS for option in ("--config", path)]
    options += [f"--trainer.default_root_dir={work}", f"--mlflow.tracking_uri=sqlite:///{work}/db"]
    done = subprocess.run([sys.executable, "-m", "fgat", "fit", *options], text=True)
    if done.returncode != 0:
        raise SystemExit("the quickstart failed")
    (results,) = (work / "results").iterdir()
    return results


def main(argv: list[str] | None = None) -> None:
    import napari  # the extra: loaded when the figure is made

    options = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    options.add_argument("--results", type=Path, help="a finished quickstart's results folder")
    options.add_argument("--out", type=Path, default=Path("docs/images/napari_quickstart.png"))
    args = options.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="fgat-figure-") as work:
        results = args.results or quickstart(Path(work))
        viewer = napari.Viewer()  # shown: a hidden canvas is not drawn
        try:
            image = results_screenshot(viewer, results)
            names = [layer.name for layer in viewer.layers]
        finally:
            viewer.close()
    import matplotlib.pyplot as plt

    from fgat.io.files import atomic_path

    with atomic_path(args.out) as temporary:
        plt.imsave(temporary, image, format="png")
    print(f"screenshot {image.shape[1]} x {image.shape[0]}: layers {names} -> {args.out}")


if __name__ == "__main__":
    main()
