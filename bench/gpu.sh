#!/usr/bin/env bash
# The GPU checks: the CUDA tests, the fused rollout kernel alone, then `bench/gpu_table.py` (planning at 1, 64 and 256 environments, eager,
# compiled + CUDA graphs and the paper's procedure as reference; EM training at the default and
# the paper's sizes), printed as one table with its targets (docs/performance.md).
#
# On any Linux machine with a CUDA GPU, from the repository's root, with the project installed
# (`uv sync`; PYTHON names its interpreter, e.g. PYTHON=.venv/bin/python):
#   bash bench/gpu.sh
# It times the trained default model (`oposm segment` and `oposm train` first, or DATA= a folder
# holding models/pointmaze-medium and segments/pointmaze-medium; LLP is timed only if its models
# are there too). On a node without network access that has torch and CUDA but not the rest of
# the dependencies: `bash bench/gpu_wheels.sh` on a machine with network fetches them as wheels
# into .whl/, and bench/gpu_env.sh installs them from there.
# Results land in OUT (default /tmp/oposm-gpu): gpu.json (written after every section),
# tests.log, kernel.json, bench.log, table.txt.
#
# Dry run of the plumbing without a GPU (no compile, tiny sizes):
#   python bench/gpu_table.py --device cpu --envs 4 --no-compile --no-triton --train-steps 3
set -uo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
OUT=${OUT:-/tmp/oposm-gpu}
DATA=${DATA:-data}  # where the trained model and segments are
mkdir -p "$OUT"
source bench/gpu_env.sh  # the wheels in .whl/, if any; PYTHONPATH
"$PY" -c "import torch, sys; sys.exit(not torch.cuda.is_available())" || {
    echo "no CUDA GPU visible to $PY"; exit 1; }
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee "$OUT/gpu.txt"

echo "== CUDA tests"
# GPU_TESTS_K: a pytest -k filter (e.g. "training"); GPU_TABLE_ARGS: gpu_table.py arguments;
# GPU_BENCH_TIMEOUT: seconds the benchmarks may take (330); each section is bounded so that a
# hung kernel cannot stall the others.
timeout 150 "$PY" -m pytest -q -ra -m gpu tests/test_gpu.py ${GPU_TESTS_K:+-k "$GPU_TESTS_K"} 2>&1 |
    tee "$OUT/tests.log"
tests=${PIPESTATUS[0]}

echo "== the fused rollout kernel alone (bench/gpu_kernel.py)"
timeout "${GPU_KERNEL_TIMEOUT:-150}" "$PY" bench/gpu_kernel.py --data "$DATA" --out "$OUT/kernel.json" 2>"$OUT/kernel.log" |
    tee "$OUT/kernel.txt"
kernel=${PIPESTATUS[0]}
[ "$kernel" -eq 0 ] || tail -30 "$OUT/kernel.log"

echo "== benchmarks"
# shellcheck disable=SC2086
timeout "${GPU_BENCH_TIMEOUT:-330}" "$PY" bench/gpu_table.py --data "$DATA" --out "$OUT/gpu.json" ${GPU_TABLE_ARGS:-} 2>"$OUT/bench.log" |
    tee "$OUT/table.txt"
bench=${PIPESTATUS[0]}
[ "$bench" -eq 0 ] || grep -A12 Traceback "$OUT/bench.log" | tail -40
echo "tests exit $tests, kernel exit $kernel, benchmarks exit $bench"
exit $(( tests || kernel || bench ))
