#!/usr/bin/env bash
# On a machine with a CUDA GPU: the compiled Triton kernels' tests, then README's GPU rows of
# Table S7 (static step, dynamic frame-iteration, JPGM update) with a profile of the dynamic
# step. Results go to benchmarks/results/ (or $1). About four minutes on an H100.
set -euo pipefail
cd "$(dirname "$0")"
out="${1:-results}"
mkdir -p "$out"
python -m pytest -q -k gpu ../tests/unit/gaussians/test_voxelize_triton.py ../tests/unit/dynamics/test_hexplane_triton.py \
    ../tests/unit/dynamics/test_deformation_triton.py ../tests/unit/dynamics/test_regularizers_triton.py \
    ../tests/unit/optics/test_defocused_field_triton.py
python dynamic_step.py --repeats 20 --out "$out/dynamic_step.json"
python dynamic_step.py --profile 5 --out "$out/dynamic_step.json" > /dev/null
head -40 "$out/dynamic_step_profile.txt"
python static_step.py --repeats 10 --out "$out/static_step.json"
python jpgm_update.py --repeats 10 --out "$out/jpgm_update.json"
python engine_step.py --out "$out/engine_step.json"
python dynamic_step.py --repeats 20 --out "$out/dynamic_step_again.json"
