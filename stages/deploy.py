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
from pipeline.envs.batch import BatchSim
from pipeline.envs.spec import make_env_spec
from pipeline.errors import UserError
from pipeline.evaluation.compat import check_model_dims, check_same_environment
from pipeline.evaluation.episodes import EpisodeResult, PlanCall, RunConfig, run_episodes
from pipeline.evaluation.stats import latency_summary, task_summary
from pipeline.evaluation.tasks import MazeTasks, check_task, train_locations
from pipeline.io import atomic_dir, write_json
from pipeline.model import load_model
from pipeline.paths import Paths
from pipeline.planning import CEMConfig, PlannerConfig, SkillPlanner
from pipeline.planning.mpc import SkillMPC
from pipeline.segments import load_segments
from pipeline.viz.deploy import recording_name, write_episode_recording
from stages.report import write_report

log = logging.getLogger(__name__)


def planner_config(p: PlannerParams) -> PlannerConfig:
    """`deploy.planner` params -> the planner's config."""
    return PlannerConfig(
        horizon=p.horizon,
        cem=CEMConfig(p.candidates, p.elites, p.iterations, p.min_std, p.stop_cost),
        init_std=p.init_std,
        prior_weight=p.prior_weight,
        warm_start=p.warm_start,
    )


def _record(
    results: list[EpisodeResult], cfg: DeployParams, envs: BatchSim, directory: Path, radius: float
) -> int:
    """Write the recordings of the episodes numbered below `deploy.record_episodes`."""
    chosen = [r for r in results if r.spec.index < cfg.record_episodes]
    for r in chosen:
        write_episode_recording(directory / f"{recording_name(r)}.rrd", r, envs.spec, radius)
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
    model_dir = paths.existing(paths.model(name))
    model, meta = load_model(model_dir, device=device)
    segments = load_segments(paths.existing(paths.segments(name)))
    info = segments.info
    check_same_environment(info, meta, f"the model in {model_dir}")
    if info.name != meta.get("dataset"):
        raise UserError(
            f"{paths.segments(name)} holds dataset '{info.name}' but the model was "
            f"trained on '{meta.get('dataset')}'; re-run `oposm train`"
        )
    spec = make_env_spec(info.env_id, info.env_kwargs)
    check_model_dims(
        model.config.state_dim, model.config.action_dim, spec, f"the model in {model_dir}"
    )

    started = time.perf_counter()
    envs = BatchSim(spec, min(cfg.num_envs, cfg.episodes))
    goal = None if cfg.goal is None else np.asarray(cfg.goal, dtype=np.float64)
    locations = train_locations(segments, spec.goal_dims)
    tasks = MazeTasks(spec.layout, locations, cfg.start_noise, goal, cfg.seed)
    specs = {task: tasks.episodes(task, cfg.episodes) for task in cfg.tasks}  # checks first
    planner = SkillPlanner(model, planner_config(cfg.planner))
    agent = SkillMPC(model, planner, cfg.sample_actions, spec.goal_dims)
    run_cfg = RunConfig(
        max_steps=cfg.max_steps or spec.max_episode_steps,
        replan_every=cfg.replan_every or int(meta["window"]) - 1,
        success_radius=cfg.success_radius,
    )

    results: dict[str, list[EpisodeResult]] = {}
    calls: list[PlanCall] = []
    recordings = paths.recordings("deploy")
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
        "env_id": spec.env_id,
        "model_step": meta.get("step"),
        "device": str(device),
        "torch_threads": torch.get_num_threads(),
        "tasks": list(cfg.tasks),
        "episodes": sum(len(r) for r in results.values()),
        "success_radius": run_cfg.success_radius,
        "max_steps": run_cfg.max_steps,
        "replan_every": run_cfg.replan_every,
        **{task: task_summary(r, spec.dt) for task, r in results.items()},
        "planning": latency_summary(calls),
        "wall_s": time.perf_counter() - started,
        "recordings": str(recordings),
        "recorded_episodes": recorded,
    }
    rows = [r.to_json() for task in cfg.tasks for r in results[task]]
    write_json(paths.live("deploy") / "episodes.json", rows)
    write_report(paths, "deploy", report)
    return report
