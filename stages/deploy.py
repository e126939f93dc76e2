"""Deploy stage: the agents of `deploy.agents` in the environment of the training data (a maze,
one of OGBench's manipulation envs, on its five object-goal tasks, or the Franka kitchen, on its
D4RL task set with D4RL's score), on the same episodes; success rates, planning cost, recordings.

Agents: `oposm` (skill MPC with the skill model, `data/models/<name>/`), `oposm_sim` (its CEM
scored by executing each candidate in the simulator: the perfect-model bound), `llp` (low-level
planning with the single-step model `<name>-dynamics/` and the BC policy `<name>-bc/`), `gcbc`
(the goal-conditioned policy `<name>-gcbc/`), `expert` (the scripted controller that made the
data).
Every agent runs the same episodes (tasks, starts, goals, seeds) under the same step limit and
success rule. Writes `data/reports/deploy/report.json` (one section per agent, and OPOSM vs LLP when
both ran), `data/reports/deploy/episodes.json` (one row per agent and episode) and
`data/recordings/deploy/<agent>-<task>-<episode>.rrd`.

Each job (one agent's episodes of one task) is kept in `data/scratch/deploy/` as soon as it
ends: a killed deploy, run again with the same params and models, reads its finished jobs back
and runs only the others, with the same bytes (`stages.deploy_jobs.JobStore`).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pipeline.config import DeployParams, Params
from pipeline.devices import resolve_device, torch_threads
from pipeline.envs.disturbance import Pushes
from pipeline.envs.kitchen import KitchenSpec
from pipeline.envs.manipspace.env import ManipSpaceSpec
from pipeline.envs.spec import EnvSpec, make_env_spec
from pipeline.errors import UserError
from pipeline.evaluation.episodes import EpisodeResult, RunConfig
from pipeline.evaluation.flops import replan_flops
from pipeline.evaluation.goals import GoalRule
from pipeline.evaluation.report import compare_planners
from pipeline.evaluation.stats import latency_summary, optimism_gap, task_summary
from pipeline.evaluation.tasks import (
    OGBENCH_PREFIX,
    MazeTasks,
    check_kitchen_tasks,
    check_manipulation_tasks,
    check_task,
    kitchen_episodes,
    manipulation_episodes,
    train_locations,
)
from pipeline.paths import Paths
from pipeline.segments import load_segments
from pipeline.viz.deploy import recording_name, write_episode_recording
from pipeline.viz.kitchen import write_kitchen_episode_recording
from pipeline.viz.manip import write_manip_episode_recording, write_manip_overview
from pipeline.viz.overview import write_overview
from stages.deploy_agents import OBJECT_GOALS, AgentSetup, build_agent
from stages.deploy_jobs import (
    Job,
    JobStore,
    Runner,
    input_files,
    make_simulators,
    run_jobs,
    worker_count,
)
from stages.report import report_files, split_timings, write_report, write_timings

log = logging.getLogger(__name__)


def _record(
    results: list[EpisodeResult], cfg: DeployParams, spec: EnvSpec, directory: Path, radius: float
) -> int:
    """Write the recordings of the episodes numbered below `deploy.record_episodes`."""
    chosen = [r for r in results if r.spec.index < cfg.record_episodes]
    for r in chosen:
        path = directory / f"{recording_name(r)}.rrd"
        if isinstance(spec, ManipSpaceSpec):
            write_manip_episode_recording(path, r, spec)
        elif isinstance(spec, KitchenSpec):
            write_kitchen_episode_recording(path, r, spec)
        else:
            write_episode_recording(path, r, spec, radius)
    return len(chosen)


def run(params: Params, paths: Paths, progress: bool = True) -> dict[str, Any]:
    """Deploy the agents of `deploy.agents` on `deploy.tasks`; write the report and recordings;
    return the report. Uses `deploy.threads` torch threads while it runs (one by default: the
    batches are small, and intra-op threads that wait on a busy core cost more than they give)."""
    with torch_threads(params.deploy.threads):
        return _run(params, paths, progress)


def _optimism(
    setup: AgentSetup, results: dict[str, list[EpisodeResult]], spec: EnvSpec
) -> dict[str, Any] | None:
    """Each task's optimism gap (`optimism_gap`) for a planning agent; None for the others."""
    if setup.plan_state_steps is None or setup.replan_every is None:
        return None
    return {
        task: optimism_gap(
            r,
            setup.plan_state_steps,
            setup.replan_every,
            spec.goal_dims,
            getattr(spec, "goal_scale", None),
        )
        for task, r in results.items()
    }


def _check_ogbench_radius(cfg: DeployParams, spec: EnvSpec) -> None:
    """OGBench's tasks count success within its own goal distance: refuse another one."""
    tolerance = getattr(spec, "goal_tolerance", None)
    if "ogbench" in cfg.tasks and tolerance is not None and cfg.success_radius != tolerance:
        raise UserError(
            f"deploy.success_radius is {cfg.success_radius:g}, but OGBench's tasks in "
            f"{spec.env_id} succeed within {tolerance:g} of the goal; set deploy.success_radius: "
            f"{tolerance:g}"
        )


def _ogbench_overall(results: dict[str, list[EpisodeResult]], dt: float, limits) -> dict:
    """`{"ogbench": summary}` over OGBench's five tasks together (its headline number), if run."""
    pooled = [r for task, rs in results.items() if task.startswith(OGBENCH_PREFIX) for r in rs]
    return {"ogbench": task_summary(pooled, dt, limits)} if pooled else {}


