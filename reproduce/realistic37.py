"""The realistic-measurement evidence: what calibration recovers and what the acquisition model
buys, on the 37-lenslet simulation of configs/simulate/realistic37.yaml.

``python reproduce/realistic37.py nominal OUT`` writes ``OUT/nominal.csv``, the system's nominal
(unrotated, on-lattice) centres a user without a calibration would give; ``python
reproduce/realistic37.py summary OUT`` compares the calibration in ``OUT/calib`` with the truth in
``OUT/sim`` (centres, gains, camera) and scores every volume of the recipe against the truth
(PSNR, SSIM, and the border frame: :func:`fgat.recon.metrics.border_ratio`, 1 = none), printing a
table and writing ``OUT/summary.json``. ``reproduce/realistic37.sh`` runs the whole recipe.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import yaml

from fgat.instrument.calibration import read_calibration
from fgat.instrument.centres import read_centers, write_centers
from fgat.io.images import read_tiff
from fgat.optics.systems import load_system
from fgat.recon.metrics import border_ratio, compare_volumes

# Volume file of each reconstruction (relative to OUT) and its label.
VOLUMES = {
    "shb_naive.ome.tif": "SHB, naive model",
    "shb_calibrated.ome.tif": "SHB, calibrated model",
    "fit_naive/results/*/volume.ome.tif": "Gaussians, naive model",
    "fit/results/*/volume.ome.tif": "Gaussians, calibrated model",
}


def calibration_errors(out: Path) -> dict[str, float]:
    """Centre, gain and camera errors of ``OUT/calib`` against the simulation's truth."""
    calibration = read_calibration(out / "calib")
    truth_centers = read_centers(out / "sim" / "centers.csv")
    imperfections = yaml.safe_load((out / "sim" / "params.yaml").read_text())["imperfections"]
    gains = np.asarray(imperfections["gains"], dtype=float)
    relative = calibration.gains / calibration.gains.max() / (gains / gains.max())
    hot = {tuple(p) for p in np.argwhere(calibration.camera.hot_pixels)}
    true_hot = {
        tuple(map(int, line.split(",")[:2]))
        for line in (out / "sim" / "hot_pixels.csv").read_text().splitlines()[1:]
    }
    return {
        "centre_error_max_px": float(np.hypot(*(calibration.centers - truth_centers).T).max()),
        "gain_error_max": float(np.abs(relative - 1).max()),
        "offset_counts": calibration.camera.offset,
        "read_noise_counts": calibration.camera.read_noise,
        "hot_pixels_found": len(hot & true_hot),
        "hot_pixels_true": len(true_hot),
        "hot_pixels_false": len(hot - true_hot),
    }


def volume_scores(out: Path) -> dict[str, dict[str, float]]:
    """PSNR, SSIM and border ratio of every reconstruction of the recipe that exists."""
    truth = read_tiff(out / "sim" / "truth.ome.tif")
    scores = {}
    for pattern, label in VOLUMES.items():
        found = sorted(out.glob(pattern), key=lambda path: path.stat().st_mtime)
        if found:  # the newest run's
            volume = read_tiff(found[-1])
            result = compare_volumes(volume, truth)
            scores[label] = {
                "psnr": result["psnr"],
                "ssim": result["ssim"],
                "psnr_xy": result["psnr_xy"],
                "border_ratio": border_ratio(volume, truth),
            }
    return scores


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("action", choices=("nominal", "summary"))
    parser.add_argument("out", type=Path, help="the recipe's folder (runs/realistic37)")
    args = parser.parse_args()
    if args.action == "nominal":
        write_centers(args.out / "nominal.csv", load_system("small37").lenslet_centers_px())
        return
    summary = {"calibration": calibration_errors(args.out), "volumes": volume_scores(args.out)}
    for key, value in summary["calibration"].items():
        print(f"{key:22s} {value:.4g}")
    print(f"{'volume':30s} {'PSNR dB':>8s} {'SSIM':>7s} {'x-y MIP dB':>10s} {'border':>7s}")
    for label, row in summary["volumes"].items():
        print(
            f"{label:30s} {row['psnr']:8.2f} {row['ssim']:7.4f} {row['psnr_xy']:10.2f} "
            f"{row['border_ratio']:7.3f}"
        )
    (args.out / "summary.json").write_text(json.dumps(summary, indent=2))
    print(f"-> {args.out / 'summary.json'}")


if __name__ == "__main__":
    main()
