#!/usr/bin/env bash
# results/stability-cpu.{md,json}: EM across seeds, each run trained (`oposm train`, the main
# job's params, one torch thread) then deployed on the main job's tasks, 100 random goals and 100
# corner-to-corner episodes (`oposm deploy`). Recipes (RECIPES below), seeds 0-9 unless said:
# `default` (the shipped params: the conv posterior, the subgoal graph once an episode is stuck;
# it deploys `conv`'s models, the same training), `gru` (the default before: the paper's GRU
# posterior, no subgoal graph), `bfloat16` (gru in bfloat16; earlier rows named `ema`), `paper`
# (gru with train.e_prior: current, the paper's E-step) on seeds 0-4, two probes on the paper's
# E-step on seeds 1 and 2: `censored` (train.action_likelihood) and `layernorm`
# (train.policy_trunk: layernorm_silu); gru's models deployed differently: `tau39` (each skill
# run whole, T = 39), `tau10` (replanning every 10 steps with 10 CEM iterations), `subgoals`
# (tau39 with the subgoal graph from the first replan) and `subgoals3` (the same with waypoints
# up to 3 skills ahead); `conv` (gru's deploy with the posterior's GRU replaced by strided
# convolutions, train.encoder). Two jobs at a time; 3-11 min of training and 1-3 of deploying
# per run on an idle 2-core CPU. A run already finished is skipped, and a killed one resumes
# where it stopped, so the same command continues a sweep.
# `bash scripts/stability_cpu.sh RECIPE...` runs only those recipes, `--seeds 0,3` only those
# seeds of them, `--jobs 1` one run at a time (beside another job on the other core); the report
# keeps every row not rerun here from the committed results/stability-cpu.json (with its commit
# and machine). Needs the main job's segments (`uv run dvc repro segment`). `--report` only
# rewrites the report.
set -euo pipefail
cd "$(dirname "$0")/.."
runs=data/runs
# The GRU recipes pin what the shipped params were before the conv posterior and the stuck
# subgoal graph became the default (`gru` is that default; its rows were named `default`).
gru="-S train.encoder=gru -S deploy.subgoals.enabled=false"
declare -A RECIPES=(
  [default]=""
  [gru]="$gru"
  [bfloat16]="$gru -S train.dtype=bfloat16"
  [paper]="$gru -S train.e_prior=current"
  [censored]="$gru -S train.e_prior=current -S train.action_likelihood=censored"
  [layernorm]="$gru -S train.e_prior=current -S train.policy_trunk=layernorm_silu"
  [tau39]="$gru -S deploy.replan_every=null"
  [tau10]="$gru -S deploy.replan_every=10 -S deploy.planner.iterations=10"
  [subgoals]="$gru -S deploy.subgoals.enabled=true -S deploy.subgoals.patience=null -S deploy.replan_every=null"
  [subgoals3]="$gru -S deploy.subgoals.enabled=true -S deploy.subgoals.patience=null -S deploy.subgoals.reach=3 -S deploy.replan_every=null"
  [conv]="-S train.encoder=conv -S deploy.subgoals.enabled=false"
)
# Recipes that only deploy differently: they deploy the model of the recipe named here (trained
# first if it is missing), and their row repeats that training's numbers. The default trains as
# `conv` does (the same train section).
declare -A DEPLOYS_MODEL_OF=([default]=conv [tau39]=gru [tau10]=gru [subgoals]=gru [subgoals3]=gru)
report_only=false
seeds=""
parallel=2
while [[ $# -gt 0 ]]; do
  case "$1" in
    --report) report_only=true; shift ;;
    --seeds) seeds="${2:?--seeds needs a list such as 0,3,4}"; shift 2 ;;
    --jobs) parallel="${2:?--jobs needs 1 or 2}"; shift 2 ;;
    *) break ;;
  esac
done
[[ "$parallel" == 1 || "$parallel" == 2 ]] || { echo "--jobs is 1 or 2, not $parallel" >&2; exit 2; }
selected=("$@")
for recipe in "${selected[@]}"; do
  [[ -v "RECIPES[$recipe]" ]] || { echo "unknown recipe $recipe; use: ${!RECIPES[*]}" >&2; exit 2; }
done
wanted() {  # recipe seed
  { [[ ${#selected[@]} -eq 0 ]] || [[ " ${selected[*]} " == *" $1 "* ]]; } &&
    { [[ -z "$seeds" ]] || [[ ",$seeds," == *",$2,"* ]]; }
}
jobs=()
for recipe in default gru bfloat16; do
  for seed in 0 1 2 3 4 5 6 7 8 9; do jobs+=("$recipe $seed"); done
done
for seed in 0 1 2 3 4; do jobs+=("paper $seed"); done
for recipe in censored layernorm; do jobs+=("$recipe 1" "$recipe 2"); done
for recipe in tau39 tau10 subgoals subgoals3 conv; do
  for seed in 0 1 2 3 4 5 6 7 8 9; do jobs+=("$recipe $seed"); done
done

run_one() {  # recipe seed
  local run="stability-$1-s$2" overrides
  read -ra overrides <<< "${RECIPES[$1]}"
  local common=(-S train.seed="$2" -S train.threads=1 "${overrides[@]}")
  if [[ -v "DEPLOYS_MODEL_OF[$1]" ]]; then
    local base="${DEPLOYS_MODEL_OF[$1]}" model
    local trained="$runs/stability-$base-s$2"
    local -a base_overrides
    read -ra base_overrides <<< "${RECIPES[$base]}"
    if [[ ! -f "$trained/metrics/train.json" ]]; then
      uv run oposm train --run "stability-$base-s$2" -S train.seed="$2" -S train.threads=1 \
        "${base_overrides[@]}" > "$runs/stability-$base-s$2.log" 2>&1
    fi
    model=$(ls -d "$trained"/models/*/ | grep -v -- '-\(dynamics\|bc\|gcbc\)/$' | head -1)
    if [[ ! -f "$runs/$run/metrics/deploy.json" ]]; then
      uv run oposm deploy --run "$run" --model "$model" "${common[@]}" \
        -S deploy.record_episodes=0 > "$runs/$run-deploy.log" 2>&1
    fi
    cp "$trained/metrics/train.json" "$runs/$run/metrics/train.json"
    return
  fi
  if [[ ! -f "$runs/$run/metrics/train.json" ]]; then
    uv run oposm train --run "$run" "${common[@]}" > "$runs/$run.log" 2>&1
  fi
  if [[ ! -f "$runs/$run/metrics/deploy.json" ]]; then
    uv run oposm deploy --run "$run" "${common[@]}" -S deploy.record_episodes=0 \
      > "$runs/$run-deploy.log" 2>&1
  fi
}

if ! $report_only; then
  mkdir -p "$runs"
  todo=()
  for job in "${jobs[@]}"; do
    read -r recipe seed <<< "$job"
    if wanted "$recipe" "$seed"; then todo+=("$job"); fi
  done
  for ((i = 0; i < ${#todo[@]}; i += parallel)); do
    run_one ${todo[i]} &
    if ((parallel == 2 && i + 1 < ${#todo[@]})); then run_one ${todo[i + 1]} & fi
    wait
  done
fi

args=()
for job in "${jobs[@]}"; do
  read -r recipe seed <<< "$job"
  args+=(--run "$recipe $seed $runs/stability-$recipe-s$seed")
done
keep=()
if [[ -f results/stability-cpu.json ]]; then keep=(--keep results/stability-cpu.json); fi
uv run python scripts/stability_report.py --out results/stability-cpu "${keep[@]}" "${args[@]}"