def _run(params: Params, paths: Paths, progress: bool) -> dict[str, Any]:
    cfg, name = params.deploy, params.ingest.name
    recordings = paths.recordings("deploy")
    files = [paths.live("deploy") / "episodes.json", *report_files(paths, "deploy")]
    paths.check(files, [recordings])  # before the episodes: a path that cannot be written fails now
    for task in cfg.tasks:
        check_task(task)
    device = resolve_device(cfg.device, "deploy.device")
    segments = load_segments(paths.existing(paths.segments(name)))
    spec = make_env_spec(segments.info.env_id, segments.info.env_kwargs)
    if isinstance(spec, ManipSpaceSpec):
        check_manipulation_tasks(spec.env_id, cfg.tasks)  # before any model is loaded
    if isinstance(spec, KitchenSpec):
        check_kitchen_tasks(spec.env_id, cfg.tasks)
    setups = {a: build_agent(a, params, paths, segments, spec, device) for a in cfg.agents}

    started = time.perf_counter()
    goal = None if cfg.goal is None else np.asarray(cfg.goal, dtype=np.float64)
    if isinstance(spec, ManipSpaceSpec):  # OGBench's five tasks from exact start states
        specs = manipulation_episodes(spec, cfg.tasks, cfg.episodes, cfg.seed)
    elif isinstance(spec, KitchenSpec):  # the D4RL task set from the env's reset state
        task_set = (segments.info.generator or {}).get("kitchen_task_set")
        specs = kitchen_episodes(spec, cfg.tasks, cfg.episodes, cfg.seed, task_set)
    else:
        locations = train_locations(segments, spec.goal_dims)
        tasks = MazeTasks(
            spec.layout, locations, cfg.start_noise, goal, cfg.seed, spec.start_observation,
            spec.env_id,
        )  # fmt: skip
        specs = tasks.expand(cfg.tasks, cfg.episodes)  # checks first; ogbench: its five tasks
    _check_ogbench_radius(cfg, spec)
    reported = [*specs, *(["ogbench"] if "ogbench" in cfg.tasks else [])]
    max_steps = cfg.max_steps or spec.max_episode_steps
    limits = [spec.max_episode_steps] if max_steps > spec.max_episode_steps else []

    flops = {}  # a replan's matrix-product FLOPs, counted on the first episode
    for agent_name, setup in setups.items():
        if setup.replan_every is not None and setup.count_flops:
            first = next(iter(specs.values()))[0]
            flops[agent_name] = replan_flops(setup.agent, first.start, first.goal, first.seed)
    jobs = [
        Job(
            agent_name,
            task,
            task_specs,
            RunConfig(max_steps, setup.replan_every, cfg.success_radius),
        )
        for agent_name, setup in setups.items()
        for task, task_specs in specs.items()
    ]
    workers = worker_count(params, len(jobs))
    # One worker: the jobs run here, on the agents built above; else each worker builds its own.
    local = Runner(make_simulators(params, segments, spec), setups) if workers == 1 else None
    store = JobStore(params, paths, input_files(params, paths, segments))  # a killed run resumes
    done = dict(
        zip(
            ((j.agent, j.task) for j in jobs),
            run_jobs(jobs, local, params, paths, workers, progress, store),
            strict=True,
        )
    )

    by_agent: dict[str, Any] = {}
    rows: list[dict] = []
    episodes: list[EpisodeResult] = []  # every agent's, for the run overview
    recorded = 0
    with paths.staged(files, [recordings]) as out:  # published together, or none
        tmp = out.folder(recordings)
        for agent_name, setup in setups.items():
            mine = {task: done[agent_name, task] for task in specs}
            results = {task: job.results for task, job in mine.items()}
            for task_results in results.values():
                recorded += _record(task_results, cfg, spec, tmp, cfg.success_radius)
            by_agent[agent_name] = {
                **{task: task_summary(r, spec.dt, limits) for task, r in results.items()},
                **_ogbench_overall(results, spec.dt, limits),
                "replan_every": setup.replan_every,
                "flops_per_replan": flops.get(agent_name),
                "planning": latency_summary([c for job in mine.values() for c in job.calls]),
                "optimism_gap": _optimism(setup, results, spec),
                "wall_s": sum(job.seconds for job in mine.values()),
                "settings": setup.about,
            }
            rows += [r.to_json() for task in specs for r in results[task]]
            episodes += [r for task in specs for r in results[task]]
        if isinstance(spec, OBJECT_GOALS):
            write_manip_overview(tmp / "overview.rrd", episodes, spec)
        else:
            write_overview(tmp / "overview.rrd", episodes, spec)

        report: dict[str, Any] = {
            "dataset": name,
            "env_id": spec.env_id,
            "device": str(device),
            "torch_threads": torch.get_num_threads(),
            "agents": list(cfg.agents),
            "tasks": reported,
            "episodes": len(rows),
            "episodes_per_task": cfg.episodes,
            "success_radius": cfg.success_radius,
            "mass_scale": cfg.mass_scale,
            "disturbance": Pushes.of_dataset(segments.info.generator).to_dict(),
            "max_steps": max_steps,
            "shorter_limits": limits,
            "by_agent": by_agent,
            "wall_s": time.perf_counter() - started,
            "recordings": str(recordings),
            "recorded_episodes": recorded,
        }
        if isinstance(spec, OBJECT_GOALS):  # distances in success tolerances, not metres
            report["distance_unit"] = GoalRule.of_spec(spec).unit
        if "oposm" in by_agent and "llp" in by_agent:
            report["oposm_vs_llp"] = compare_planners(report, "oposm", "llp")
        kept_rows, row_timings = split_timings(rows)  # each episode's planning seconds
        out.write_json(paths.live("deploy") / "episodes.json", kept_rows)
        write_report(paths, "deploy", report, out)
        write_timings(paths, "deploy-episodes", row_timings)
    store.clear(jobs)  # the outputs are written: the finished jobs are no longer needed
    return report
