"""Deploy stage: skill MPC in the maze of the training data; success rates, latency, recordings.

Reads the model (`data/models/<name>/`) and the segments (training-data locations, the goals of
`random_goal`); writes `data/reports/deploy.json` (DVC metrics), `data/reports/deploy/episodes.json`
(one row per episode) and `data/recordings/deploy/<task>-<episode>.rrd`.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from pipeline.config import DeployParams, Params, PlannerParams
from pipeline.devices import resolve_device, torch_threads
from pipeline.envs.maze import SUPPORTED_ENVS, max_episode_steps
from pipeline.errors import UserError
from pipeline.evaluation.episodes import EpisodeResult, PlanCall, RunConfig, run_episodes
from pipeline.evaluation.maze_batch import MazeBatch
from pipeline.evaluation.stats import latency_summary, task_summary
from pipeline.evaluation.tasks import MazeTasks, check_task, train_locations
from pipeline.io import atomic_dir, write_json
from pipeline.model import SkillModel, load_model
from pipeline.paths import Paths
from pipeline.planning import CEMConfig, PlannerConfig, SkillPlanner
from pipeline.planning.mpc import SkillMPC
from pipeline.segments import load_segments
from pipeline.viz.deploy import recording_name, write_episode_recording

log = logging.getLogger(__name__)

# PointMaze observations: [x, y, vx, vy].
MAZE_STATE_DIM = 4


def planner_config(p: PlannerParams) -> PlannerConfig:
    """`deploy.planner` params -> the planner's config."""
    return PlannerConfig(
        horizon=p.horizon,
        cem=CEMConfig(p.candidates, p.elites, p.iterations, p.min_std, p.stop_cost),
        init_std=p.init_std,
        prior_weight=p.prior_weight,
        warm_start=p.warm_start,
    )


def check_model_env(model: SkillModel, meta: dict[str, Any], directory: str) -> tuple[str, Any]:
    """The env id and maze map the checkpoint was trained on; errors if deploy cannot run there."""
    info = meta.get("info") or {}
    env_id = info.get("env_id", "")
    if env_id not in SUPPORTED_ENVS:
        raise UserError(
            f"the model in {directory} was trained on data from env {env_id!r}; deploy runs "
            f"PointMaze only ({', '.join(SUPPORTED_ENVS)})"
        )
    if model.config.state_dim != MAZE_STATE_DIM:
        raise UserError(
            f"the model in {directory} has state_dim {model.config.state_dim}, but {env_id} "
            f"states have {MAZE_STATE_DIM} ([x, y, vx, vy]); retrain on this env's observations"
        )
    return env_id, (info.get("env_kwargs") or {}).get("maze_map")


def _record(
    results: list[EpisodeResult], cfg: DeployParams, envs: MazeBatch, directory: Path, radius: float
) -> int:
    """Write the recordings of the episodes numbered below `deploy.record_episodes`."""
    chosen = [r for r in results if r.spec.index < cfg.record_episodes]
    for r in chosen:
        path = directory / f"{recording_name(r)}.rrd"
        write_episode_recording(path, r, envs.layout, envs.dt, radius)
    return len(chosen)


def run(params: Params, paths: Paths, progress: bool = True) -> dict[str, Any]:
    """Deploy the trained model on `deploy.tasks`; write the report and recordings; return the
    report. Uses `deploy.threads` torch threads while it runs (one by default: the batches are
    small, and intra-op threads that wait on a busy core cost more than they give)."""
    with torch_threads(params.deploy.threads):
        return _run(params, paths, progress)


def _run(params: Params, paths: Paths, progress: bool) -> dict[str, Any]:
    cfg, name = params.deploy, params.ingest.name
    for task in cfg.tasks:
        check_task(task)
    device = resolve_device(cfg.device, "deploy.device")
    model_dir = paths.model(name)
    model, meta = load_model(model_dir, device=device)
    env_id, maze_map = check_model_env(model, meta, str(model_dir))
    segments = load_segments(paths.segments(name))
    if segments.info.name != meta.get("dataset"):
        raise UserError(
            f"{paths.segments(name)} holds dataset '{segments.info.name}' but the model was "
            f"trained on '{meta.get('dataset')}'; re-run `oposm train`"
        )

    started = time.perf_counter()
    envs = MazeBatch(env_id, maze_map, min(cfg.num_envs, cfg.episodes))
    goal = None if cfg.goal is None else np.asarray(cfg.goal, dtype=np.float64)
    tasks = MazeTasks(envs.layout, train_locations(segments), cfg.start_noise, goal, cfg.seed)
    specs = {task: tasks.episodes(task, cfg.episodes) for task in cfg.tasks}  # checks first
    agent = SkillMPC(model, SkillPlanner(model, planner_config(cfg.planner)), cfg.sample_actions)
    run_cfg = RunConfig(
        max_steps=cfg.max_steps or max_episode_steps(env_id),
        replan_every=cfg.replan_every or int(meta["window"]) - 1,
        success_radius=cfg.success_radius,
    )

    results: dict[str, list[EpisodeResult]] = {}
    calls: list[PlanCall] = []
    recordings = paths.root / "recordings" / "deploy"
    recorded = 0
    with atomic_dir(recordings) as tmp:
        for task in cfg.tasks:
            bar = tqdm(total=cfg.episodes, desc=task, unit="episode", disable=not progress)

            def on_wave(done: list[EpisodeResult], bar=bar) -> None:
                nonlocal recorded
                recorded += _record(done, cfg, envs, tmp, run_cfg.success_radius)
                bar.update(len(done))
                bar.set_postfix(success=f"{np.mean([r.success for r in done]):.2f}")

            results[task], task_calls = run_episodes(agent, envs, specs[task], run_cfg, on_wave)
            calls += task_calls
            bar.close()

    report: dict[str, Any] = {
        "dataset": name,
        "env_id": env_id,
        "model_step": meta.get("step"),
        "device": str(device),
        "torch_threads": torch.get_num_threads(),
        "tasks": list(cfg.tasks),
        "episodes": sum(len(r) for r in results.values()),
        "success_radius": run_cfg.success_radius,
        "max_steps": run_cfg.max_steps,
        "replan_every": run_cfg.replan_every,
        **{task: task_summary(r, envs.dt) for task, r in results.items()},
        "planning": latency_summary(calls),
        "wall_s": time.perf_counter() - started,
        "recordings": str(recordings),
        "recorded_episodes": recorded,
    }
    rows = [r.to_json() for task in cfg.tasks for r in results[task]]
    write_json(paths.live("deploy") / "episodes.json", rows)
    write_json(paths.report("deploy"), report)
    return report
