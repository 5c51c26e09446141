"""The README's results figure: x-y maximum-intensity projections (MIPs) of the quickstart's
truth, its SHB reconstruction and its Gaussians, side by side.

It runs the quickstart as a user does (``python -m fgat fit --config configs/base/common.yaml
--config configs/quickstart.yaml``, logging into a temporary folder), simulates the same scene
with ``python -m fgat simulate`` to get its truth (the ``data.init_args.simulation`` settings
and the seed of the two config files), and draws the three volumes, each divided by its own
maximum, with their volume PSNR against the truth (``fgat.metrics.psnr``, ``data_range`` 1).
Run from the repository root (about a minute on a 2-core CPU)::

    python docs/figures/quickstart_mips.py [--results RUNS/quickstart/results/<run id>]
        [--out docs/images/quickstart_mips.png]

``--results`` reuses the ``volume.ome.tif`` and ``shb.ome.tif`` of a finished quickstart
instead of running it.
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import tifffile
import yaml

ROOT = Path(__file__).resolve().parents[2]

CONFIGS = ("configs/base/common.yaml", "configs/quickstart.yaml")
SIMULATION = "data.init_args.simulation."


def simulation_settings(configs: tuple[str, ...]) -> dict:
    """The ``fgat simulate`` config of the recipe's scene: its dotted
    ``data.init_args.simulation.*`` keys, later files winning, and its ``seed_everything``."""
    settings: dict = {}
    for path in configs:
        recipe = yaml.safe_load(Path(path).read_text()) or {}
        for key, value in recipe.items():
            if key.startswith(SIMULATION):
                settings[key[len(SIMULATION) :]] = value
            elif key == "seed_everything":
                settings["seed"] = value
    return settings


def fgat(*arguments: str) -> str:
    """Run ``python -m fgat ARGUMENTS`` and return its standard output; stop on failure."""
    done = subprocess.run(
        [sys.executable, "-m", "fgat", *arguments], capture_output=True, text=True
    )
    if done.returncode != 0:
        raise SystemExit(f"fgat {arguments[0]} failed:\n{done.stderr[-2000:]}")
    return done.stdout


def voxel_size_um(path: Path) -> tuple[float, float]:
    """(dy, dx) in um from an OME-TIFF's ``PhysicalSizeY`` and ``PhysicalSizeX``."""
    with tifffile.TiffFile(path) as tiff:
        ome = tiff.ome_metadata or ""
    sizes = dict(re.findall(r'PhysicalSize([XY])="([0-9.eE+-]+)"', ome))
    if set(sizes) != {"X", "Y"}:
        raise SystemExit(f"{path}: no PhysicalSizeX/Y in its OME metadata")
    return float(sizes["Y"]), float(sizes["X"])


def normalized(volume: np.ndarray) -> np.ndarray:
    """``volume`` clipped at zero and divided by its maximum, as fgat scores volumes."""
    volume = np.clip(volume.astype(np.float64), 0.0, None)
    return volume / max(float(volume.max()), np.finfo(np.float64).tiny)


def draw(truth: Path, shb: Path, gaussians: Path, out: Path) -> None:
    """Three x-y MIPs in um with one colour bar, PSNR against the truth in the titles."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from fgat.metrics import psnr

    dy, dx = voxel_size_um(truth)
    reference = normalized(tifffile.imread(truth))
    panels = [("truth", reference)]
    for name, path in (("SHB, 50 iterations", shb), ("Gaussians (3DGAT), 500 steps", gaussians)):
        volume = normalized(tifffile.imread(path))
        if volume.shape != reference.shape:
            raise SystemExit(
                f"{path}: shape {volume.shape}, expected the truth's {reference.shape}"
            )
        panels.append(
            (f"{name}\n{psnr(volume, reference, data_range=1.0):.1f} dB volume PSNR", volume)
        )
    height, width = reference.shape[1] * dy, reference.shape[2] * dx
    figure, axes = plt.subplots(1, 3, figsize=(11, 4.2), constrained_layout=True)
    for axis, (title, volume) in zip(axes, panels):
        image = axis.imshow(
            volume.max(axis=0), cmap="magma", vmin=0, vmax=1, extent=(0, width, height, 0)
        )
        axis.set_title(title, fontsize=10)
        axis.set_xlabel("x (um)")
    axes[0].set_ylabel("y (um)")
    figure.colorbar(image, ax=axes, shrink=0.85, label="intensity / volume maximum")
    figure.suptitle("Quickstart scene: x-y maximum-intensity projections", fontsize=11)
    out.parent.mkdir(parents=True, exist_ok=True)
    temporary = out.with_name(f".{out.name}.tmp.png")
    figure.savefig(temporary, dpi=110)
    temporary.replace(out)
    print(f"figure -> {out}")


def main(argv: list[str] | None = None) -> None:
    options = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    options.add_argument("--results", type=Path, help="a finished quickstart's results folder")
    options.add_argument("--out", type=Path, default=Path("docs/images/quickstart_mips.png"))
    args = options.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="fgat-figure-") as work:
        work = Path(work)
        (work / "simulation.yaml").write_text(yaml.safe_dump(simulation_settings(CONFIGS)))
        fgat("simulate", "--config", str(work / "simulation.yaml"), "--out", str(work / "sim"))
        results = args.results
        if results is None:
            config_options = [option for path in CONFIGS for option in ("--config", path)]
            fgat(
                "fit",
                *config_options,
                f"--trainer.default_root_dir={work / 'runs'}",
                f"--mlflow.tracking_uri=sqlite:///{work / 'mlflow.db'}",
                "--trainer.enable_progress_bar=false",
            )
            (results,) = (work / "runs" / "results").iterdir()
        draw(
            work / "sim" / "truth.ome.tif",
            results / "shb.ome.tif",
            results / "volume.ome.tif",
            args.out,
        )


if __name__ == "__main__":
    main()
