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
"""

from __future__ import annotations

import hashlib
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from pipeline.config import DeployParams, Params
from pipeline.devices import resolve_device, torch_threads
from pipeline.envs.ant_expert import load_actor
from pipeline.envs.batch import BatchSim
from pipeline.envs.disturbance import Pushes
from pipeline.envs.expert import ExpertConfig
from pipeline.envs.kitchen import KitchenSpec
from pipeline.envs.manipspace import ManipSpaceSpec
from pipeline.envs.ogbench import OGBenchMazeSpec
from pipeline.envs.ogbench_oracle import POINT_NOISE, OGBenchOracleAgent
from pipeline.envs.perturb import scale_mass
from pipeline.envs.spec import EnvSpec, make_env_spec
from pipeline.errors import UserError
from pipeline.evaluation.compat import check_model_dims, check_same_environment
from pipeline.evaluation.episodes import EpisodeResult, PlanCall, RunConfig, run_episodes
from pipeline.evaluation.flops import replan_flops
from pipeline.evaluation.goals import GoalRule
from pipeline.evaluation.report import compare_planners
from pipeline.evaluation.stats import latency_summary, optimism_gap, task_summary
from pipeline.evaluation.tasks import (
    OGBENCH_PREFIX,
    EpisodeSpec,
    MazeTasks,
    check_kitchen_tasks,
    check_manipulation_tasks,
    check_task,
    kitchen_episodes,
    manipulation_episodes,
    train_locations,
)
from pipeline.model.checkpoint import load_dynamics, load_model, load_policy, skill_horizon
from pipeline.paths import Paths
from pipeline.planning.agents import Agent, ExpertAgent, PolicyAgent
from pipeline.planning.llp import LowLevelMPC, LowLevelPlanner
from pipeline.planning.mpc import SkillMPC
from pipeline.planning.settings import llp_config, planner_config
from pipeline.planning.simulated import SimulatedRollout, SimulatedSkillMPC, SimulatorPlanner
from pipeline.planning.skills import SkillPlanner
from pipeline.planning.subgoals import StuckWatch, SubgoalGraph
from pipeline.planning.subtasks import ObjectSubtasks
from pipeline.segments import Segments, load_segments
from pipeline.value.network import load_value
from pipeline.viz.deploy import recording_name, write_episode_recording
from pipeline.viz.kitchen import write_kitchen_episode_recording
from pipeline.viz.manip import write_manip_episode_recording, write_manip_overview
from pipeline.viz.overview import write_overview
from stages.report import report_files, split_timings, write_report, write_timings

log = logging.getLogger(__name__)

# Environments whose goals are object configurations, not places in a maze.
OBJECT_GOALS = (ManipSpaceSpec, KitchenSpec)


@dataclass
class AgentSetup:
    """An agent ready to run: how often it replans and what the report says about it."""

    agent: Agent
    replan_every: int | None
    about: dict[str, Any] = field(default_factory=dict)
    plan_state_steps: int | None = None  # environment steps per predicted plan state
    count_flops: bool = True  # the report counts a replan's matrix-product FLOPs


def _check(meta: dict, segments: Segments, spec: EnvSpec, dims: tuple[int, int], what: str):
    check_same_environment(segments.info, meta, what)
    check_model_dims(*dims, spec, what)


def _skill_model(params: Params, paths: Paths, segments: Segments, spec: EnvSpec, device):
    """The skill model of `data/models/<name>/`, its metadata and folder, checked against the
    segments and the environment."""
    cfg, name = params.deploy, params.ingest.name
    model_dir = paths.existing(paths.model(name))
    model, meta = load_model(model_dir, device=device)
    what = f"the model in {model_dir}"
    _check(meta, segments, spec, (model.config.state_dim, model.config.action_dim), what)
    if segments.info.name != meta.get("dataset"):
        raise UserError(
            f"{paths.segments(name)} holds dataset '{segments.info.name}' but the model was "
            f"trained on '{meta.get('dataset')}'; re-run `oposm train`"
        )
    if cfg.planner.kernel == "triton" and device.type != "cuda":
        raise UserError(
            f"deploy.planner.kernel: triton runs on a CUDA GPU, but deploy.device is "
            f"{device.type}; set deploy.planner.kernel=torch"
        )
    return model, meta, model_dir


def _oposm(params: Params, paths: Paths, segments: Segments, spec: EnvSpec, device) -> AgentSetup:
    cfg = params.deploy
    model, meta, model_dir = _skill_model(params, paths, segments, spec, device)
    planner = SkillPlanner(model, planner_config(cfg.planner))
    subgoals = None
    if cfg.subgoals.enabled and isinstance(spec, OBJECT_GOALS):
        raise UserError(
            f"deploy.subgoals: the subgoal graph is a maze's (cells of the plane); {spec.env_id} "
            "plans to its object goals directly: set deploy.subgoals.enabled=false"
        )
    if cfg.subgoals.enabled:
        sub = cfg.subgoals
        subgoals = SubgoalGraph.from_segments(
            segments, spec.goal_dims, sub.cell, sub.reach, device, line_of_sight=sub.line_of_sight
        )
        log.info("subgoal graph: %d nodes (cells of %g m), reach %d skills%s%s",
                 len(subgoals.nodes), sub.cell, sub.reach,
                 ", line of sight" if sub.line_of_sight else "",
                 f", once {sub.patience} replans bring no {sub.progress} m closer"
                 if sub.patience else "")  # fmt: skip
    stuck = None
    if subgoals is not None and cfg.subgoals.patience is not None:
        stuck = StuckWatch(cfg.subgoals.patience, cfg.subgoals.progress)
    subtasks = None
    if cfg.object_subtasks:
        if not isinstance(spec, ManipSpaceSpec):
            raise UserError(
                f"deploy.object_subtasks plans an OGBench manipulation goal one object at a "
                f"time; {spec.env_id} has no such goal: set deploy.object_subtasks=false"
            )
        subtasks = ObjectSubtasks(spec.goal_objects, spec.goal_scale)
        log.info("one object at a time: %d objects in the goal", len(subtasks.objects))
    skill_steps = skill_horizon(meta, model_dir)
    value, value_info = _value(params, paths, segments, spec, device, skill_steps)
    return AgentSetup(
        SkillMPC(
            model,
            planner,
            cfg.sample_actions,
            spec.goal_dims,
            subgoals,
            getattr(spec, "fallen", None),
            getattr(spec, "goal_scale", None),
            value,
            subtasks,
            stuck,
        ),  # fmt: skip
        _tau(cfg.replan_every, skill_horizon(meta, model_dir)),
        {"model": str(model_dir), "model_step": meta.get("step"), **cfg.planner.model_dump()}
        | (
            {f"subgoals_{k}": v for k, v in _subgoal_settings(cfg.subgoals).items()}
            if subgoals
            else {}
        )
        | ({"object_subtasks": True} if subtasks else {})
        | value_info,
        plan_state_steps=skill_horizon(meta, model_dir),  # a skill
    )


def _subgoal_settings(sub) -> dict:
    """`deploy.subgoals` as the report names it; `patience` and `progress` only when the graph
    waits for a stuck episode (reports from before they existed read the same)."""
    settings = sub.model_dump()
    if sub.patience is None:
        del settings["patience"], settings["progress"]
    return settings


def _tau(replan_every: int | None, skill_steps: int) -> int:
    """Steps of a skill run before the next plan: `deploy.replan_every`, at most the skill's
    length T (a skill is not run beyond the steps it was trained on); None: T."""
    if replan_every is not None and replan_every > skill_steps:
        log.info("deploy.replan_every %d > the skills' %d steps: replanning every %d",
                 replan_every, skill_steps, skill_steps)  # fmt: skip
    return min(replan_every or skill_steps, skill_steps)


def _value(params: Params, paths: Paths, segments: Segments, spec: EnvSpec, device, skill_steps):
    """The learned steps-to-go for the planner's cost (`value.weight > 0`), with what the
    report says of it; (None, {}) for the paper's cost."""
    weight = params.value.weight
    if not weight:
        return None, {}
    value_dir = paths.existing(paths.value(params.ingest.name))
    value, meta = load_value(value_dir, device=device)
    c = value.config
    what = f"the value in {value_dir}"
    _check(meta, segments, spec, (c.state_dim, segments.info.action_dim), what)
    if c.goal_dims != tuple(spec.goal_dims):
        raise UserError(
            f"the value in {value_dir} takes goals in state dims {list(c.goal_dims)}, "
            f"{spec.env_id} gives {list(spec.goal_dims)}; re-run `oposm value`"
        )
    info = {"value": str(value_dir), "value_weight": weight, "value_skill_steps": skill_steps}
    return (value.steps_to_go, weight, skill_steps), info


