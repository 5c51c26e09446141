#!/usr/bin/env bash
# Everything fgat checks on a CUDA GPU, in one run of under 9 minutes on one H100, the most
# important first:
#   1. triton_tests     the compiled Triton kernels (voxelizer, HexPlane, deformation, plane
#                       regularisers, defocused field) against the PyTorch path: their `-k gpu`
#                       tests, which a CPU only ever runs in Triton's interpreter
#   2. static_step      Table S7: the static step (benchmarks/static_step.py)
#   3. dynamic_step     Table S7: the dynamic frame-iteration (benchmarks/dynamic_step.py)
#   4. jpgm_update      Table S7: one JPGM update (benchmarks/jpgm_update.py)
#   5. optics_trial     one paper-scale Fig. S7 joint trial, seed 3, as its recipe sets it
#                       (benchmarks/optics_trial.py --figure figS7 --seed 3)
#   6. engine_step      each engine's step as a fit runs it (benchmarks/engine_step.py)
#   7. dynamic_profile  torch.profiler's table of the Fig. 3a frame-iteration
#   8. crossinfo        Tables S2-S5 at the paper's scale, leakage and noisy refits included
#                       (reproduce/tablesS2_S5.py on configs/crossinfo_paper.yaml), with what
#                       time is left
#
# Usage:
#   benchmarks/gpu_checks.sh [OUT]              on a GPU; OUT defaults to benchmarks/results
#   benchmarks/gpu_checks.sh --dry-run [OUT]    the same commands at tiny sizes on the CPU (1-2
#                                               minutes; tests/recipes/test_gpu_checks.py)
#
# Each step runs under `timeout` with its own limit, never past the run's budget
# (GPU_CHECKS_BUDGET_S seconds from the start: 510 on a GPU, 600 in a dry run); a step that
# fails or runs out of time leaves the others running. Each step writes its own result into OUT
# as it ends (JSON, the profile's table, the tests' JUnit XML, the tables' folder), its output
# into OUT/gpu_checks_logs/STEP.log, and a line into OUT/gpu_checks_summary.tsv: the step, its
# status (ok, timeout, failed:RC, or skipped when the budget is spent), its seconds, its limit
# and its command. The exit status is 0 when every step is ok.
set -euo pipefail

dry_run=false
if [[ "${1:-}" == "--dry-run" ]]; then
    dry_run=true
    shift
fi
cd "$(dirname "$0")/.."  # the repository root: result files record `python benchmarks/...`
if $dry_run; then
    out="${1:-${TMPDIR:-/tmp}/gpu_checks_dry_run}"
    budget="${GPU_CHECKS_BUDGET_S:-600}"
    export CUDA_VISIBLE_DEVICES=""  # the CPU even on a GPU machine
    device=cpu
else
    out="${1:-benchmarks/results}"
    budget="${GPU_CHECKS_BUDGET_S:-510}"
    device=cuda
    if ! python -c "import sys, torch; sys.exit(not torch.cuda.is_available())"; then
        echo "gpu_checks.sh: no CUDA GPU here (gpu_checks.sh --dry-run runs on a CPU)" >&2
        exit 2
    fi
fi
mkdir -p "$out/gpu_checks_logs"
summary="$out/gpu_checks_summary.tsv"
printf 'step\tstatus\tseconds\tlimit_s\tcommand\n' > "$summary"
export PYTHONUNBUFFERED=1  # a step cut off by its timeout keeps all it printed in its log
deadline=$((SECONDS + budget))
failures=0

# run_step NAME LIMIT_S COMMAND...: run COMMAND for at most LIMIT_S seconds (less when less of the
# budget is left; skipped when under 10 s is), logged to gpu_checks_logs/NAME.log, then append
# its line to the summary.
run_step() {
    local name=$1 limit=$2 status rc start
    shift 2
    local left=$((deadline - SECONDS))
    ((limit <= left)) || limit=$left
    start=$SECONDS
    echo "== $name (at most ${limit} s): $*"
    if ((limit < 10)); then
        status=skipped
    elif timeout --kill-after=10 "$limit" "$@" 2>&1 | tee "$out/gpu_checks_logs/$name.log"; then
        status=ok
    else
        rc=$?
        if ((rc == 124 || rc == 137)); then status=timeout; else status="failed:$rc"; fi
    fi
    [[ $status == ok ]] || failures=$((failures + 1))
    printf '%s\t%s\t%s\t%s\t%s\n' "$name" "$status" $((SECONDS - start)) "$limit" "$*" >> "$summary"
    echo "== $name: $status in $((SECONDS - start)) s"
}

# tiny_crossinfo YAML: configs/crossinfo.yaml's scene shrunk to 32 x 32 x 7 voxels and 6 beads,
# with 2 noisy refits (seconds on a CPU).
tiny_crossinfo() {
    python - "$1" <<'EOF'
import sys

import yaml

config = yaml.safe_load(open("configs/crossinfo.yaml"))
config["scene"].update(depths_um="-4.5:4.5:7", view_size=32)
config["scene"]["phantom"].update(n_beads=6, min_spacing=4.0, margin=2.0)
config["refits"] = 2
with open(sys.argv[1], "w") as handle:
    yaml.safe_dump(config, handle, sort_keys=False)
EOF
}

triton_tests=(
    tests/unit/gaussians/test_voxelize_triton.py
    tests/unit/dynamics/test_hexplane_triton.py
    tests/unit/dynamics/test_deformation_triton.py
    tests/unit/dynamics/test_regularizers_triton.py
    tests/unit/optics/test_defocused_field_triton.py
)
if $dry_run; then
    # Tiny cases, one repeat, a short JPGM schedule; the `-k gpu` tests skip ("no CUDA").
    size=(--tiny --repeats 1)
    profile=(--tiny --profile 1)
    trial=(--quick --start 1 --every 1 --steps 2 --max-steps 3 --device "$device")
    crossinfo="$out/crossinfo_tiny.yaml"
    tiny_crossinfo "$crossinfo"
else
    size=(--repeats 10)
    profile=(--profile 5)
    trial=(--device "$device")  # the recipe's own scale and JPGM schedule
    crossinfo=configs/crossinfo_paper.yaml
fi

run_step triton_tests 150 python -m pytest -q -k gpu --junitxml "$out/triton_tests.xml" \
    "${triton_tests[@]}"
run_step static_step 60 python benchmarks/static_step.py "${size[@]}" --out "$out/static_step.json"
run_step dynamic_step 60 python benchmarks/dynamic_step.py "${size[@]}" \
    --out "$out/dynamic_step.json"
run_step jpgm_update 90 python benchmarks/jpgm_update.py "${size[@]}" --out "$out/jpgm_update.json"
run_step optics_trial 200 python benchmarks/optics_trial.py --figure figS7 --seed 3 "${trial[@]}" \
    --out "$out/optics_trial.json"
run_step engine_step 60 python benchmarks/engine_step.py "${size[@]}" --out "$out/engine_step.json"
run_step dynamic_profile 40 python benchmarks/dynamic_step.py "${profile[@]}" \
    --out "$out/dynamic_step.json"  # writes dynamic_step_profile.txt beside it
run_step crossinfo 3600 python reproduce/tablesS2_S5.py --config "$crossinfo" \
    --out "$out/tablesS2_S5" --overwrite --device "$device"

echo "== $SECONDS s in all; summary: $summary"
column -t -s $'\t' "$summary" 2> /dev/null || cat "$summary"
((failures == 0))
