#!/usr/bin/env bash
# Fig. S9: RMS sweep of JPGM self-estimation, then its summary (panels a-e, PNG + CSV).
#   reproduce/figS9.sh              20x/0.45, 300 x 300 x 101, RMS 0.5 1.0 1.5 2.0 waves x seeds 0-4 (GPU;
#                                   configs/base/common.yaml, base/paper.yaml, base/optics_paper.yaml,
#                                   figS9.yaml)
#   reproduce/figS9.sh --quick      small CPU optics, RMS 0.05 0.1 0.15 0.2 waves x seeds 0-4 (the
#                                   small system samples its pupil 8x more coarsely; configs/base/
#                                   common.yaml, base/optics_quick.yaml, figS9.yaml, figS9_quick.yaml)
# Further options (--seeds, --levels, --tracking-uri; --parallel N or --address to run the trials
# at once on Ray): python reproduce/figS9.py --help.
# Finished trials are skipped, so a killed sweep resumes where it stopped.
set -euo pipefail
cd "$(dirname "$0")/.."
python reproduce/figS9.py "$@"
