"""A foreign FLFM image end to end: the 3DGAT reticular sensor image, whose PSF fgat does not know.

``python reproduce/reticular_lfimage.py prepare OUT`` bins ``LFimage.tif`` (1600 x 1600) 4 x 4
into ``OUT/lfimage_4x.ome.tif`` (400 x 400, summed counts), averages ``data.tif`` (200^3) over
4 x 4 x 4 blocks into the truth ``OUT/truth.ome.tif`` (50^3, the 3DGAT code's Z order), and
writes the image's own centre file (``MLcenter_idxes.mat``: 1-based whole pixels, its own view
order) on the binned grid in fgat's view order as ``OUT/reference_centers.csv``.

``python reproduce/reticular_lfimage.py summary OUT`` compares the centres that ``fgat
calibrate`` found on the image with that file (as they are, and without the scene gauge that
no fluorescence image fixes: :func:`fgat.recon.estimation.remove_scene_gauge`), and scores SHB,
3DGAT (Gaussians, optics fixed) and 4DGAT (Gaussians, optics self-estimated) against the truth,
as they are and after the whole-voxel shift that best aligns them
(:func:`fgat.recon.metrics.align_to_truth`, the same gauge in the volume), printing a table and
writing ``OUT/summary.json``. ``reproduce/reticular_lfimage.sh`` runs the whole recipe.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from fgat.instrument.centres import read_centers, write_centers
from fgat.io.images import read_mat, read_tiff, write_tiff
from fgat.optics.lenslets import sort_lenslet_centers
from fgat.recon.estimation import remove_scene_gauge
from fgat.recon.metrics import align_to_truth, compare_volumes

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "reticular1"
BIN = 4  # binning of the sensor image and of the truth volume
VOLUMES = {
    "shb.ome.tif": "SHB",
    "fit_3dgat/results/*/volume.ome.tif": "3DGAT (optics fixed)",
    "fit_4dgat/results/*/volume.ome.tif": "4DGAT (optics estimated)",
}


def binned_position(full_res: np.ndarray) -> np.ndarray:
    """Position on the binned grid of 0-based full-resolution pixel coordinates: binned pixel
    ``i`` covers full pixels ``BIN i .. BIN i + BIN - 1``, centred at ``BIN i + (BIN - 1) / 2``."""
    return (np.asarray(full_res, dtype=np.float64) - (BIN - 1) / 2.0) / BIN


def prepare(out: Path, data: Path) -> None:
    """Write the binned image, the binned truth and the reference centres into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    image = read_tiff(data / "LFimage.tif", ndim=2).astype(np.float64)
    h, w = (s // BIN for s in image.shape)
    binned = image[: h * BIN, : w * BIN].reshape(h, BIN, w, BIN).sum(axis=(1, 3))
    write_tiff(out / "lfimage_4x.ome.tif", binned.astype(np.float32), axes="YX")
    truth = read_tiff(data / "data.tif", ndim=3).astype(np.float64)
    z, y, x = (s // BIN for s in truth.shape)
    truth = truth[: z * BIN, : y * BIN, : x * BIN].reshape(z, BIN, y, BIN, x, BIN)
    write_tiff(out / "truth.ome.tif", truth.mean(axis=(1, 3, 5)).astype(np.float32), axes="ZYX")
    reference = binned_position(read_mat(data / "MLcenter_idxes.mat") - 1.0)
    write_centers(out / "reference_centers.csv", sort_lenslet_centers(reference))
    print(f"-> {out}: image {binned.shape}, truth {(z, y, x)}, reference_centers.csv")


def centre_errors(out: Path) -> dict[str, float]:
    """Largest distance (binned pixels) of the calibrated centres from the reference file's,
    as they are and without the scene gauge (a common shift and a radial scale)."""
    found = read_centers(out / "calib" / "centers.csv")
    reference = read_centers(out / "reference_centers.csv")
    difference = torch.from_numpy(found - reference)
    residual = remove_scene_gauge(difference, torch.from_numpy(reference - reference[:1]))
    return {
        "centre_offset_max_px": float(np.hypot(*(found - reference).T).max()),
        "centre_residual_max_px": float(torch.linalg.norm(residual, dim=1).max()),
    }


def volume_scores(out: Path) -> dict[str, dict[str, float]]:
    """PSNR and SSIM of every reconstruction of the recipe that exists (the newest run's), as it
    is and aligned to the truth by a whole-voxel shift."""
    truth = read_tiff(out / "truth.ome.tif")
    scores = {}
    for pattern, label in VOLUMES.items():
        found = sorted(out.glob(pattern), key=lambda path: path.stat().st_mtime)
        if found:
            volume = read_tiff(found[-1])
            aligned, shift = align_to_truth(volume, truth)
            raw, best = compare_volumes(volume, truth), compare_volumes(aligned, truth)
            scores[label] = {
                "psnr": raw["psnr"],
                "ssim": raw["ssim"],
                "psnr_aligned": best["psnr"],
                "ssim_aligned": best["ssim"],
                "shift_zyx": list(shift),
            }
    return scores


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("action", choices=("prepare", "summary"))
    parser.add_argument("out", type=Path, help="the recipe's folder (runs/reticular_lfimage)")
    parser.add_argument("--data", type=Path, default=DATA, help="the reticular1 folder")
    args = parser.parse_args()
    if args.action == "prepare":
        prepare(args.out, args.data)
        return
    summary = {"centres": centre_errors(args.out), "volumes": volume_scores(args.out)}
    for key, value in summary["centres"].items():
        print(f"{key:24s} {value:.3f}")
    print(f"{'volume':26s} {'PSNR dB':>8s} {'SSIM':>7s} {'aligned dB':>10s} {'SSIM':>7s}  shift")
    for label, row in summary["volumes"].items():
        print(
            f"{label:26s} {row['psnr']:8.2f} {row['ssim']:7.4f} {row['psnr_aligned']:10.2f} "
            f"{row['ssim_aligned']:7.4f}  {tuple(row['shift_zyx'])}"
        )
    (args.out / "summary.json").write_text(json.dumps(summary, indent=2))
    print(f"-> {args.out / 'summary.json'}")


if __name__ == "__main__":
    main()
