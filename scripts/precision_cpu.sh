#!/usr/bin/env bash
# results/precision-cpu.{md,json}: the main job's training and planning in bfloat16 against float32
# (issue 16), on this machine's CPU. Needs the main job's outputs (`uv run dvc repro`): its
# segments, and its model as the float32 seed-0 run. About 45 min on 2 cores (two jobs at a time,
# one torch thread each). `--report` only rewrites the report from the runs already there.
set -euo pipefail
cd "$(dirname "$0")/.."
oposm() { uv run oposm "$@"; }
runs=data/runs

if [[ "${1:-}" == "--report" ]]; then
  shift
else
  train() {  # dtype seed
    local tag=${1/float32/fp32}; tag=${tag/bfloat16/bf16}
    oposm train --run "precision-$tag-s$2" -S train.dtype="$1" -S train.seed="$2" \
      -S train.threads=1 > "$runs/precision-$tag-s$2.log" 2>&1
  }
  deploy() {  # run, then overrides
    local run=$1; shift
    oposm deploy --run "$run" -S deploy.episodes=300 -S deploy.record_episodes=0 "$@" \
      > "$runs/$run-deploy.log" 2>&1
  }
  mkdir -p "$runs"
  train bfloat16 0 & train float32 1 & wait
  train bfloat16 1 & train float32 2 & wait
  train bfloat16 2 &
  deploy precision-bf16-s0 & wait
  deploy precision-main-float32 -S deploy.planner.dtype=float32 &
  deploy precision-main-bfloat16 -S deploy.planner.dtype=bfloat16 & wait
fi

uv run python scripts/runs_report.py --out results/precision-cpu \
  --title "bfloat16 against float32: training and planning on the CPU (issue 16)" \
  --command "bash scripts/precision_cpu.sh   # two jobs at a time, one torch thread each; each run's log: data/runs/precision-*.log" \
  --train "float32, seed 0 (the main job's model: metrics/train.json, dvc repro)=metrics/train.json" \
  --train "bfloat16, seed 0=$runs/precision-bf16-s0/metrics/train.json" \
  --train "float32, seed 1=$runs/precision-fp32-s1/metrics/train.json" \
  --train "bfloat16, seed 1=$runs/precision-bf16-s1/metrics/train.json" \
  --train "float32, seed 2=$runs/precision-fp32-s2/metrics/train.json" \
  --train "bfloat16, seed 2=$runs/precision-bf16-s2/metrics/train.json" \
  --deploy "float32 model, float32 planner=$runs/precision-main-float32" \
  --deploy "float32 model, bfloat16 planner=$runs/precision-main-bfloat16" \
  --deploy "bfloat16 model (seed 0), float32 planner=$runs/precision-bf16-s0" \
  --pair "float32 model, float32 planner|float32 model, bfloat16 planner" \
  --pair "float32 model, float32 planner|bfloat16 model (seed 0), float32 planner" \
  --note "What the committed run shows is discussed in CHANGELOG.md (Moved from the README: bfloat16 against float32). Seeds 1 and 2 are only trained: their published checkpoints come from early steps, in both precisions, so they are not deployed." \
  "$@"
