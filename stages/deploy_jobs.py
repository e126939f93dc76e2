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

import hashlib
import json
import logging
import multiprocessing
import os
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from pipeline import cpu_math
from pipeline.config import Params
from pipeline.devices import resolve_device, torch_threads
from pipeline.envs.batch import BatchSim
from pipeline.envs.disturbance import Pushes
from pipeline.envs.perturb import scale_mass
from pipeline.envs.spec import EnvSpec, make_env_spec
from pipeline.evaluation.episode_store import load_episodes, save_episodes
from pipeline.evaluation.episodes import EpisodeResult, PlanCall, RunConfig, run_episodes
from pipeline.evaluation.tasks import EpisodeSpec
from pipeline.paths import Paths
from pipeline.planning.simulated import SimulatedSkillMPC
from pipeline.segments import Segments, load_segments
from stages.deploy_agents import AgentSetup, build_agent

log = logging.getLogger(__name__)


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


def input_files(params: Params, paths: Paths, segments: Segments) -> list[Path]:
    """Every file an agent of this deploy may read: the segments' index, the trained models of
    the dataset, and the ant expert's actor that made the data."""
    name = params.ingest.name
    folders = [
        paths.model(name), paths.dynamics(name), paths.policy(name, "bc"),
        paths.policy(name, "gcbc"), paths.value(name),
    ]  # fmt: skip
    files = [paths.existing(paths.segments(name)) / "segments.json"]
    for folder in (paths.existing(f) for f in folders):
        if folder.is_dir():
            files += sorted(f for f in folder.rglob("*") if f.is_file())
    actor = ((segments.info.generator or {}).get("expert") or {}).get("path")
    if actor is not None and Path(actor).is_file():
        files.append(Path(actor))
    return files


class JobStore:
    """Finished jobs kept in `data/scratch/deploy/` until the stage's outputs are written, so
    that a killed deploy resumes from them (`pipeline.evaluation.episode_store`).

    A job's folder is keyed by everything its episodes depend on: the params (less
    `deploy.workers`, which only changes the wall time), the job's episodes and run config, the
    bytes of every input file, and the CPU arithmetic mode. Anything else changed, and the job
    runs again.
    """

    def __init__(self, params: Params, paths: Paths, inputs: list[Path]):
        digest = hashlib.sha256()
        for f in inputs:
            digest.update(str(f).encode() + b"\0" + hashlib.sha256(f.read_bytes()).digest())
        dumped = params.model_dump(mode="json")
        dumped["deploy"].pop("workers", None)
        self._base = {
            "params": dumped,
            "inputs": digest.hexdigest(),
            "cpu_math": cpu_math.mode(),
        }
        self._paths = paths
        self._name = params.ingest.name

    def folder(self, job: Job) -> Path:
        specs = [
            [s.task, s.index, s.seed, s.start.tolist(), s.goal.tolist(),
             None if s.physics is None else s.physics.tolist()]
            for s in job.specs
        ]  # fmt: skip
        what = {**self._base, "agent": job.agent, "task": job.task, "specs": specs,
                "run": asdict(job.run)}  # fmt: skip
        key = hashlib.sha256(json.dumps(what, sort_keys=True).encode()).hexdigest()[:16]
        return self._paths.scratch("deploy", f"{self._name}-{job.agent}-{job.task}-{key}")

    def load(self, job: Job) -> JobResult | None:
        stored = load_episodes(self.folder(job))
        return None if stored is None else JobResult(*stored)

    def save(self, job: Job, result: JobResult) -> None:
        save_episodes(self.folder(job), result.results, result.calls, result.seconds)

    def clear(self, jobs: list[Job]) -> None:
        """Delete the jobs' folders (once the outputs made from them are written)."""
        for job in jobs:
            shutil.rmtree(self.folder(job), ignore_errors=True)


def run_jobs(
    jobs: list[Job],
    local: Runner | None,
    params: Params,
    paths: Paths,
    workers: int,
    progress: bool,
    store: JobStore | None = None,
) -> list[JobResult]:
    """Every job's results, in the order of `jobs`: here on `local` with one worker, else on
    `workers` spawned processes (`local` unused: None). With a `store`, the jobs it holds are
    read back instead of run, and each job is saved to it as soon as it ends."""
    done: dict[int, JobResult] = {}
    if store is not None:
        for i, job in enumerate(jobs):
            if (kept := store.load(job)) is not None:
                done[i] = kept
        if done:
            log.info("resuming: %d of %d jobs read back from %s", len(done), len(jobs),
                     paths.scratch("deploy", ""))  # fmt: skip
    todo = [i for i in range(len(jobs)) if i not in done]

    def finished(i: int, result: JobResult) -> None:
        done[i] = result
        if store is not None:
            store.save(jobs[i], result)

    if todo and workers <= 1:
        assert local is not None, "one worker runs the jobs here, on `local`"
        for i in todo:
            finished(i, local.run(jobs[i], progress))
    elif todo:
        context = multiprocessing.get_context("spawn")
        pool = context.Pool(min(workers, len(todo)), _start_worker, (params, paths))
        try:
            tasks = [(i, jobs[i], progress, position) for position, i in enumerate(todo)]
            for i, result in pool.imap_unordered(_worker_job, tasks):
                finished(i, result)  # saved as each ends, in the order they end
            pool.close()  # the workers exit on their own, their resources released
            pool.join()
        finally:
            pool.terminate()  # on an error or an interrupt: stop the others now
    return [done[i] for i in range(len(jobs))]


_WORKER: dict = {}  # a worker process's params, paths, segments, spec and Runner


def _start_worker(params: Params, paths: Paths) -> None:
    segments = load_segments(paths.existing(paths.segments(params.ingest.name)))
    spec = make_env_spec(segments.info.env_id, segments.info.env_kwargs)
    _WORKER.update(params=params, paths=paths, segments=segments, spec=spec)
    _WORKER["runner"] = Runner(make_simulators(params, segments, spec), {})


def _worker_job(task: tuple[int, Job, bool, int]) -> tuple[int, JobResult]:
    index, job, progress, position = task
    params, runner = _WORKER["params"], _WORKER["runner"]
    with torch_threads(params.deploy.threads):
        if job.agent not in runner.setups:
            device = resolve_device(params.deploy.device, "deploy.device")
            setup = build_agent(
                job.agent, params, _WORKER["paths"], _WORKER["segments"], _WORKER["spec"], device
            )
            runner.add(job.agent, setup)
        return index, runner.run(job, progress, position)
