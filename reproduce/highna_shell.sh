#!/usr/bin/env bash
# The high-NA case end to end (reproduce/highna_shell.py): a hollow microsphere 15 um across with
# beads around it, some beyond the views' field, seen through 37 hexagonal lenslets of a
# 60x/1.3 silicone objective imaging into water (configs/simulate/highna_shell.yaml,
# reproduce/systems/highna37.yaml). Simulate, calibrate from the white-light and dark images,
# check that a calibration with the MLA pitch given in the wrong convention (corner to corner)
# is refused, deconvolve (SHB; and with the system's sample index left out, depths taken in
# the immersion oil), fit Gaussians with the optics fixed (3DGAT) and estimated
# (4DGAT), and score every volume: PSNR, SSIM, border frame, empty or not, and the shell's
# axial/lateral aspect against the truth's. Run from the repository root; extra options go to
# both fits (e.g. --trainer.max_steps=300). The script exits non-zero at the end when the
# wrong-convention calibration was accepted. HIGHNA_OUT (the folder, default runs/highna_shell),
# HIGHNA_CONFIG (the simulation) and HIGHNA_DEPTHS (its depths_um) run it on another simulation
# of the same system.
set -euo pipefail
source "$(dirname "$0")/steps.sh"
out=${HIGHNA_OUT:-runs/highna_shell}
config=${HIGHNA_CONFIG:-configs/simulate/highna_shell.yaml}
depths=${HIGHNA_DEPTHS:--9:9:37}
system=reproduce/systems/highna37.yaml
fit=(python -m fgat fit --config configs/base/common.yaml --config configs/measured.yaml
    --config configs/highna_shell.yaml --data.init_args.measurement=$out/sim/sensor.ome.tif
    --data.init_args.calibration=$out/calib --data.init_args.truth=$out/sim/truth.ome.tif
    --data.init_args.depths_um=$depths)
step python -m fgat simulate --config $config --out $out/sim --overwrite
calibrate=(python -m fgat calibrate --image $out/sim/flat.ome.tif --flat $out/sim/flat.ome.tif
    --dark $out/sim/dark.ome.tif --overwrite)
step "${calibrate[@]}" --system $system --out $out/calib
step python reproduce/highna_shell.py systems $out
if step "${calibrate[@]}" --system $out/wrong_pitch.yaml --out $out/calib_wrong_pitch; then
    echo accepted > $out/wrong_pitch.txt
else
    echo refused > $out/wrong_pitch.txt
fi
step python -m fgat deconvolve --measurement $out/sim/sensor.ome.tif --system $system \
    --depths-um=$depths --calibration $out/calib \
    --truth $out/sim/truth.ome.tif --out $out/shb.ome.tif --overwrite
step python -m fgat deconvolve --measurement $out/sim/sensor.ome.tif --system $out/immersion_depths.yaml \
    --depths-um=$depths --calibration $out/calib \
    --truth $out/sim/truth.ome.tif --out $out/shb_immersion_depths.ome.tif --overwrite
step "${fit[@]}" --trainer.default_root_dir=$out/fit_3dgat "$@"
step "${fit[@]}" --trainer.default_root_dir=$out/fit_4dgat --model.init_args.optics.estimate=joint "$@"
step python reproduce/highna_shell.py summary $out
if [ "$(cat $out/wrong_pitch.txt)" != refused ]; then
    echo "error: calibrate accepted the system with the MLA pitch given corner to corner" >&2
    exit 1
fi
