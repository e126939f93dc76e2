#!/usr/bin/env bash
# The ant chain on a CUDA GPU, its data made on the CPU cores beside it: OGBench's
# antmaze-medium-navigate recipe (PARAMS: another ant params file) with our expert (ingest,
# EPISODES episodes, WORKERS processes), segment, then EM training on CUDA with
# `train.cuda_graph` for MINUTES minutes, in DATA (default /tmp/oposm-ant). The trained model and
# the training reports are also packed into OUT (default /tmp/oposm-gpu-ant) as ant.tgz, the logs
# beside them, to copy elsewhere: validate and deploy then run on any CPU, with the same params
# and `--data` at the unpacked folder. WORKERS defaults to one per CPU core but one.
#
# On any Linux machine with a CUDA GPU, from the repository's root, with the project installed
# (`uv sync`; PYTHON names its interpreter):
#   bash bench/gpu_ant.sh
# On a node without network access that has torch and CUDA but not the rest: `bash
# bench/gpu_wheels.sh --ant` on a machine with network fetches the rest as wheels into .whl/ (33 MB, without
# gymnasium-robotics, which the ant chain does not import).
# DEADLINE (epoch seconds, e.g. a batch job's time limit) shortens the training so that the
# script ends by then.
# Dry run without a GPU (tiny sizes, CPU): EPISODES=20 WORKERS=2 MINUTES=0.5 DEVICE=cpu \
#   OUT=/tmp/ant-dry bash bench/gpu_ant.sh
set -uo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
OUT=${OUT:-/tmp/oposm-gpu-ant}
DATA=${DATA:-/tmp/oposm-ant}
EPISODES=${EPISODES:-1000}
WORKERS=${WORKERS:-$(( $(nproc) > 1 ? $(nproc) - 1 : 1 ))}
MINUTES=${MINUTES:-5}
DEVICE=${DEVICE:-cuda}
PARAMS=${PARAMS:-params-ogbench-antmaze-medium.yaml}   # or params-ogbench-antmaze-large.yaml
mkdir -p "$OUT"
source bench/gpu_env.sh  # the wheels in .whl/, if any; PYTHONPATH
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
# One archive of the published model, the training metrics and curves, and segments.json
# (`tar xzf ant.tgz` in a data folder to unpack).
(cd "$DATA" && tar czf - models/*/model.safetensors models/*/config.json \
    reports/train/metrics.json reports/train/plots segments/*/segments.json 2>/dev/null) \
    > "$OUT/ant.tgz"
exit $rc
