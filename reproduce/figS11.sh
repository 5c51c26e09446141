#!/usr/bin/env bash
# Fig. S11: RL vs SHB deconvolution on line-sphere and bead phantoms.
#   reproduce/figS11.sh            the 20x/0.45 system at 101 x 300 x 300 (GPU recommended)
#   reproduce/figS11.sh --quick    the small CPU system, a few minutes on a laptop
set -euo pipefail
cd "$(dirname "$0")/.."
# exec: the recipe replaces this shell, so a signal sent to it reaches it and the exit code
# is the recipe's
exec python reproduce/figS11.py "$@"
