#!/usr/bin/env bash
# A sensor image fgat did not make: the 3DGAT reticular FLFM image (../shared/data/reticular1,
# simulated by another group's code with a PSF that is not public), binned 4 x 4. Calibrate the
# lenslet centres on the image itself, then reconstruct through a guessed system
# (reproduce/systems/reticular_3dgat.yaml) with SHB, with Gaussians on the fixed optics (3DGAT) and
# with Gaussians whose optics are self-estimated (4DGAT), and score them against the truth
# (reproduce/reticular_lfimage.py). The truth's Z runs the other way from fgat's: --depth-axis
# down. Run from the repository root (about 15 min on 2 cores); extra options go to both fits.
set -euo pipefail
source "$(dirname "$0")/steps.sh"
out=runs/reticular_lfimage
step python reproduce/reticular_lfimage.py prepare $out
step python -m fgat calibrate --image $out/lfimage_4x.ome.tif --system reproduce/systems/reticular_3dgat.yaml \
    --depth-axis down --out $out/calib --overwrite
step python -m fgat deconvolve --measurement $out/lfimage_4x.ome.tif \
    --system reproduce/systems/reticular_3dgat.yaml --depths-um=-30.625:30.625:50 \
    --calibration $out/calib --truth $out/truth.ome.tif --out $out/shb.ome.tif --overwrite
step python -m fgat fit --config configs/base/common.yaml --config configs/reticular_lfimage.yaml \
    --model.init_args.optics.estimate=none --trainer.default_root_dir=$out/fit_3dgat "$@"
step python -m fgat fit --config configs/base/common.yaml --config configs/reticular_lfimage.yaml "$@"
step python reproduce/reticular_lfimage.py summary $out
