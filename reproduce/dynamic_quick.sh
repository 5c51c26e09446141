#!/usr/bin/env bash
# Quick dynamic recipe on CPU: static then dynamic stage on the beating-shell phantom
# (configs/base/common.yaml and configs/dynamic_quick.yaml, configs/dynamic_quick_static.yaml laid
# over them for the static stage), then Fig. S12 (kymographs and PSNR of frames, cubic
# interpolation and 4DGAT at 10x the frame rate) into reproduce/results/figS12.
# A stage that finished with the same configuration is skipped and a killed one resumes, so the
# script can be re-run; a changed one runs beside the first (see python -m fgat pipeline --help).
# Extra options go to both stages, e.g. reproduce/dynamic_quick.sh --trainer.accelerator=cpu
set -euo pipefail
cd "$(dirname "$0")/.."
# exec: the recipe replaces this shell, so a signal sent to it (kill, scancel) reaches the
# pipeline and the exit code is the recipe's (130 or 143 when stopped by SIGINT or SIGTERM)
exec python reproduce/figS12.py --config configs/base/common.yaml --config configs/dynamic_quick.yaml \
    --static configs/dynamic_quick_static.yaml --dynamic configs/dynamic_quick_dynamic.yaml "$@"