def _llp(params: Params, paths: Paths, segments: Segments, spec: EnvSpec, device) -> AgentSetup:
    cfg, name = params.deploy.llp, params.ingest.name
    dyn_dir = paths.existing(paths.dynamics(name))
    dynamics, dyn_meta = load_dynamics(dyn_dir, device=device)
    d = dynamics.config
    _check(dyn_meta, segments, spec, (d.state_dim, d.action_dim), f"the model in {dyn_dir}")
    bc_dir = paths.existing(paths.policy(name, "bc"))
    policy, bc_meta = load_policy(bc_dir, "bc", device=device)
    p = policy.config
    _check(bc_meta, segments, spec, (p.state_dim, p.action_dim), f"the policy in {bc_dir}")
    planner = LowLevelPlanner(policy, dynamics, llp_config(cfg))
    return AgentSetup(
        LowLevelMPC(planner, spec.goal_dims, getattr(spec, "goal_scale", None)),
        cfg.execute,
        {"dynamics": str(dyn_dir), "bc": str(bc_dir), **cfg.model_dump()},
        plan_state_steps=1,  # an action
    )


def _gcbc(params: Params, paths: Paths, segments: Segments, spec: EnvSpec, device) -> AgentSetup:
    policy_dir = paths.existing(paths.policy(params.ingest.name, "gcbc"))
    policy, meta = load_policy(policy_dir, "gcbc", device=device)
    p = policy.config
    _check(meta, segments, spec, (p.state_dim, p.action_dim), f"the policy in {policy_dir}")
    if p.goal_dims != tuple(spec.goal_dims):
        raise UserError(
            f"the policy in {policy_dir} takes goals in state dims {list(p.goal_dims)}, "
            f"{spec.env_id} gives {list(spec.goal_dims)}; re-run `oposm gcbc`"
        )
    sample = params.deploy.gcbc.sample_actions
    return AgentSetup(
        PolicyAgent(policy, sample), None, {"policy": str(policy_dir), "sample_actions": sample}
    )


