#!/usr/bin/env bash
# Fig. S9: RMS sweep of JPGM self-estimation. Every (RMS, seed) trial is one fit of the figS9
# config into one MLflow experiment (run name rms<R>-seed<S>); the summary then reads them back.
#   reproduce/figS9.sh              20x/0.45, 300 x 300 x 101, RMS 0.5 1.0 1.5 2.0 waves (GPU)
#   reproduce/figS9.sh --quick      small CPU optics, RMS 0.05 0.1 0.15 0.2 waves (the small
#                                   system samples the pupil 8x more coarsely, see
#                                   configs/figS9_quick.yaml)
# Environment: SEEDS (default "0 1 2 3 4"), MLFLOW_TRACKING_URI (default sqlite:///mlflow.db).
# A trial that already finished is not run again (delete its run to redo it).
set -euo pipefail
cd "$(dirname "$0")/.."
if [[ "${1:-}" == "--quick" ]]; then
  experiment=figS9_quick; levels="0.05 0.1 0.15 0.2"
else
  experiment=figS9; levels="0.5 1.0 1.5 2.0"
fi
export MLFLOW_TRACKING_URI="${MLFLOW_TRACKING_URI:-sqlite:///mlflow.db}"
seeds="${SEEDS:-0 1 2 3 4}"
for rms in $levels; do
  for seed in $seeds; do
    name="rms${rms}-seed${seed}"
    if python reproduce/figS9_summary.py --experiment "$experiment" --has-run "$name"; then
      echo "figS9: $name already finished, skipped"; continue
    fi
    python -m fgat fit --config "configs/${experiment}.yaml" --mlflow.experiment="$experiment" \
      --mlflow.run_name="$name" --seed_everything="$seed" --data.init_args.simulation.seed="$seed" \
      "--data.init_args.simulation.aberrations={terms: 17, rms: ${rms}, seed: ${seed}}" \
      --trainer.default_root_dir="runs/${experiment}/${name}"
  done
done
python reproduce/figS9_summary.py --experiment "$experiment"
