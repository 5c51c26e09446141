#!/usr/bin/env bash
# Fig. S9: RMS sweep of JPGM self-estimation, then its summary (panels a-e, PNG + CSV).
#   reproduce/figS9.sh              20x/0.45, 300 x 300 x 101, RMS 0.5 1.0 1.5 2.0 waves x seeds 0-4 (GPU;
#                                   configs/base/common.yaml, base/paper.yaml, base/optics_paper.yaml,
#                                   figS9.yaml)
#   reproduce/figS9.sh --quick      small CPU optics, RMS 0.05 0.1 0.15 0.2 waves x seeds 0-4 (the
#                                   small system samples its pupil 8x more coarsely; configs/base/
#                                   common.yaml, base/optics_quick.yaml, figS9.yaml, figS9_quick.yaml)
# Further options (--seeds, --levels, --tracking-uri; --parallel N or --address to run the trials
# at once on Ray): python reproduce/figS9.py --help; other options (--trainer.accelerator=gpu)
# are passed to every fit. Ctrl-C or SIGTERM stops the sweep (exit code 130 or 143, the trial
# under way KILLED in MLflow, no further trial started); finished trials are skipped, so the
# same command resumes where it stopped.
set -euo pipefail
cd "$(dirname "$0")/.."
# exec: the recipe replaces this shell, so a signal sent to it (kill, scancel) reaches the
# trials and the exit code is the recipe's (130 or 143 when stopped by SIGINT or SIGTERM)
exec python reproduce/figS9.py "$@"