def _ogbench_oracle(params: Params, segments: Segments, spec: EnvSpec) -> AgentSetup:
    """OGBench's data-generating BFS oracle, with the dataset's noise (or deploy.expert's)."""
    noise = params.deploy.expert.action_noise
    recorded = (segments.info.generator or {}).get("noise")
    if noise is None:
        noise = POINT_NOISE if recorded is None else float(recorded)
    source = "deploy.expert" if params.deploy.expert.action_noise is not None else "the dataset's"
    info = {"config": "OGBench's BFS oracle (generate_locomaze.py)", "noise": noise, "from": source}
    actor = None
    if spec.loco == "ant":  # the actor that made the data walks the oracle's directions
        made_with = (segments.info.generator or {}).get("expert") or {}
        path = made_with.get("path", "experts/ant/actor.safetensors")
        actor = load_actor(path)
        if (actor.spec.obs_dim, actor.spec.action_dim) != (spec.state_dim, spec.action_dim):
            raise UserError(f"{path} does not fit {spec.env_id}'s ant; re-run `oposm ingest`")
        digest = hashlib.sha256(Path(path).read_bytes()).hexdigest()
        info |= {"actor": str(path), "actor_sha256": digest}
        if made_with.get("sha256") not in (None, digest):
            log.warning("%s is not the actor that made the data (its sha256 differs)", path)
    return AgentSetup(OGBenchOracleAgent(spec.env_id, noise, actor=actor), None, info)


def _expert(params: Params, paths: Paths, segments: Segments, spec: EnvSpec, device) -> AgentSetup:
    if isinstance(spec, KitchenSpec):
        raise UserError(
            f"no expert agent for {spec.env_id}: its data are human demonstrations, with no "
            "controller to run; use oposm, llp or gcbc"
        )
    if isinstance(spec, ManipSpaceSpec):
        raise UserError(
            f"no expert agent for {spec.env_id}: OGBench's manipulation oracles pursue the "
            "subtasks the env draws, not an evaluation task's goal; use oposm, llp or gcbc"
        )
    if isinstance(spec, OGBenchMazeSpec):
        return _ogbench_oracle(params, segments, spec)
    recorded = (segments.info.generator or {}).get("expert")
    config = ExpertConfig(**recorded) if recorded else ExpertConfig()
    if params.deploy.expert.action_noise is not None:
        config.action_noise = params.deploy.expert.action_noise
    source = "the dataset's" if recorded else "D4RL's defaults (the dataset records none)"
    return AgentSetup(
        ExpertAgent(spec.layout, config), None, {"config": source, **config.to_dict()}
    )


