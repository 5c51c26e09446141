#!/usr/bin/env bash
# The measured-data path end to end, on a realistic simulated measurement (37 lenslets, MLA
# rotated 0.4 deg, centres up to 2 px off the lattice, gains 0.7-1.0, camera offset, read noise,
# hot pixels, beads beyond the view borders): calibrate from a white-light and a dark image,
# deconvolve and fit Gaussians with the naive model (nominal centres, no gains, no hot-pixel
# mask, no guard band) and with the calibrated one, and score them (reproduce/realistic37.py).
# Run from the repository root; extra options go to both fits.
set -euo pipefail
source "$(dirname "$0")/steps.sh"
out=runs/realistic37
depths=-4:4:25
step python -m fgat simulate --config configs/simulate/realistic37.yaml --out $out/sim --overwrite
step python -m fgat calibrate --image $out/sim/flat.ome.tif --flat $out/sim/flat.ome.tif \
    --dark $out/sim/dark.ome.tif --system small37 --out $out/calib --overwrite
step python reproduce/realistic37.py nominal $out
step python -m fgat deconvolve --measurement $out/sim/sensor.ome.tif --system small37 \
    --depths-um=$depths --centers $out/nominal.csv --background 100 --guard-px 0 \
    --truth $out/sim/truth.ome.tif --out $out/shb_naive.ome.tif --overwrite
step python -m fgat deconvolve --measurement $out/sim/sensor.ome.tif --system small37 \
    --depths-um=$depths --calibration $out/calib \
    --truth $out/sim/truth.ome.tif --out $out/shb_calibrated.ome.tif --overwrite
step python -m fgat fit --config configs/base/common.yaml --config configs/measured.yaml "$@"
step python -m fgat fit --config configs/base/common.yaml --config configs/measured.yaml \
    --data.init_args.calibration=null --data.init_args.centers=$out/nominal.csv \
    --data.init_args.background=100 --data.init_args.guard_px=0 \
    --model.init_args.estimate_gains=false --trainer.default_root_dir=$out/fit_naive "$@"
step python reproduce/realistic37.py summary $out
