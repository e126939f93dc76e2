#!/usr/bin/env bash
# The planner sweep on pointmaze-giant-stitch on a CUDA GPU and the CPU cores beside it:
# OGBench's stitch recipe at OGBench's size (5000 episodes of 201 steps, the `giant-stitch5k` root of experiments/ogbench/params.yaml), segment,
# EM on CUDA (the variant's 5000 steps), then one deploy per planner setting, all at once (one
# core each, plans on the GPU), on OGBench's five tasks with 2000-step episodes: success within
# OGBench's 1000 steps is `steps_to_goal <= 1000` of the same episodes, and the rest says how
# many failures only ran out of time. A development sweep (EPISODES per task, default 20), not a
# results row: the chosen setting is then run by experiments/ogbench/dvc.yaml.
#
# On any Linux machine with a CUDA GPU, from the repository's root, with the project installed
# (`uv sync`; PYTHON names its interpreter): `bash bench/gpu_giant_sweep.sh`; on a node without
# network access, the wheels of `bash bench/gpu_wheels.sh --ant` in .whl/ first. The reports are
# packed into OUT (default /tmp/oposm-gpu-sweep) as sweep.tgz, one folder per setting:
# reports/deploy/episodes.json and metrics; the logs as logs.tgz. WORKERS defaults to one per
# CPU core but one.
# The deploys need rerun-sdk installed (stages/deploy.py imports it; these deploys record
# nothing, `deploy.record_episodes=0`). DEPLOY_TIMEOUT (seconds, `timeout`'s 0 = none) bounds
# the deploys; the reports written by then are packed either way.
# Dry run without a GPU: DEVICE=cpu EPISODES_DATA=40 STEPS=20 EPISODES=1 MAX_STEPS=60 \
#   SETTINGS=2 OUT=/tmp/sweep-dry bash bench/gpu_giant_sweep.sh
set -uo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
OUT=${OUT:-/tmp/oposm-gpu-sweep}
DATA=${DATA:-/tmp/oposm-giant-stitch}
DEVICE=${DEVICE:-cuda}
EPISODES_DATA=${EPISODES_DATA:-5000}
STEPS=${STEPS:-5000}
EPISODES=${EPISODES:-20}
MAX_STEPS=${MAX_STEPS:-2000}
WORKERS=${WORKERS:-$(( $(nproc) > 1 ? $(nproc) - 1 : 1 ))}
LOGS="$DATA/logs"  # every log, packed as $OUT/logs.tgz
mkdir -p "$OUT" "$LOGS"
source bench/gpu_env.sh
P=(-p params-ogbench-pointmaze-giant.yaml --data "$DATA"
   -S ingest.name=ogbench-pointmaze-giant-stitch -S ingest.ogbench.dataset_type=stitch
   -S "ingest.episodes=$EPISODES_DATA" -S ingest.episode_steps=201)
stage() {  # name, then the command; its time and exit code in $OUT/times.txt
    local name=$1 start rc
    shift
    start=$(date +%s)
    "$@" 2>&1 | tr '\r' '\n' | grep -v "it/s]$\|frame/s]$\|step/s]$" > "$LOGS/$name.log"
    rc=${PIPESTATUS[0]}
    echo "$name $(( $(date +%s) - start )) s exit $rc" | tee -a "$OUT/times.txt"
    return "$rc"
}
stage ingest "$PY" cli.py ingest "${P[@]}" -S "ingest.ogbench.workers=$WORKERS" || exit 1
stage segment "$PY" cli.py segment "${P[@]}" || exit 1
T=(-S "train.device=$DEVICE" -S "train.max_steps=$STEPS")
[ "$DEVICE" = cuda ] && T+=(-S train.cuda_graph=true)
stage train "$PY" cli.py train "${P[@]}" "${T[@]}" || exit 1
# name|overrides: the committed row's setting first, then one change each, then combinations.
SWEEP=(
    "base|"
    "mean|-S deploy.sample_actions=false"
    "tau13|-S deploy.replan_every=13"
    "tau8|-S deploy.replan_every=8"
    "reach3|-S deploy.subgoals.reach=3"
    "reach4|-S deploy.subgoals.reach=4"
    "cell2|-S deploy.subgoals.cell=2.0"
    "penalty1|-S deploy.planner.skill_penalty=1.0"
    "prior0|-S deploy.planner.prior_weight=0.0"
    "cem3x|-S deploy.planner.candidates=300 -S deploy.planner.elites=60"
    "mean-tau13|-S deploy.sample_actions=false -S deploy.replan_every=13"
    "mean-reach3|-S deploy.sample_actions=false -S deploy.subgoals.reach=3"
    "mean-tau13-reach3|-S deploy.sample_actions=false -S deploy.replan_every=13 -S deploy.subgoals.reach=3"
    "mean-tau13-reach4|-S deploy.sample_actions=false -S deploy.replan_every=13 -S deploy.subgoals.reach=4"
)
SWEEP=("${SWEEP[@]:0:${SETTINGS:-${#SWEEP[@]}}}")
D=(-S "deploy.agents=[oposm]" -S "deploy.episodes=$EPISODES" -S "deploy.num_envs=$EPISODES"
   -S "deploy.max_steps=$MAX_STEPS" -S deploy.record_episodes=0 -S deploy.threads=1)
start=$(date +%s)
for entry in "${SWEEP[@]}"; do
    name=${entry%%|*}
    # shellcheck disable=SC2206
    extra=(${entry#*|})
    timeout "${DEPLOY_TIMEOUT:-0}" "$PY" cli.py deploy "${P[@]}" --run "$name" "${D[@]}" "${extra[@]}" 2>&1 | tr '\r' '\n' |
        grep -v "it/s]$\|step/s]$" > "$LOGS/deploy-$name.log" &
done
wait
echo "deploys $(( $(date +%s) - start )) s" | tee -a "$OUT/times.txt"
tar czf "$OUT/logs.tgz" -C "$DATA" logs
(cd "$DATA" && tar czf "$OUT/sweep.tgz" runs/*/reports/deploy runs/*/metrics \
    reports/train/metrics.json 2>/dev/null)
"$PY" - "$DATA" "$MAX_STEPS" <<'EOF' | tee "$OUT/summary.txt"
import json, sys
from pathlib import Path
root, limit, longest = Path(sys.argv[1]), 1000, sys.argv[2]  # OGBench's limit; the episodes' own
print(f"{'setting':20s} {'ogbench(1000)':>14s} {longest + ' steps':>11s} {'median steps':>13s} per task (1000)")
for run in sorted((root / "runs").glob("*")):
    f = run / "reports/deploy/episodes.json"
    if not f.exists():
        print(f"{run.name:20s} no report"); continue
    rows = json.loads(f.read_text())
    ok = [r for r in rows if r["steps_to_goal"] is not None and r["steps_to_goal"] <= limit]
    late = [r for r in rows if r["steps_to_goal"] is not None]
    steps = sorted(r["steps_to_goal"] for r in ok)
    tasks = {}
    for r in rows:
        t = tasks.setdefault(str(r.get("task")), [0, 0])
        t[1] += 1
        t[0] += r["steps_to_goal"] is not None and r["steps_to_goal"] <= limit
    med = steps[len(steps) // 2] if steps else None
    print(f"{run.name:20s} {len(ok):6d}/{len(rows):<7d} {len(late):5d}/{len(rows):<5d} {str(med):>13s} "
          + " ".join(f"{a}/{b}" for a, b in tasks.values()))
EOF
