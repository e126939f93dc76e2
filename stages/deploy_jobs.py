"""Deploy's episodes as jobs, one per agent and task, run in this process or in `deploy.workers`
processes side by side.

A job's episodes do not depend on what ran before them in the same process: each wave resets the
agent with its episodes' seeds, the planner's noise is a function of those seeds, and the
simulators are reset to each episode's start. So a task run alone in a worker process gives the
same bytes as after another task in one process (`tests/test_deploy.py` compares the two), and the
workers only change the wall-clock time. Each worker loads the segments and builds its agents
itself (spawned, not forked: torch's thread pools do not survive a fork), once per agent.
"""

from __future__ import annotations

import multiprocessing
import os
import time
from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from pipeline.config import Params
from pipeline.devices import resolve_device, torch_threads
from pipeline.envs.batch import BatchSim
from pipeline.envs.disturbance import Pushes
from pipeline.envs.perturb import scale_mass
from pipeline.envs.spec import EnvSpec, make_env_spec
from pipeline.evaluation.episodes import EpisodeResult, PlanCall, RunConfig, run_episodes
from pipeline.evaluation.tasks import EpisodeSpec
from pipeline.paths import Paths
from pipeline.planning.simulated import SimulatedSkillMPC
from pipeline.segments import Segments, load_segments
from stages.deploy_agents import AgentSetup, build_agent


@dataclass(frozen=True)
class Job:
    """One agent's episodes of one task."""

    agent: str
    task: str
    specs: list[EpisodeSpec]
    run: RunConfig


@dataclass
class JobResult:
    results: list[EpisodeResult]
    calls: list[PlanCall]
    seconds: float  # wall-clock time of the episodes


def make_simulators(params: Params, segments: Segments, spec: EnvSpec) -> BatchSim:
    """The batch of simulators every agent runs in: `deploy.num_envs` (at most one per
    episode), every body's mass scaled by `deploy.mass_scale`, pushed as the data were."""
    cfg = params.deploy
    n_envs = min(cfg.num_envs, cfg.episodes)
    pushes = Pushes.of_dataset(segments.info.generator)  # the data's, if it was pushed
    return BatchSim(spec, n_envs, [scale_mass(spec.model, cfg.mass_scale)] * n_envs, pushes)


class Runner:
    """Runs jobs on one batch of simulators with agents built once each."""

    def __init__(self, envs: BatchSim, setups: dict[str, AgentSetup]):
        self.envs = envs
        self.setups: dict[str, AgentSetup] = {}
        for name, setup in setups.items():
            self.add(name, setup)

    def add(self, name: str, setup: AgentSetup) -> None:
        if isinstance(setup.agent, SimulatedSkillMPC):
            setup.agent.attach(self.envs)  # it plans from the episodes' exact physics states
        self.setups[name] = setup

    def run(self, job: Job, progress: bool, position: int | None = None) -> JobResult:
        agent = self.setups[job.agent].agent
        bar = tqdm(
            total=len(job.specs),
            desc=f"{job.agent} {job.task}",
            unit="episode",
            disable=not progress,
            position=position,
        )

        def on_wave(done: list[EpisodeResult]) -> None:
            bar.update(len(done))
            bar.set_postfix(success=f"{np.mean([r.success for r in done]):.2f}")

        started = time.perf_counter()
        try:
            results, calls = run_episodes(agent, self.envs, job.specs, job.run, on_wave)
        finally:
            bar.close()
        return JobResult(results, calls, time.perf_counter() - started)


def worker_count(params: Params, jobs: int) -> int:
    """`deploy.workers`, auto: one process per job up to the cores this process may use; one on
    CUDA (the jobs would share one device)."""
    workers = params.deploy.workers
    if workers == "auto":
        if resolve_device(params.deploy.device, "deploy.device").type == "cuda":
            return 1
        workers = len(os.sched_getaffinity(0))
    return max(1, min(workers, jobs))


def run_jobs(
    jobs: list[Job],
    local: Runner | None,
    params: Params,
    paths: Paths,
    workers: int,
    progress: bool,
) -> list[JobResult]:
    """Every job's results, in the order of `jobs`: here on `local` with one worker, else on
    `workers` spawned processes (`local` unused: None)."""
    if workers <= 1:
        assert local is not None, "one worker runs the jobs here, on `local`"
        return [local.run(job, progress) for job in jobs]
    context = multiprocessing.get_context("spawn")
    pool = context.Pool(workers, _start_worker, (params, paths))
    try:
        pending = [
            pool.apply_async(_worker_job, (job, progress, position))
            for position, job in enumerate(jobs)
        ]
        done = [p.get() for p in pending]
        pool.close()  # the workers exit on their own, their resources released
        pool.join()
        return done
    finally:
        pool.terminate()  # on an error or an interrupt: stop the others now


_WORKER: dict = {}  # a worker process's params, paths, segments, spec and Runner


def _start_worker(params: Params, paths: Paths) -> None:
    segments = load_segments(paths.existing(paths.segments(params.ingest.name)))
    spec = make_env_spec(segments.info.env_id, segments.info.env_kwargs)
    _WORKER.update(params=params, paths=paths, segments=segments, spec=spec)
    _WORKER["runner"] = Runner(make_simulators(params, segments, spec), {})


def _worker_job(job: Job, progress: bool, position: int) -> JobResult:
    params, runner = _WORKER["params"], _WORKER["runner"]
    with torch_threads(params.deploy.threads):
        if job.agent not in runner.setups:
            device = resolve_device(params.deploy.device, "deploy.device")
            setup = build_agent(
                job.agent, params, _WORKER["paths"], _WORKER["segments"], _WORKER["spec"], device
            )
            runner.add(job.agent, setup)
        return runner.run(job, progress, position)
