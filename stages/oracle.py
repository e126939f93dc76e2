"""Oracle stage: OGBench's scripted oracles on its manipulation evaluation tasks.

The reference row beside the learned agents (`pipeline.envs.manipspace.solver`): OGBench's plan
oracles, subtask by subtask, in OGBench's own env, on the starts of `oposm deploy`'s episodes
(`deploy.episodes` per task from `deploy.seed`). Writes `<data>/reports/deploy/report.json` in the
deploy report's layout with one agent, `oracle` (run it with `--run oracle`: the manipulation
reports read every run's deploy report as one agent's row).
"""

from __future__ import annotations

import logging
import time
from typing import Any

import numpy as np

from pipeline.config import Params
from pipeline.envs.manipspace.env import EPISODE_STEPS, is_manipspace, manipspace_spec
from pipeline.envs.manipspace.solver import OracleEpisode, evaluate
from pipeline.errors import UserError
from pipeline.evaluation.proportions import wilson_interval
from pipeline.paths import Paths
from pipeline.segments import load_segments
from stages.report import split_timings, write_timings

log = logging.getLogger(__name__)

AGENT = "oracle"
OVERALL = "ogbench"


def _summary(episodes: list[OracleEpisode]) -> dict[str, Any]:
    n, wins = len(episodes), sum(e.success for e in episodes)
    low, high = wilson_interval(wins, n)
    steps = [e.steps for e in episodes if e.success]
    return {
        "episodes": n,
        "successes": wins,
        "success_rate": wins / n,
        "success_ci95_low": low,
        "success_ci95_high": high,
        "steps_to_goal": None if not steps else {
            "mean": float(np.mean(steps)), "p50": float(np.median(steps)), "max": max(steps)},
        "subtasks_mean": float(np.mean([e.subtasks for e in episodes])),
        "final_distance_mean": None,
    }  # fmt: skip


def run(params: Params, paths: Paths) -> dict[str, Any]:
    """Run the oracle on OGBench's five tasks of the dataset's env; write and return the report.

    Raises:
        UserError: the dataset's env is not one of OGBench's manipulation envs, or its segments
            are missing (run `oposm segment` first).
    """
    cfg, name = params.deploy, params.ingest.name
    report_path = paths.report("deploy")
    paths.check([report_path])
    env_id = load_segments(paths.existing(paths.segments(name))).info.env_id
    if not is_manipspace(env_id):
        raise UserError(
            f"{name}: its env {env_id} is not one of OGBench's manipulation envs; the oracle "
            "stage runs OGBench's manipulation oracles (on mazes: `oposm deploy` agent expert)"
        )
    started = time.perf_counter()
    log.info("oracle: OGBench's plan oracles on %s, %d episodes per task", env_id, cfg.episodes)
    results = evaluate(manipspace_spec(env_id), cfg.episodes, cfg.seed)
    by_task = {task: _summary(eps) for task, eps in results.items()}
    by_task[OVERALL] = _summary([e for eps in results.values() for e in eps])
    wall = time.perf_counter() - started
    report = {
        "dataset": name,
        "env_id": env_id,
        "agents": [AGENT],
        "tasks": [*results, OVERALL],
        "episodes": sum(len(eps) for eps in results.values()),
        "episodes_per_task": cfg.episodes,
        "max_steps": EPISODE_STEPS[env_id],
        "by_agent": {AGENT: {**by_task, "wall_s": wall, "settings": {
            "config": "OGBench's plan oracles (ogbench.manipspace.oracles.plan), noise-free, "
                      "one subtask at a time (pipeline/envs/manipspace/solver.py)"}}},
        "wall_s": wall,
        "distance_unit": "success tolerances",
    }  # fmt: skip
    kept, timings = split_timings(report)  # no clock in the output: the same bytes every run
    with paths.staged([report_path]) as out:
        out.write_json(report_path, kept)
    write_timings(paths, "deploy", timings)
    for task, row in by_task.items():
        log.info("oracle %-14s %d/%d", task, row["successes"], row["episodes"])
    return report
