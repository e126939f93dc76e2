#!/usr/bin/env bash
# The ant chain of issue 19 in one prepared GPU run (< 10 min on one H100/H200): OGBench's
# antmaze-medium-navigate recipe (PARAMS: another ant params file) with our expert (ingest,
# EPISODES episodes, WORKERS processes),
# segment, then EM training on CUDA with `train.cuda_graph` for MINUTES minutes. The trained
# model and the training reports land in $OUT as ant.tgz.NN, the logs beside them; validate and
# deploy run on the CPU afterwards, with the same params and `--data` at the unpacked folder.
#
# Where: the device tool's machine (no network; torch with CUDA, accelerate, scipy, ... in its
# image). What it lacks travels as wheels in .whl/: `bash bench/gpu_wheels.sh --ant` here first
# (33 MB without gymnasium-robotics, which the ant chain does not import). Then, from this
# repo's root:
#   run(command="bash bench/gpu_ant.sh", timeout_s=600, carry=[".whl"])
# DEADLINE (epoch seconds) shortens the training so that the script ends by then.
# Dry run without a GPU (tiny sizes, CPU): EPISODES=20 WORKERS=2 MINUTES=0.5 DEVICE=cpu \
#   OUT=/tmp/ant-dry bash bench/gpu_ant.sh
set -uo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
OUT=${OUT:-/tmp/oposm-gpu-ant}
DATA=${DATA:-/tmp/oposm-ant}
EPISODES=${EPISODES:-1000}
WORKERS=${WORKERS:-15}
MINUTES=${MINUTES:-5}
DEVICE=${DEVICE:-cuda}
PARAMS=${PARAMS:-params-ogbench-antmaze-medium.yaml}   # or params-ogbench-antmaze-large.yaml
mkdir -p "$OUT"
source bench/gpu_env.sh  # the carried wheels, PYTHONPATH
if [ "$DEVICE" = cuda ]; then
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee "$OUT/gpu.txt"
fi
# OVERRIDES: more -S settings for every stage, e.g. "-S segment.exclude_fallen=true".
# shellcheck disable=SC2206
P=(-p "$PARAMS" --data "$DATA" ${OVERRIDES:-})
T=(-S "train.device=$DEVICE" -S train.cuda_graph=true
   -S train.max_steps=1000000 -S "train.max_minutes=$MINUTES" -S train.eval_every=1000
   -S train.checkpoint_every=1000)
stage() {  # name, then the command; its time and exit code in $OUT/times.txt
    local name=$1 start rc
    shift
    start=$(date +%s)
    "$@" 2>&1 | tr '\r' '\n' | grep -v "it/s]$\|frame/s]$\|step/s]$" | tee "$OUT/$name.log"
    rc=${PIPESTATUS[0]}
    echo "$name $(( $(date +%s) - start )) s exit $rc" | tee -a "$OUT/times.txt"
    return "$rc"
}
stage ingest "$PY" cli.py ingest "${P[@]}" -S "ingest.episodes=$EPISODES" \
    -S "ingest.ogbench.workers=$WORKERS" || exit 1
stage segment "$PY" cli.py segment "${P[@]}" || exit 1
if [ -n "${DEADLINE:-}" ]; then  # epoch seconds by which everything must have ended
    MINUTES=$("$PY" -c "print(round(min($MINUTES, ($DEADLINE - $(date +%s) - 45) / 60), 2))")
    T+=(-S "train.max_minutes=$MINUTES")
fi
echo "training for $MINUTES minutes"
stage train "$PY" cli.py train "${P[@]}" "${T[@]}"
rc=$?
if [ "$rc" -ne 0 ] && [ "$DEVICE" = cuda ]; then  # e.g. a failed capture: eager, same budget
    stage train_eager "$PY" cli.py train "${P[@]}" "${T[@]}" -S train.cuda_graph=false
    rc=$?
fi
# What comes back from the device tool is limited in file count and size: one archive of the
# published model, the training metrics and curves, and segments.json, in 2.5 MB parts
# (`cat ant.tgz.* | tar xz` here).
(cd "$DATA" && tar czf - models/*/model.safetensors models/*/config.json \
    reports/train/metrics.json reports/train/plots segments/*/segments.json 2>/dev/null) |
    split -b 2500k -d - "$OUT/ant.tgz."
exit $rc