def _oposm_sim(
    params: Params, paths: Paths, segments: Segments, spec: EnvSpec, device
) -> AgentSetup:
    """OPOSM's CEM over the same skills, each candidate executed in a copy of the deploy
    environment instead of predicted by the TAWM (`pipeline.planning.simulated`)."""
    cfg = params.deploy
    model, meta, model_dir = _skill_model(params, paths, segments, spec, device)
    if cfg.subgoals.enabled:
        raise UserError(
            "agent oposm_sim plans to the goal itself: set deploy.subgoals.enabled=false"
        )
    config = planner_config(cfg.planner)
    steps = skill_horizon(meta, model_dir)
    rollout = SimulatedRollout(
        model, spec, scale_mass(spec.model, cfg.mass_scale), config.cem.candidates, steps
    )
    agent = SimulatedSkillMPC(
        model, SimulatorPlanner(model, config, rollout), cfg.sample_actions, spec.goal_dims,
        None, getattr(spec, "fallen", None), getattr(spec, "goal_scale", None),
    )  # fmt: skip
    return AgentSetup(
        agent,
        _tau(cfg.replan_every, steps),
        {
            "model": str(model_dir),
            "model_step": meta.get("step"),
            "scored_in": "simulator",
            **cfg.planner.model_dump(),
        },  # fmt: skip
        plan_state_steps=steps,
        count_flops=False,  # the cost of a plan is simulator steps, not matrix products
    )


BUILDERS = {
    "oposm": _oposm, "oposm_sim": _oposm_sim, "llp": _llp, "gcbc": _gcbc, "expert": _expert,
}  # fmt: skip


def build_agent(
    name: str, params: Params, paths: Paths, segments: Segments, spec: EnvSpec, device
) -> AgentSetup:
    """Load what agent `name` needs and build it; a missing model names the stage to run.

    Raises:
        UserError: an unknown agent (the message lists the valid ones), or its models are
            missing, corrupt or from another environment.
    """
    if name not in BUILDERS:
        raise UserError(f"unknown agent {name!r}; use one of: {', '.join(BUILDERS)}")
    try:
        return BUILDERS[name](params, paths, segments, spec, device)
    except UserError as exc:
        raise UserError(f"agent {name}: {exc}") from exc


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


def _run_agent(
    setup: AgentSetup,
    envs: BatchSim,
    specs: dict[str, list[EpisodeSpec]],
    run_cfg: RunConfig,
    record: Any,
    progress: bool,
) -> tuple[dict[str, list[EpisodeResult]], list[PlanCall]]:
    """All tasks' episodes of one agent; `record(results)` after each wave."""
    results: dict[str, list[EpisodeResult]] = {}
    calls: list[PlanCall] = []
    name = setup.agent.name
    for task, task_specs in specs.items():
        bar = tqdm(
            total=len(task_specs), desc=f"{name} {task}", unit="episode", disable=not progress
        )

        def on_wave(done: list[EpisodeResult], bar=bar) -> None:
            record(done)
            bar.update(len(done))
            bar.set_postfix(success=f"{np.mean([r.success for r in done]):.2f}")

        results[task], task_calls = run_episodes(setup.agent, envs, task_specs, run_cfg, on_wave)
        calls += task_calls
        bar.close()
    return results, calls


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
    n_envs = min(cfg.num_envs, cfg.episodes)
    pushes = Pushes.of_dataset(segments.info.generator)  # the data's, if it was pushed
    envs = BatchSim(spec, n_envs, [scale_mass(spec.model, cfg.mass_scale)] * n_envs, pushes)
    for setup in setups.values():
        if isinstance(setup.agent, SimulatedSkillMPC):
            setup.agent.attach(envs)  # it plans from the episodes' exact physics states
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

    by_agent: dict[str, Any] = {}
    rows: list[dict] = []
    episodes: list[EpisodeResult] = []  # every agent's, for the run overview
    recorded = 0
    with paths.staged(files, [recordings]) as out:  # published together, or none
        tmp = out.folder(recordings)
        for agent_name, setup in setups.items():
            run_cfg = RunConfig(max_steps, setup.replan_every, cfg.success_radius)

            def record(done: list[EpisodeResult]) -> None:
                nonlocal recorded
                recorded += _record(done, cfg, spec, tmp, cfg.success_radius)

            flops = None
            if setup.replan_every is not None and setup.count_flops:  # on the first episode
                first = next(iter(specs.values()))[0]
                flops = replan_flops(setup.agent, first.start, first.goal, first.seed)
            agent_started = time.perf_counter()
            results, calls = _run_agent(setup, envs, specs, run_cfg, record, progress)
            by_agent[agent_name] = {
                **{task: task_summary(r, spec.dt, limits) for task, r in results.items()},
                **_ogbench_overall(results, spec.dt, limits),
                "replan_every": setup.replan_every,
                "flops_per_replan": flops,
                "planning": latency_summary(calls),
                "optimism_gap": _optimism(setup, results, spec),
                "wall_s": time.perf_counter() - agent_started,
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
            "disturbance": pushes.to_dict(),
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
    return report
