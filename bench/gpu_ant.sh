#!/usr/bin/env bash
# The ant chain of issue 19 in one prepared GPU run (< 10 min on one H100/H200): OGBench's
# antmaze-medium-navigate recipe with our expert (ingest, EPISODES episodes, WORKERS processes),
# segment, then EM training on CUDA with `train.cuda_graph` for MINUTES minutes. The trained
# model, the training reports and the logs land in $OUT; validate and deploy run on the CPU
# afterwards, with the same params and `--data` pointing at the returned folder.
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
mkdir -p "$OUT"
if compgen -G ".whl/*.whl" >/dev/null; then
    "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
        --target /tmp/oposm-site .whl/*.whl || exit 1
    export PYTHONPATH=/tmp/oposm-site
fi
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1 MUJOCO_GL=egl
if [ "$DEVICE" = cuda ]; then
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee "$OUT/gpu.txt"
fi
P=(-p params-ogbench-antmaze-medium.yaml --data "$DATA")
T=(-S train.lr_e=0.0001 -S train.lr_m=0.0001 -S "train.device=$DEVICE" -S train.cuda_graph=true
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
mkdir -p "$OUT/data"
cp -r "$DATA/models" "$DATA/reports" "$OUT/data/" 2>/dev/null
cp "$DATA"/segments/*/segments.json "$OUT/data/" 2>/dev/null
exit $rc
